"""Frame sources that know nothing of the bus: a video file or a folder of images.

Each yields (index, BGR image (H,W,3) uint8) and says its nominal frame rate; errors that a
user can cause (missing file, corrupt video, empty folder) raise ValueError naming the cause.
"""
from __future__ import annotations

import os
from pathlib import Path

# FFmpeg's own log lines ("moov atom not found") would come before our one clear error line
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
import cv2  # noqa: E402  (reads the variable above when it first opens a video)
import numpy as np

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff"}
MISSING_FRAMES_SLACK = 0.05   # share of the container's frame count a video may fall short of
VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".flv"}


class VideoFrames:
    """Frames of a video file, decoded by OpenCV (which also applies the container's rotation tag)."""

    def __init__(self, path: str | Path, start_s: float = 0.0):
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"video {self.path}: no such file")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise ValueError(f"video {self.path}: cannot be opened (corrupt, or not a video OpenCV can decode)")
        self.fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
        if not 1.0 <= self.fps <= 1000.0:
            self.fps = 30.0
        self.frame_count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        cap.release()
        self.start_frame = int(round(start_s * self.fps))

    def __iter__(self):
        cap = cv2.VideoCapture(str(self.path))
        try:
            i = 0
            while i < self.start_frame and cap.grab():
                i += 1
            n = 0
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                yield self.start_frame + n, frame
                n += 1
            if n == 0:
                raise ValueError(f"video {self.path}: no frame could be decoded"
                                 + (f" after {self.start_frame} skipped" if self.start_frame else
                                    " (corrupt or unsupported)"))
            end = self.start_frame + n
            # OpenCV ends a video at its first undecodable packet, as if it were the end: a file
            # corrupt in the middle would otherwise replay part of itself and exit 0. The
            # container's count is an estimate for some formats (duration x fps), hence the slack.
            if self.frame_count and self.frame_count - end > max(2, MISSING_FRAMES_SLACK * self.frame_count):
                raise ValueError(f"video {self.path}: decoding stopped at frame {end} of {self.frame_count} "
                                 f"(the file is corrupt or cut short there)")
        finally:
            cap.release()


class ImageFolderFrames:
    """Images of a folder and its subfolders, sorted by path (a dataset's per-person folders
    read as they are); an unreadable file is an error (a camera stream must not skip
    silently), or with skip_unreadable a (i, None) for the caller to report (a folder of
    photos: one bad file must not cost the others)."""

    def __init__(self, path: str | Path, fps: float = 30.0, start_s: float = 0.0, skip_unreadable: bool = False):
        self.path = Path(path)
        self.skip_unreadable = skip_unreadable
        self.files = sorted(p for p in self.path.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        if not self.files:
            raise ValueError(f"image folder {self.path}: no images ({', '.join(sorted(IMAGE_SUFFIXES))}), "
                             f"subfolders included")
        self.fps = fps
        self.frame_count = len(self.files)
        self.start_frame = int(round(start_s * fps))

    def __iter__(self):
        for i, p in enumerate(self.files[self.start_frame:], self.start_frame):
            frame = cv2.imread(str(p), cv2.IMREAD_COLOR)   # grey, alpha, 16-bit: all as 8-bit BGR
            if frame is None and not self.skip_unreadable:
                raise ValueError(f"image {p}: cannot be decoded")
            yield i, frame


def open_frames(path: str | Path, fps: float | None = None, start_s: float = 0.0):
    """A VideoFrames or ImageFolderFrames for `path`, chosen by what it is."""
    path = Path(path)
    if path.is_dir():
        return ImageFolderFrames(path, fps or 30.0, start_s)
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise ValueError(f"{path}: a single image; give the folder that holds it")
    src = VideoFrames(path, start_s)
    if fps:
        src.fps = fps
    return src


def read_video(path: str | Path) -> list[np.ndarray]:
    """Every frame (H,W,3) BGR uint8 of a video file, with VideoFrames' checks (a file that
    cannot be opened or stops decoding early is a ValueError)."""
    return [frame for _, frame in VideoFrames(path)]


def image_message(frame: np.ndarray, jpeg_quality: int | None = None) -> dict:
    """The Image body (without header) of one BGR frame (H,W,3) uint8: raw bgr8, or with
    jpeg_quality (1-100) a JPEG of it (about 1/20 of the bytes at 90 on camera frames)."""
    h, w = frame.shape[:2]
    if jpeg_quality is None:
        return {"encoding": "bgr8", "width": w, "height": h, "data": np.ascontiguousarray(frame)}
    ok, jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise ValueError(f"could not JPEG-encode a {w}x{h} frame")
    return {"encoding": "jpeg", "width": w, "height": h, "data": jpeg.reshape(-1)}


def compressed(image_msg: dict, jpeg_quality: int) -> dict:
    """An Image message (with its header) as JPEG; one already JPEG comes back as it is."""
    if image_msg["encoding"] == "jpeg":
        return image_msg
    return {**image_msg, **image_message(frame_bgr(image_msg), jpeg_quality)}


def frame_bgr(image_msg):
    """BGR (H,W,3) uint8 of an Image message (bgr8, rgb8, mono8 or jpeg)."""
    data, encoding = np.asarray(image_msg["data"]), image_msg["encoding"]
    if encoding == "bgr8":
        return data
    if encoding == "rgb8":
        return np.ascontiguousarray(data[..., ::-1])
    if encoding == "mono8":
        return cv2.cvtColor(data, cv2.COLOR_GRAY2BGR)
    frame = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if frame is None:
        raise ValueError("undecodable JPEG image")
    return frame

"""`camera`: a webcam (anything OpenCV's VideoCapture opens) as `/camera/image` + `/camera/info`.

Parameters (PARAMS):
- device: an int index (/dev/videoN), or a path or URL string (a string of digits counts
  as an index). A video file works too: it plays once at `fps` and then ends the stream
  normally (exit 0), which makes the node testable without a camera.
- width, height, fps: the capture format asked for. A camera may pick another; the node
  publishes what it delivers (logged once) and scales K to it.
- calibration: a calibration file (formats: handmocap.perception.camera_info); without one K comes from
  a 60 degree horizontal field of view (source 'default-fov').
- frame_id: header frame id of both topics.
- jpeg_quality: null publishes raw bgr8 frames; 1-100 JPEG frames of that quality (a graph
  spread over hosts sends about 1/20 of the bytes; the detector decodes them).
- mirror: flip frames left-right (selfie view). K and the distortion are mirrored with them,
  so downstream sees a consistent pinhole camera of the mirrored scene: a real left hand
  then appears, and is reported, as a right hand.

Output: `/camera/image` (Image, bgr8, data (H,W,3) uint8) and `/camera/info` (CameraInfo).
CameraInfo is repeated with every frame, published just before that frame's image with the
same stamp: a late subscriber has K with its first image and can pair the two by stamp
(latched semantics by repetition; it costs about 300 bytes a frame).

Stamps: CLOCK_REALTIME taken when `grab()` returns, before decoding: the closest to capture
time that OpenCV exposes for every backend.

Failures: a device that can't be opened or yields no first frame is one error line and exit
2; a live camera that stops delivering frames for FAIL_AFTER_S (unplugged) is one error line
and exit 2 too.
"""
from __future__ import annotations

import os
import time
from collections.abc import Iterator

import cv2
import numpy as np

from handmocap.perception.camera_info import Intrinsics, camera_info_message, check_calibration_param, intrinsics_for_frames
from handmocap.runtime.frames import image_message
from handmocap.runtime.node import Node, check_bool_param, check_jpeg_param, check_number_param, run

PARAMS = {"device": 0, "width": 640, "height": 480, "fps": 30, "calibration": None, "frame_id": "camera",
          "mirror": False, "jpeg_quality": None}

FAIL_AFTER_S = 2.0        # a live camera without a frame this long has failed
FIRST_FRAME_TIMEOUT_S = 5.0


def parse_device(device) -> int | str:
    """An int index for ints and digit strings, else the path/URL string as given."""
    if isinstance(device, bool) or not isinstance(device, (int, str)):
        raise ValueError(f"camera param device: expected an index or a path/URL, got {device!r}")
    if isinstance(device, str) and device.strip().isdigit():
        return int(device)
    return device


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param): the
    device reads as an index or a path/URL, the format is numbers, the calibration file reads.
    Whether the camera opens is known only when the node opens it."""
    parse_device(params.get("device", PARAMS["device"]))
    for key in ("width", "height"):
        check_number_param("camera", key, params.get(key, PARAMS[key]), minimum=1, integer=True)
    check_number_param("camera", "fps", params.get("fps", PARAMS["fps"]), positive=True)
    check_bool_param("camera", "mirror", params.get("mirror", PARAMS["mirror"]))
    check_jpeg_param("camera", params.get("jpeg_quality"))
    check_calibration_param("camera", params.get("calibration"))


def is_file(device: int | str) -> bool:
    """A regular file (a recorded video), as opposed to a live camera or a stream URL."""
    return isinstance(device, str) and os.path.isfile(device)


def open_camera(device: int | str, width: int, height: int, fps: float) -> tuple[cv2.VideoCapture, int, np.ndarray]:
    """Open `device`, ask for width×height@fps (live cameras only) and read the first frame.

    Returns the capture, the first frame's stamp (ns) and the frame (H,W,3) uint8 BGR. Raises RuntimeError naming
    the device and the likely cause when it can't be opened or yields no frame."""
    if isinstance(device, int) and not os.path.exists(f"/dev/video{device}") and os.path.isdir("/dev"):
        raise RuntimeError(f"camera {device}: /dev/video{device} does not exist (no camera plugged in, or "
                           f"another index; list them with `v4l2-ctl --list-devices`)")
    if isinstance(device, str) and "://" not in device and not os.path.exists(device):
        raise RuntimeError(f"camera {device!r}: no such device or file (camera unplugged, or a wrong path)")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)   # our error says it once
    try:
        cap = cv2.VideoCapture(device)
        if not cap.isOpened():
            raise RuntimeError(f"camera {device!r} can't be opened (in use by another program, no permission "
                               f"to the device, or not a video source OpenCV can read)")
        if not is_file(device):
            # MJPG first: many USB cameras do 720p and up at full rate only compressed (V4L2
            # keeps its current format when the camera can't)
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*"MJPG"))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            cap.set(cv2.CAP_PROP_FPS, fps)
        deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
        while True:
            ok, frame = cap.read()
            if ok and frame is not None:
                return cap, time.time_ns(), as_bgr(frame)
            if is_file(device) or time.monotonic() > deadline:
                cap.release()
                raise RuntimeError(f"camera {device!r} opened but delivered no frame (an empty or unreadable "
                                   f"video, a camera in use, or a format {width}x{height}@{fps} it can't do)")
            time.sleep(0.05)
    finally:
        cv2.utils.logging.setLogLevel(level)


def as_bgr(frame: np.ndarray) -> np.ndarray:
    """A frame as (H,W,3) uint8 BGR (some backends deliver gray (H,W) or BGRA (H,W,4))."""
    if frame.ndim == 2:
        return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    if frame.shape[2] == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    return frame


def read_frames(cap, live: bool, fps: float, fail_after_s: float = FAIL_AFTER_S) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (stamp_ns, frame (H,W,3) uint8 BGR) from an opened capture (anything with
    `grab()`/`retrieve()`). A file ends the iteration at its end and is paced at `fps`; a
    live source that yields nothing for `fail_after_s` raises RuntimeError."""
    period = 1.0 / fps if fps and fps > 0 else 0.0
    next_due = time.monotonic()
    failing_since = None
    while True:
        if not live and period:
            delay = next_due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            next_due = max(next_due + period, time.monotonic() - period)
        grabbed = cap.grab()
        stamp_ns = time.time_ns()
        ok, frame = cap.retrieve() if grabbed else (False, None)
        if ok and frame is not None:
            failing_since = None
            yield stamp_ns, as_bgr(frame)
            continue
        if not live:
            return
        now = time.monotonic()
        failing_since = failing_since or now
        if now - failing_since > fail_after_s:
            raise RuntimeError(f"camera stopped delivering frames for {fail_after_s:g} s (unplugged, or taken by "
                               f"another program)")
        time.sleep(0.01)


def mirrored(intr: Intrinsics, width: int) -> Intrinsics:
    """Intrinsics of the left-right flipped image: u' = (W-1) - u, i.e. the camera of the
    mirrored scene x' = -x. The principal point and skew flip; of OpenCV's distortion
    coefficients the odd-in-x ones flip sign (p2, s1, s2, tau_y)."""
    K = intr.K.copy()
    K[0, 2] = (width - 1) - K[0, 2]
    K[0, 1] = -K[0, 1]
    d = intr.distortion.copy()
    for i in (3, 8, 9, 13):   # p2, s1, s2, tau_y
        if i < d.size:
            d[i] = -d[i]
    return Intrinsics(K, d, intr.size, intr.source)


def main() -> None:
    node = Node("camera", params=PARAMS)
    p = node.params
    device = parse_device(p["device"])
    cap, stamp_ns, first = open_camera(device, p["width"], p["height"], p["fps"])
    try:
        size = first.shape[1::-1]
        info = _camera_info(size, p, node)   # a bad calibration fails here, before any topic exists
        node.advertise("/camera/info", "CameraInfo")
        node.advertise("/camera/image", "Image")
        frames = read_frames(cap, live=not is_file(device), fps=p["fps"])
        for stamp_ns, frame in _chain_first(stamp_ns, first, frames):
            if not node.ok():
                break
            if frame.shape[1::-1] != size:   # the camera renegotiated its format
                size = frame.shape[1::-1]
                info = _camera_info(size, p, node)
            if p["mirror"]:
                frame = cv2.flip(frame, 1)
            node.publish("/camera/info", info, stamp_ns=stamp_ns, frame_id=p["frame_id"])
            node.publish("/camera/image", image_message(frame, p["jpeg_quality"]), stamp_ns=stamp_ns, frame_id=p["frame_id"])
    finally:
        cap.release()
        node.close()


def _chain_first(stamp_ns: int, first: np.ndarray, rest: Iterator) -> Iterator[tuple[int, np.ndarray]]:
    yield stamp_ns, first
    yield from rest


def _camera_info(size: tuple[int, int], p: dict, node: Node) -> dict:
    w, h = size
    if (w, h) != (p["width"], p["height"]) and not is_file(parse_device(p["device"])):
        node.log.info("camera delivers %dx%d (asked for %dx%d)", w, h, p["width"], p["height"])
    intr = intrinsics_for_frames(w, h, p["calibration"])
    if intr.source == "default-fov":
        node.log.info("no calibration: K from a default field of view, fx=fy=%.1f px", intr.K[0, 0])
    if p["mirror"]:
        intr = mirrored(intr, w)
    return camera_info_message(intr.K, intr.distortion, w, h, intr.source)


if __name__ == "__main__":
    run(main)

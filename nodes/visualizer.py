"""visualizer: annotated frames. /camera/image (+ /camera/info, /hand/keypoints, /hand/pose)
-> /viz/image, and optionally an MP4.

A thin loop over handmocap.runtime.frame_sync.FrameSync (pairs each frame with the pose and keypoints
of its stamp; in a video, a frame the detector skipped gets the previous frame's) and handmocap.perception.overlay.Overlay (the posed hand mesh of every hand, rendered once
per frame with the camera's K and alpha-blended; the 2D skeleton with per-finger colours;
handedness, mean joint confidence and track id; a side-view inset). A frame whose pose never comes (no hand
pipeline, or the detector skipped it and no earlier pose is held) is drawn without overlay; a
pose with no hands too.

Params:
- video: an MP4 path to write (mp4v; parent folders are made, an existing file is replaced).
  Every frame is written, in order: the subscriptions are then keep-all, so on a live camera the
  visualizer must keep up. The file is finished properly at the end of the stream and on
  SIGINT/SIGTERM.
- fps: frame rate written into the MP4 (the Image stream does not carry one).
- every_frame: keep-all subscriptions and every frame drawn (default: true when `video` is
  set); false: latest-only, a live view that never lags (frames the detector skipped are
  not drawn).
- publish: publish /viz/image (Image, bgr8).
- mesh, alpha, side, joints3d: see handmocap.perception.overlay.Overlay (mesh:=false needs no OpenGL).
- model: hand model path (default bundled); timeout: seconds a frame waits for its pose
  while no pose arrives at all (default 0.5 live, 5 with every_frame).
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception import camera_info
from handmocap.runtime.frame_sync import FrameSync
from handmocap.runtime.frames import frame_bgr, image_message
from handmocap.perception.hand_model import HandModel
from handmocap.runtime.node import Node, check_bool_param, check_file_param, check_number_param, run
from handmocap.perception.overlay import Overlay

PARAMS = {"video": None, "fps": 30.0, "every_frame": None, "publish": True, "mesh": True, "alpha": 0.6,
          "side": 0.33, "joints3d": True, "model": None, "timeout": None}
TICK_S = 0.05           # wake-up period when nothing arrives: waiting frames may have expired
SHUTDOWN_DRAW_S = 2.0   # on SIGINT/SIGTERM, frames still held are drawn this long, then written as they are


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    check_file_param("visualizer", "model", params.get("model"))
    check_number_param("visualizer", "fps", params.get("fps", PARAMS["fps"]), positive=True)
    for key in ("publish", "mesh", "joints3d"):
        check_bool_param("visualizer", key, params.get(key, PARAMS[key]))
    if params.get("every_frame") is not None:
        check_bool_param("visualizer", "every_frame", params["every_frame"])
    check_number_param("visualizer", "alpha", params.get("alpha", PARAMS["alpha"]), minimum=0)
    check_number_param("visualizer", "side", params.get("side", PARAMS["side"]), minimum=0)
    check_number_param("visualizer", "timeout", params.get("timeout"), minimum=0, null=True)


class VideoOut:
    """An MP4 written frame by frame (cv2.VideoWriter, mp4v), opened at the first frame's size;
    frames of another size are resized to it."""

    def __init__(self, path: str, fps: float):
        self.path, self.fps, self.writer, self.size, self.frames = Path(path).expanduser(), float(fps), None, None, 0
        try:                                          # a bad path fails now, not at the first frame
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RuntimeError(f"video {self.path}: cannot make its folder ({e.strerror})") from None
        if not os.access(self.path.parent, os.W_OK) or self.path.is_dir():
            raise RuntimeError(f"video {self.path}: cannot be written (no permission, or a folder)")

    def write(self, frame) -> None:
        h, w = frame.shape[:2]
        if self.writer is None:
            self.size = (w, h)
            self.writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, self.size)
            if not self.writer.isOpened():
                raise RuntimeError(f"video {self.path}: cannot be written (mp4v encoder unavailable, or no "
                                   f"permission)")
        if (w, h) != self.size:
            frame = cv2.resize(frame, self.size, interpolation=cv2.INTER_AREA)
        self.writer.write(frame)
        self.frames += 1

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()   # writes the MP4 index: without it the file does not play
            self.writer = None


def K_of(frame) -> np.ndarray:
    """K (3,3) of a synced frame: its CameraInfo, else a default field of view."""
    if frame.info is not None:
        return np.asarray(frame.info["K"], dtype=np.float64)
    return camera_info.default_K(frame.image["width"], frame.image["height"])


def main() -> None:
    node = Node("visualizer", params=PARAMS)
    p = node.params
    keep_all = bool(p["video"]) if p["every_frame"] is None else bool(p["every_frame"])
    timeout = float(p["timeout"]) if p["timeout"] is not None else (5.0 if keep_all else 0.5)
    overlay = Overlay(HandModel.load(p["model"]), mesh=bool(p["mesh"]), alpha=float(p["alpha"]),
                      side=float(p["side"]), joints3d=bool(p["joints3d"]))
    overlay.check()                                   # no OpenGL: one error line now, not mid-stream
    sync = FrameSync(keep_all=keep_all, timeout_s=timeout)
    video = VideoOut(p["video"], p["fps"]) if p["video"] else None
    # a video gets every frame (the sources wait for it); live: never a backlog of frames
    image_mode = "lossless" if keep_all else "latest"
    node.subscribe("/camera/image", "Image", mode=image_mode)
    node.subscribe("/camera/info", "CameraInfo", mode=image_mode)
    pose_mode = "lossless" if keep_all else "all"    # small; every one may pair
    node.subscribe("/hand/keypoints", "HandKeypoints", mode=pose_mode)
    node.subscribe("/hand/pose", "HandPose", mode=pose_mode)
    if p["publish"]:
        node.advertise("/viz/image", "Image")
    drawn = paired = held = 0

    def emit(frames, deadline=None) -> None:
        """Draw, write and publish; past `deadline` (monotonic s) frames go into the video
        undrawn, so a shutdown finishes the file before the launcher's kill."""
        nonlocal drawn, paired, held
        for f in frames:
            try:
                image = frame_bgr(f.image)
            except ValueError as e:
                node.log.warning("skipped an image: %s", e)
                continue
            if deadline is not None and time.monotonic() > deadline:
                if video is not None:
                    video.write(image)
                continue
            out = overlay.draw(image, K_of(f), f.pose["hands"] if f.pose else (),
                               f.keypoints["hands"] if f.keypoints else ())
            if video is not None:
                video.write(out)
            if p["publish"]:
                node.publish("/viz/image", image_message(out), stamp_ns=f.stamp_ns,
                             frame_id=f.image["header"]["frame_id"])
            drawn += 1
            paired += f.pose is not None and not f.held
            held += f.held

    try:
        for msg in node.events(timeout=TICK_S):
            now = time.monotonic()
            if msg is not None:
                if msg.type == "Image":
                    sync.add_image(msg.data, now)
                elif msg.type == "CameraInfo":
                    sync.add_info(msg.data)
                elif msg.type == "HandKeypoints":
                    sync.add_keypoints(msg.data)
                else:
                    sync.add_pose(msg.data, now)
            emit(sync.pop(now))
        # end of stream or shutdown: the frames still held (on SIGINT/SIGTERM within a time
        # budget well under the launcher's STOP_TIMEOUT_S)
        emit(sync.pop(time.monotonic(), flush=True), None if node.ok() else time.monotonic() + SHUTDOWN_DRAW_S)
    finally:
        if video is not None:
            video.close()
        overlay.release()
        node.log.info("drew %d frame(s), %d with their pose%s%s", drawn, paired,
                      f", {held} with the previous frame's (skipped by the detector)" if held else "",
                      f"; wrote {video.frames} to {video.path}" if video is not None else "")
        if sync.overflowed:
            node.log.warning("%d frame(s) drawn without their pose: the buffer was full", sync.overflowed)
        node.close()


if __name__ == "__main__":
    run(main)

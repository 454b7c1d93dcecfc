"""`depthai`: an OAK camera (Luxonis, depthai v3 API) as `/camera/image` + `/camera/info`.

Parameters (PARAMS):
- device: the OAK to open, by device id (serial) or IP address; None: the first one found.
- socket: the board socket of the colour camera (CameraBoardSocket name, e.g. CAM_A).
- width, height, fps: the colour output asked of the Camera node (BGR888i, resized on the
  device; a different aspect ratio than the sensor's is a centre crop).
- frame_id: header frame id of both topics.
- replay: a video file (e.g. the .mp4 of a depthai holistic recording) played through
  depthai's host-side `ReplayVideo` node instead of a device: the same frame path without
  hardware. Frames keep the video's own size; width/height are not applied.
- replay_calibration: in replay mode, the device calibration to publish: a depthai
  calibration JSON (`CalibrationHandler.eepromToJsonFile`, or a holistic recording's
  calibration.json). Without it, K comes from the default field of view.

CameraInfo comes from the device's own calibration (`readCalibration()`, then
`getCameraIntrinsics(socket, w, h)` and the distortion coefficients, OpenCV's 14-term
pinhole model), source 'device'; it is repeated with every frame, just before the image,
same stamp (as the webcam node does).

Stamps: the frame's host-synchronised capture timestamp (`ImgFrame.getTimestamp()`, the
host's steady clock = CLOCK_MONOTONIC) moved to CLOCK_REALTIME.

Failures: no device (or not the one asked for) is one error line "no OAK device found ..."
and exit 2; a device whose frames stop (unplugged) is one error line and exit 2; a replay
that reaches the end of its video ends the stream normally (exit 0).

depthai is imported lazily, so `handlaunch` can read PARAMS without it installed.
"""
from __future__ import annotations

import datetime
import os
import time
from collections.abc import Callable, Iterator

import numpy as np

from handmocap.perception.camera_info import as_distortion, as_K, camera_info_message, default_intrinsics
from handmocap.runtime.node import Node, check_file_param, check_number_param, run

PARAMS = {"device": None, "socket": "CAM_A", "width": 640, "height": 480, "fps": 30, "frame_id": "camera",
          "replay": None, "replay_calibration": None}

POLL_S = 0.1               # how long one queue read waits before checking for shutdown
FRAME_TIMEOUT_S = 5.0      # a running device without a frame this long has failed


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param); whether
    an OAK device is there is known only when the node opens it."""
    for key in ("width", "height"):
        check_number_param("depthai", key, params.get(key, PARAMS[key]), minimum=1, integer=True)
    check_number_param("depthai", "fps", params.get("fps", PARAMS["fps"]), positive=True)
    check_file_param("depthai", "replay", params.get("replay"))
    check_file_param("depthai", "replay_calibration", params.get("replay_calibration"))

def import_depthai():
    """The depthai module (v3), or RuntimeError saying how to install it. Its own console
    logging defaults to errors only (set DEPTHAI_LEVEL=warn to see its warnings)."""
    os.environ.setdefault("DEPTHAI_LEVEL", "error")
    try:
        import depthai
    except ImportError as e:
        raise RuntimeError(f"the depthai node needs the depthai package "
                           f"(pip install 'handmocap[depthai]'): {e}") from None
    if not hasattr(depthai.node, "Camera") or not hasattr(depthai.node, "ReplayVideo"):
        raise RuntimeError(f"the depthai node needs depthai 3.x, found {getattr(depthai, '__version__', '?')}")
    return depthai


def board_socket(name: str):
    """CameraBoardSocket by name (CAM_A, CAM_B, ...); ValueError listing the names otherwise."""
    dai = import_depthai()
    members = dai.CameraBoardSocket.__members__
    if name not in members:
        raise ValueError(f"unknown camera socket {name!r}; one of {', '.join(sorted(members))}")
    return members[name]


# -- the device-open step (needs hardware) ---------------------------------------------------
def open_device(device_id: str | None = None):
    """Open the OAK `device_id` (serial or IP; None: the first found) and return the
    dai.Device. RuntimeError "no OAK device found ..." when there is none, or not that one."""
    dai = import_depthai()
    found = dai.Device.getAllAvailableDevices()
    if not found:
        raise RuntimeError("no OAK device found (is it plugged in and powered? on Linux USB access needs Luxonis' "
                           "udev rule; in a container pass /dev/bus/usb; a PoE device must be reachable)")
    if device_id is None:
        chosen = found[0]
    else:
        matches = [d for d in found if str(device_id) in (d.getDeviceId(), d.name)]
        if not matches:
            names = ", ".join(f"{d.getDeviceId()} ({d.name})" for d in found)
            raise RuntimeError(f"no OAK device found with id or address {device_id!r}; available: {names}")
        chosen = matches[0]
    try:
        return dai.Device(chosen)
    except RuntimeError as e:
        raise RuntimeError(f"OAK device {chosen.getDeviceId()} ({chosen.name}) found but can't be opened "
                           f"(in use by another program?): {e}") from None


def device_pipeline(device, socket, width: int, height: int, fps: float):
    """A pipeline on `device`: the Camera node at `socket`, colour output width×height BGR888i
    at `fps`. Returns (pipeline, output queue of dai.ImgFrame)."""
    dai = import_depthai()
    pipeline = dai.Pipeline(device)
    cam = pipeline.create(dai.node.Camera).build(socket)
    out = cam.requestOutput((int(width), int(height)), dai.ImgFrame.Type.BGR888i, fps=float(fps))
    return pipeline, out.createOutputQueue(maxSize=4, blocking=False)


# -- host-only pieces (no hardware) --------------------------------------------------------
def replay_pipeline(video: str, fps: float | None = None):
    """A host-only pipeline (no device) whose ReplayVideo node plays `video` once as BGR888i
    frames, paced at `fps` (None: the video's own rate). Returns (pipeline, output queue)."""
    dai = import_depthai()
    if not os.path.isfile(video):
        raise FileNotFoundError(f"replay video {video}: no such file")
    pipeline = dai.Pipeline(False)
    replay = pipeline.create(dai.node.ReplayVideo)
    replay.setReplayVideoFile(video)
    replay.setOutFrameType(dai.ImgFrame.Type.BGR888i)
    replay.setLoop(False)
    if fps:
        replay.setFps(float(fps))
    return pipeline, replay.out.createOutputQueue(maxSize=4, blocking=True)


def load_device_calibration(path: str):
    """A dai.CalibrationHandler from a depthai calibration JSON; ValueError naming the file."""
    dai = import_depthai()
    if not os.path.isfile(path):
        raise ValueError(f"device calibration {path}: no such file")
    try:
        return dai.CalibrationHandler(os.path.abspath(path))
    except RuntimeError as e:
        raise ValueError(f"device calibration {path}: not a depthai calibration JSON: {e}") from None


def camera_info_from_calibration(calib, socket, width: int, height: int) -> dict:
    """The CameraInfo body for width×height frames of the camera at `socket`, from a
    dai.CalibrationHandler (the device's EEPROM calibration): K (3,3) from
    `getCameraIntrinsics(socket, width, height)`, distortion (14,) OpenCV pinhole terms.
    ValueError when the device has no usable calibration for that camera."""
    dai = import_depthai()
    try:
        K = calib.getCameraIntrinsics(socket, width, height)
        dist = calib.getDistortionCoefficients(socket)
        model = calib.getDistortionModel(socket)
    except RuntimeError as e:
        raise ValueError(f"no calibration for camera {socket.name} on this device: {e}") from None
    if model != dai.CameraModel.Perspective:
        raise ValueError(f"camera {socket.name} is calibrated with the {model.name} model; only the pinhole "
                         f"(Perspective) model maps to OpenCV distortion")
    try:
        return camera_info_message(as_K(K), as_distortion(dist), width, height, "device")
    except ValueError as e:
        raise ValueError(f"device calibration of camera {socket.name}: {e}") from None


def frame_stamp_ns(frame) -> int:
    """CLOCK_REALTIME ns of a dai.ImgFrame's capture: its host-synced timestamp is on the
    host's steady clock (CLOCK_MONOTONIC)."""
    td: datetime.timedelta = frame.getTimestamp()
    monotonic_ns = (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000
    return time.time_ns() - time.monotonic_ns() + monotonic_ns


def image_message(frame) -> dict:
    """The Image body (no header) of a dai.ImgFrame: bgr8, data (H,W,3) uint8."""
    bgr = np.ascontiguousarray(frame.getCvFrame())
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise RuntimeError(f"OAK delivered a {frame.getType().name} frame of shape {bgr.shape}, expected BGR")
    return {"encoding": "bgr8", "width": int(bgr.shape[1]), "height": int(bgr.shape[0]), "data": bgr}


def frames(queue, pipeline_running: Callable[[], bool], stop: Callable[[], bool], end_is_error: bool,
           frame_timeout_s: float = FRAME_TIMEOUT_S) -> Iterator:
    """Yield the dai.ImgFrames of an output queue until `stop()` (shutdown) or the stream ends:
    the queue closes or the pipeline stops (a replay reached its end). With `end_is_error` (a
    live device), an end, or no frame for `frame_timeout_s`, raises RuntimeError: the device
    is gone."""
    dai = import_depthai()
    last = time.monotonic()
    while not stop():
        if not pipeline_running():
            break
        try:
            frame = queue.get(datetime.timedelta(seconds=POLL_S))
        except dai.MessageQueue.QueueException:
            break
        if frame is not None:
            last = time.monotonic()
            yield frame
        elif end_is_error and time.monotonic() - last > frame_timeout_s:
            raise RuntimeError(f"OAK delivered no frame for {frame_timeout_s:g} s (device disconnected?)")
    else:
        return   # asked to stop
    if end_is_error:
        raise RuntimeError("OAK stopped delivering frames (device disconnected?)")


def publish_frames(node: Node, frame_source: Iterator, info_for_size: Callable[[int, int], dict],
                   frame_id: str) -> int:
    """Publish each frame as /camera/info + /camera/image (same stamp) until the source ends
    or the node is asked to stop; returns how many were published."""
    n = 0
    info, size = None, None
    for frame in frame_source:
        image = image_message(frame)
        if (image["width"], image["height"]) != size:
            size = (image["width"], image["height"])
            info = info_for_size(*size)
        stamp_ns = frame_stamp_ns(frame)
        node.publish("/camera/info", info, stamp_ns=stamp_ns, frame_id=frame_id)
        node.publish("/camera/image", image, stamp_ns=stamp_ns, frame_id=frame_id)
        n += 1
        if not node.ok():
            break
    return n


def main() -> None:
    node = Node("depthai", params=PARAMS)
    p = node.params
    socket = board_socket(p["socket"])
    if p["replay"]:
        calib = load_device_calibration(p["replay_calibration"]) if p["replay_calibration"] else None
        pipeline, queue = replay_pipeline(p["replay"], p["fps"])
        live = False
    else:
        device = open_device(p["device"])
        calib = device.readCalibration()
        pipeline, queue = device_pipeline(device, socket, p["width"], p["height"], p["fps"])
        live = True

    def info_for_size(width: int, height: int) -> dict:
        if calib is None:
            intr = default_intrinsics(width, height)
            node.log.warning("no device calibration in replay mode: K from a default field of view")
            return camera_info_message(intr.K, intr.distortion, width, height, intr.source)
        return camera_info_from_calibration(calib, socket, width, height)

    if calib is not None:
        info_for_size(p["width"], p["height"])   # fail on a bad calibration before any topic exists
    node.advertise("/camera/info", "CameraInfo")
    node.advertise("/camera/image", "Image")
    pipeline.start()
    try:
        source = frames(queue, pipeline.isRunning, stop=lambda: not node.ok(), end_is_error=live)
        n = publish_frames(node, source, info_for_size, p["frame_id"])
        node.log.info("published %d frames", n)
    finally:
        pipeline.stop()
        node.close()


if __name__ == "__main__":
    run(main)

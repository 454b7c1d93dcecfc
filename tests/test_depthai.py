"""The OAK node (nodes/depthai.py) without hardware: host-built device calibrations and
depthai's host-side ReplayVideo node, which runs in a pipeline made without a device.

(depthai's holistic replay can't stand in here: it replays into the Camera node, which runs
on the device; in a device-less pipeline depthai refuses it with "Pipeline is host only,
cannot create device node".)
"""
from __future__ import annotations

import time

import numpy as np
import pytest

dai = pytest.importorskip("depthai", reason="depthai is an optional extra: pip install 'handmocap[depthai]'")

from handmocap.runtime import codec  # noqa: E402
from handmocap.nodes import depthai as oak  # noqa: E402
from conftest import write_test_video  # noqa: E402
from source_nodes import run_failing, run_source  # noqa: E402

CAM_A = dai.CameraBoardSocket.CAM_A
K_1280 = [[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]]
DIST_14 = [0.11, -0.23, 0.001, -0.002, 0.05] + [0.0] * 9


def _calibration(model=None):
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(CAM_A, K_1280, 1280, 720)
    calib.setDistortionCoefficients(CAM_A, DIST_14)
    if model is not None:
        calib.setCameraType(CAM_A, model)
    return calib


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """A 10-frame 320x180 MJPG video; returns (path, frames as OpenCV decodes them)."""
    path = tmp_path_factory.mktemp("oak") / "CameraCAM_A.avi"
    return str(path), write_test_video(path, 10, size=(320, 180))


@pytest.fixture(scope="module")
def calibration_json(tmp_path_factory):
    path = tmp_path_factory.mktemp("oak") / "calibration.json"
    _calibration().eepromToJsonFile(str(path))
    return str(path)


# -- calibration ------------------------------------------------------------------------
def test_camera_info_from_device_calibration_scales_to_the_output():
    info = oak.camera_info_from_calibration(_calibration(), CAM_A, 640, 360)
    assert (info["width"], info["height"], info["source"]) == (640, 360, "device")
    K = info["K"]
    assert K.dtype == np.float64 and K.shape == (3, 3)
    np.testing.assert_allclose(K[[0, 1], [0, 1]], [450.0, 450.0], rtol=1e-6)
    np.testing.assert_allclose(K[:2, 2], [320.0, 180.0], atol=0.5)
    np.testing.assert_allclose(info["distortion"], DIST_14, atol=1e-7)   # stored as float32 on the device
    codec.encode({"header": codec.header(0), **info}, "CameraInfo")       # a valid message


def test_camera_without_calibration_is_a_clear_error():
    with pytest.raises(ValueError, match="no calibration for camera CAM_B"):
        oak.camera_info_from_calibration(_calibration(), dai.CameraBoardSocket.CAM_B, 640, 360)


def test_fisheye_calibration_is_refused():
    with pytest.raises(ValueError, match="Fisheye model"):
        oak.camera_info_from_calibration(_calibration(dai.CameraModel.Fisheye), CAM_A, 640, 360)


def test_calibration_json_round_trip(calibration_json, tmp_path):
    calib = oak.load_device_calibration(calibration_json)
    np.testing.assert_allclose(calib.getCameraIntrinsics(CAM_A), K_1280)
    bad = tmp_path / "calibration.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not a depthai calibration JSON"):
        oak.load_device_calibration(str(bad))


def test_board_socket_names():
    assert oak.board_socket("CAM_A") == CAM_A
    with pytest.raises(ValueError, match="unknown camera socket 'CAM_Z'"):
        oak.board_socket("CAM_Z")


# -- frames through depthai's host-side replay ------------------------------------------------
def test_replay_frames_become_bgr_images(video):
    path, decoded = video
    pipeline, queue = oak.replay_pipeline(path, fps=200)
    started_ns = time.time_ns()
    pipeline.start()
    try:
        got = list(oak.frames(queue, pipeline.isRunning, stop=lambda: False, end_is_error=False))
    finally:
        pipeline.stop()
    ended_ns = time.time_ns()
    assert len(got) == len(decoded)
    for frame, ref in zip(got, decoded):
        image = oak.image_message(frame)
        assert (image["encoding"], image["width"], image["height"]) == ("bgr8", 320, 180)
        assert image["data"].shape == (180, 320, 3) and image["data"].dtype == np.uint8
        assert np.abs(image["data"].astype(int) - ref).mean() < 2.0   # depthai decodes with its own OpenCV
        assert started_ns - 5e6 <= oak.frame_stamp_ns(frame) <= ended_ns + 5e6   # capture time, realtime clock


def test_end_of_frames_from_a_live_device_is_an_error(video):
    """A device's queue closing (unplugged) must end the node with an error, not quietly."""
    pipeline, queue = oak.replay_pipeline(video[0], fps=200)
    pipeline.start()
    try:
        source = oak.frames(queue, pipeline.isRunning, stop=lambda: False, end_is_error=True)
        with pytest.raises(RuntimeError, match="OAK stopped delivering frames"):
            for _ in source:
                pass
    finally:
        pipeline.stop()


def test_node_replays_a_recording_with_the_device_calibration(video, calibration_json):
    path, decoded = video
    r = run_source("handmocap.nodes.depthai", {"replay": path, "replay_calibration": calibration_json, "fps": 100,
                                               "frame_id": "oak"})
    assert r.returncode == 0, r.stderr
    images, infos = r.messages["/camera/image"], r.messages["/camera/info"]
    assert len(images) == len(infos) == len(decoded)
    for i, (img, info) in enumerate(zip(images, infos)):
        assert img["data"].shape == (180, 320, 3) and img["encoding"] == "bgr8"
        assert img["header"]["seq"] == i and img["header"]["frame_id"] == "oak"
        assert info["header"]["stamp_ns"] == img["header"]["stamp_ns"]
        assert (info["width"], info["height"], info["source"]) == (320, 180, "device")
    np.testing.assert_allclose(infos[0]["K"], _calibration().getCameraIntrinsics(CAM_A, 320, 180))
    assert np.abs(images[-1]["data"].astype(int) - decoded[-1]).mean() < 2.0


def test_no_device_is_one_error_line():
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is attached")
    r = run_failing("handmocap.nodes.depthai", {})
    assert r.returncode == 2
    lines = [line for line in (r.stdout + r.stderr).splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert "no OAK device found" in lines[0] and "Traceback" not in r.stderr

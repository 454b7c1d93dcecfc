"""Intrinsics (handmocap.perception.camera_info) and the webcam node (nodes/camera.py)."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import yaml

from handmocap.runtime import codec
from handmocap.perception.camera_info import (Intrinsics, camera_info_message, default_K, intrinsics_for_frames,
                                   load_calibration, scale_K)
from handmocap.nodes import camera
from conftest import write_test_video
from source_nodes import run_failing, run_source

K_1280 = np.array([[900.0, 0.0, 641.25], [0.0, 902.0, 357.5], [0.0, 0.0, 1.0]])
DIST_5 = np.array([0.11, -0.23, 0.001, -0.002, 0.05])


# -- default field of view --------------------------------------------------------------
def test_default_K_has_the_documented_field_of_view():
    K = default_K(640, 480)
    assert math.degrees(2 * math.atan(320 / K[0, 0])) == pytest.approx(60.0)
    assert K[0, 0] == K[1, 1]
    assert (K[0, 2], K[1, 2]) == (319.5, 239.5)
    assert math.degrees(2 * math.atan(640 / default_K(1280, 720, hfov_deg=90)[0, 0])) == pytest.approx(90.0)


# -- calibration formats ------------------------------------------------------------------
def _write_opencv_storage(path, K, dist, size):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(-1, 1))
    fs.release()


def _check(intr: Intrinsics, K=K_1280, dist=DIST_5, size=(1280, 720)):
    assert intr.K.dtype == np.float64 and intr.K.shape == (3, 3)
    np.testing.assert_allclose(intr.K, K)
    np.testing.assert_allclose(intr.distortion, dist)
    assert intr.size == size
    assert intr.source == "calibration"


def test_yaml_with_3x3_K(tmp_path):
    p = tmp_path / "cam.yaml"
    p.write_text(yaml.safe_dump({"K": K_1280.tolist(), "distortion": DIST_5.tolist(), "width": 1280, "height": 720}))
    _check(load_calibration(p))


def test_json_with_fx_fy_cx_cy_and_no_distortion(tmp_path):
    p = tmp_path / "cam.json"
    p.write_text(json.dumps({"K": [900.0, 902.0, 641.25, 357.5], "width": 1280, "height": 720}))
    _check(load_calibration(p), dist=np.zeros(5))


def test_ros_ost_yaml(tmp_path):
    p = tmp_path / "ost.yaml"
    p.write_text(yaml.safe_dump({
        "image_width": 1280, "image_height": 720, "camera_name": "webcam",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K_1280.ravel().tolist()},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": DIST_5.tolist()},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
    }))
    _check(load_calibration(p))


@pytest.mark.parametrize("suffix", [".yaml", ".xml", ".json"])
def test_opencv_filestorage(tmp_path, suffix):
    p = tmp_path / f"out_camera_data{suffix}"
    _write_opencv_storage(p, K_1280, DIST_5, (1280, 720))
    _check(load_calibration(p))


@pytest.mark.parametrize("K", [K_1280, np.array([900.0, 902.0, 641.25, 357.5])])
def test_npy(tmp_path, K):
    p = tmp_path / "K.npy"
    np.save(p, K)
    _check(load_calibration(p), dist=np.zeros(5), size=None)


# -- scaling ----------------------------------------------------------------------------
def test_calibration_scales_to_the_frame_size(tmp_path):
    p = tmp_path / "cam.yaml"
    p.write_text(yaml.safe_dump({"K": K_1280.tolist(), "width": 1280, "height": 720}))
    intr = intrinsics_for_frames(640, 360, p)
    assert intr.size == (640, 360)
    np.testing.assert_allclose(intr.K[[0, 1], [0, 1]], [450.0, 451.0])
    # pixel centres: u' + 0.5 = (u + 0.5) / 2
    np.testing.assert_allclose(intr.K[:2, 2], [(641.25 + 0.5) / 2 - 0.5, (357.5 + 0.5) / 2 - 0.5])
    # a point projects where cv2.resize puts it
    np.testing.assert_allclose(scale_K(default_K(1280, 720), (1280, 720), (640, 360)), default_K(640, 360))


def test_other_aspect_ratio_is_one_clear_error(tmp_path):
    p = tmp_path / "cam.yaml"
    p.write_text(yaml.safe_dump({"K": K_1280.tolist(), "width": 1280, "height": 720}))
    with pytest.raises(ValueError, match=r"cam\.yaml.*1280x720.*640x480.*aspect ratio"):
        intrinsics_for_frames(640, 480, p)


def test_unknown_size_with_principal_point_outside_the_frame(tmp_path):
    p = tmp_path / "K.npy"
    np.save(p, K_1280)
    with pytest.raises(ValueError, match=r"K\.npy.*principal point.*outside the 320x240 frame"):
        intrinsics_for_frames(320, 240, p)
    assert intrinsics_for_frames(1280, 720, p).size is None


def test_no_calibration_gives_the_default_field_of_view():
    intr = intrinsics_for_frames(320, 240, None)
    assert intr.source == "default-fov"
    np.testing.assert_allclose(intr.K, default_K(320, 240))


# -- wrong K files ----------------------------------------------------------------------
def _yaml(**doc):
    return yaml.safe_dump(doc)


WRONG_FILES = {
    "missing": (None, "no such file"),
    "garbage.npy": (b"\x93NUMPY nonsense", "unreadable"),
    "shape.npy": (np.eye(2), r"shape \(2, 2\)"),
    "rows.npy": (np.ones((5, 4)), r"shape \(5, 4\)"),
    "negative.yaml": (_yaml(K=[-900.0, 900.0, 320.0, 240.0]), "non-positive focal length"),
    "zero.json": (json.dumps({"K": [[0, 0, 320], [0, 500, 240], [0, 0, 1]]}), "non-positive focal length"),
    "nan.yaml": (_yaml(K=[900.0, float("nan"), 320.0, 240.0]), "NaN"),
    "lastrow.yaml": (_yaml(K=[[900, 0, 320], [0, 900, 240], [0, 1, 1]]), "not an intrinsic matrix"),
    "text.yaml": (_yaml(K="fx=900"), "not a matrix of numbers"),
    "nokey.yaml": (_yaml(focal=900), "no K or camera_matrix"),
    "list.yaml": ("- 1\n- 2\n", "mapping"),
    "broken.yaml": ("K: [900, 900\n", "malformed"),
    "dist.yaml": (_yaml(K=[900.0, 900.0, 320.0, 240.0], distortion=[0.1, 0.2, 0.3]), "3 coefficients"),
    "fisheye.yaml": (_yaml(camera_matrix={"rows": 3, "cols": 3, "data": K_1280.ravel().tolist()},
                           distortion_model="equidistant", distortion_coefficients={"data": [0.1, 0, 0, 0]}),
                     "equidistant"),
    "halfsize.yaml": (_yaml(K=[900.0, 900.0, 320.0, 240.0], width=640), "only one of width and height"),
}


@pytest.mark.parametrize("name", sorted(WRONG_FILES))
def test_wrong_calibration_file_is_one_clear_error(tmp_path, name):
    content, problem = WRONG_FILES[name]
    p = tmp_path / name
    if isinstance(content, np.ndarray):
        np.save(p, content)
    elif isinstance(content, bytes):
        p.write_bytes(content)
    elif content is not None:
        p.write_text(content)
    with pytest.raises(ValueError, match=problem) as e:
        load_calibration(p)
    assert str(e.value).startswith(f"calibration file {p}: ")


# -- messages -----------------------------------------------------------------------------
def test_camera_info_message_is_a_valid_CameraInfo():
    body = camera_info_message(K_1280, DIST_5, 1280, 720, "calibration")
    payload = codec.encode({"header": codec.header(0), **body}, "CameraInfo")
    msg = codec.decode(payload, "CameraInfo")
    assert msg["K"].dtype == np.float64 and msg["K"].shape == (3, 3)
    assert msg["distortion"].shape == (5,)
    np.testing.assert_array_equal(msg["K"], K_1280)
    assert (msg["width"], msg["height"], msg["source"]) == (1280, 720, "calibration")


def test_mirrored_intrinsics_project_the_mirrored_scene():
    """Flipping the image left-right = imaging the scene mirrored in x with the mirrored
    camera: every point must land on the flipped pixel, distortion included."""
    dist = np.array([0.11, -0.23, 0.004, -0.006, 0.05, 0.01, -0.02, 0.003, 0.001, -0.002, 0.003, 0.0005])
    K = K_1280.copy()
    K[0, 1] = 1.5   # skew
    intr = Intrinsics(K, dist, (1280, 720), "calibration")
    mirror = camera.mirrored(intr, 1280)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.2, 0.2, 50), rng.uniform(0.5, 1.5, 50)])
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    pts_m = pts * [-1, 1, 1]
    uv_m, _ = cv2.projectPoints(pts_m, np.zeros(3), np.zeros(3), mirror.K, mirror.distortion)
    np.testing.assert_allclose(uv_m[:, 0, 0], 1279 - uv[:, 0, 0], atol=1e-6)
    np.testing.assert_allclose(uv_m[:, 0, 1], uv[:, 0, 1], atol=1e-6)


def test_parse_device():
    assert camera.parse_device(2) == 2
    assert camera.parse_device("1") == 1
    assert camera.parse_device("/dev/video3") == "/dev/video3"
    assert camera.parse_device("rtsp://cam/stream") == "rtsp://cam/stream"
    with pytest.raises(ValueError):
        camera.parse_device(True)


class _DyingCamera:
    """A live capture that delivers `n` frames and then nothing (unplugged)."""

    def __init__(self, n):
        self.left = n

    def grab(self):
        self.left -= 1
        return self.left >= 0

    def retrieve(self):
        return True, np.zeros((4, 6, 3), np.uint8)


def test_live_camera_that_stops_delivering_raises():
    frames = camera.read_frames(_DyingCamera(3), live=True, fps=30, fail_after_s=0.2)
    got = [next(frames) for _ in range(3)]
    assert all(f.shape == (4, 6, 3) for _, f in got)
    assert got[0][0] <= got[1][0] <= got[2][0]
    with pytest.raises(RuntimeError, match="stopped delivering frames"):
        next(frames)


def test_file_source_ends_without_error():
    assert len(list(camera.read_frames(_DyingCamera(3), live=False, fps=0))) == 3


# -- the node as a process --------------------------------------------------------------
@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """A 12-frame 320x240 MJPG video whose frames differ; returns (path, decoded frames)."""
    path = tmp_path_factory.mktemp("video") / "clip.avi"
    return str(path), write_test_video(path, 12)


def test_device_that_cannot_be_opened_is_one_error_line():
    r = run_failing("handmocap.nodes.camera", {"device": "/dev/video99"})
    assert r.returncode == 2
    lines = [line for line in (r.stdout + r.stderr).splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert "/dev/video99" in lines[0] and "ERROR" in lines[0]
    assert "Traceback" not in r.stderr


def test_file_that_is_not_a_video_is_one_error_line(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("not a video")
    r = run_failing("handmocap.nodes.camera", {"device": str(p)})
    assert r.returncode == 2
    lines = [line for line in (r.stdout + r.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and "notes.txt" in lines[0] and "can't be opened" in lines[0], lines


def test_bad_calibration_is_one_error_line(tmp_path, video):
    p = tmp_path / "K.npy"
    np.save(p, np.array([0.0, 900.0, 160.0, 120.0]))
    r = run_failing("handmocap.nodes.camera", {"device": video[0], "calibration": str(p)})
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "K.npy" in errors[0] and "non-positive focal length" in errors[0]
    assert "Traceback" not in r.stderr


def test_video_file_as_device_publishes_every_frame_with_camera_info(video, tmp_path):
    path, frames = video
    calib = tmp_path / "cam.yaml"   # made at 640x480: must be scaled to the 320x240 frames
    calib.write_text(yaml.safe_dump({"K": [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]], "width": 640,
                                     "height": 480, "distortion": [0.1, -0.05, 0, 0, 0]}))
    r = run_source("handmocap.nodes.camera", {"device": path, "fps": 200, "calibration": str(calib),
                                              "frame_id": "webcam"})
    assert r.returncode == 0, r.stderr
    images, infos = r.messages["/camera/image"], r.messages["/camera/info"]
    assert len(images) == len(frames) == len(infos)
    for i, (img, info, frame) in enumerate(zip(images, infos, frames)):
        assert img["encoding"] == "bgr8" and (img["width"], img["height"]) == (320, 240)
        assert img["data"].shape == (240, 320, 3) and img["data"].dtype == np.uint8
        np.testing.assert_array_equal(img["data"], frame)
        assert img["header"]["seq"] == i and img["header"]["frame_id"] == "webcam"
        assert info["header"]["stamp_ns"] == img["header"]["stamp_ns"]
        assert (info["width"], info["height"], info["source"]) == (320, 240, "calibration")
    np.testing.assert_allclose(infos[0]["K"], [[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    np.testing.assert_allclose(infos[0]["distortion"], [0.1, -0.05, 0, 0, 0])
    stamps = [m["header"]["stamp_ns"] for m in images]
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] >= 0.8 * 11 / 200 * 1e9   # paced at fps


def test_mirror_flips_frames_and_K(video):
    path, frames = video
    r = run_source("handmocap.nodes.camera", {"device": path, "fps": 200, "mirror": True})
    assert r.returncode == 0, r.stderr
    images, infos = r.messages["/camera/image"], r.messages["/camera/info"]
    assert len(images) == len(frames)
    np.testing.assert_array_equal(images[5]["data"], frames[5][:, ::-1])
    assert infos[0]["source"] == "default-fov"
    np.testing.assert_allclose(infos[0]["K"], default_K(320, 240))   # centred: its own mirror image

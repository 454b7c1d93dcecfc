"""The visualizer: its drawing functions and frame pairing in-process (the mesh lands on the
published joints, skeleton colours, side view, stamp pairing), and the node in real graphs
(the demo writes one MP4 frame per input frame; SIGINT leaves a playable MP4; no OpenGL is one
error line)."""
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from conftest import ROOT, graph_env, handlaunch
from handmocap.perception.camera_info import project
from handmocap.runtime.frame_sync import FrameSync
from handmocap.perception.hand_model import HandModel
from handmocap.perception.overlay import FINGER_COLOURS, Overlay, composite, draw_skeleton, side_view_transform
from handmocap.perception.pose import hand_mesh
from handmocap.training.pose_data import PoseSampler
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import ROOT as ROOT_JOINT

MODEL = HandModel.load()
W, H = 640, 480
K = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
CLIP_FRAMES = 90   # data/demo/hand_clip.mp4


def pose_hand(quats, beta, root, handedness="right", track_id=0):
    """A HandPose hand as the ik node builds it (handmocap.perception.pose.pose_fields): xyz = root +
    (model joints - joint 9), mirrored for a left hand."""
    _, joints = MODEL.forward(quats, beta)
    rel = joints - joints[ROOT_JOINT]
    rel = mirror_points(rel) if handedness == "left" else rel
    xyz = root + rel
    return {"track_id": track_id, "handedness": handedness, "score": 0.9, "xyz": xyz.astype(np.float32),
            "root": np.asarray(root, np.float32), "quat": quats.astype(np.float32),
            "pose": np.zeros((16, 3), np.float32), "beta": beta.astype(np.float32),
            "uv": project(K, xyz).astype(np.float32)}


@pytest.fixture(scope="module")
def samples():
    d = PoseSampler(MODEL).sample(6, np.random.default_rng(7))
    return d["quats"], d["beta"]


@pytest.fixture(scope="module")
def overlay():
    o = Overlay(MODEL, side=0.0, joints3d=False)
    yield o
    o.release()


@pytest.mark.parametrize("handedness", ["right", "left"])
def test_mesh_joints_are_the_published_joints(samples, handedness):
    quats, betas = samples
    for q, b in zip(quats, betas):
        hand = pose_hand(q, b, np.array([0.05, -0.03, 0.6]), handedness)
        vertices, faces, joints = hand_mesh(MODEL, hand)
        np.testing.assert_allclose(joints, hand["xyz"], atol=1e-5)
        assert vertices.shape == MODEL.v_template.shape and faces.shape == MODEL.faces.shape


@pytest.mark.parametrize("handedness", ["right", "left"])
def test_rendered_mesh_covers_the_projected_joints(samples, overlay, handedness):
    """The silhouette of the mesh rendered with K covers every projected joint of `xyz`, and
    spans the box of its projected vertices (no more, no less: same projection, same scale)."""
    quats, betas = samples
    for i, (q, b) in enumerate(zip(quats, betas)):
        hand = pose_hand(q, b, np.array([0.03 * (i % 3 - 1), -0.02, 0.55]), handedness)
        vertices, faces, _ = hand_mesh(MODEL, hand)
        _, depth = overlay._render("main", W, H, [(vertices, faces)], K)
        silhouette = cv2.dilate((depth > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0   # 2 px: tips lie on the rim
        u, v = np.round(project(K, hand["xyz"])).astype(int).T
        assert silhouette[v, u].all(), f"sample {i}: joints {np.flatnonzero(~silhouette[v, u])} off the mesh"
        box = np.concatenate([project(K, vertices).min(0), project(K, vertices).max(0)])
        box = np.clip(box, 0, [W - 1, H - 1, W - 1, H - 1])
        ys, xs = np.nonzero(depth > 0)
        np.testing.assert_allclose([xs.min(), ys.min(), xs.max(), ys.max()], box, atol=3)   # a thin tip may miss pixel centres


def test_draw_blends_the_mesh_and_draws_skeleton_label_and_side_view(samples):
    quats, betas = samples
    hand = pose_hand(quats[0], betas[0], np.array([0.0, 0.0, 0.5]), "left", track_id=4)
    frame = np.full((H, W, 3), 90, np.uint8)
    o = Overlay(MODEL, alpha=0.5, side=0.3)
    try:
        out = o.draw(frame, K, [hand], [])
        empty = o.draw(frame, K, [], [])
    finally:
        o.release()
    assert out.shape == frame.shape and out.dtype == np.uint8 and not np.shares_memory(out, frame)
    assert (frame == 90).all()                                   # the input is left alone
    u, v = np.round(project(K, hand["xyz"][ROOT_JOINT])).astype(int)
    assert (out[v - 3:v + 4, u - 3:u + 4] != 90).any()          # something was drawn on the hand
    size = int(0.3 * H)
    inset = out[H - size - 8:H - 8, W - size - 8:W - 8]
    assert (inset != empty[H - size - 8:H - 8, W - size - 8:W - 8]).any()   # the side view shows the hand
    outside = np.ones((H, W), bool)
    outside[H - size - 8:H - 8, W - size - 8:W - 8] = False
    assert (empty[outside] == 90).all()                          # no hands: the frame as it came, plus the inset


def test_composite_blends_only_where_a_surface_was_drawn():
    frame = np.full((4, 4, 3), 100, np.uint8)
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 0] = 200                                            # red in RGB
    depth = np.zeros((4, 4), np.float32)
    depth[1, 2] = 0.5
    out = composite(frame, rgb, depth, alpha=0.5)
    assert tuple(out[1, 2]) == (50, 50, 150)                     # BGR: red blended in
    assert (np.delete(out.reshape(-1, 3), 1 * 4 + 2, 0) == 100).all()


def test_skeleton_is_coloured_per_finger_and_skips_missing_joints():
    uv = np.array([[100, 200]] + [[60 + 20 * f + 3 * k, 180 - 25 * k] for f in range(5) for k in range(4)], float)
    img = np.zeros((240, 240, 3), np.uint8)
    draw_skeleton(img, uv, thickness=3, radius=1)
    for f in range(5):
        a, b = uv[1 + 4 * f + 1], uv[1 + 4 * f + 2]               # a bone in the middle of finger f
        x, y = np.round((a + b) / 2).astype(int)
        assert tuple(img[y, x]) == FINGER_COLOURS[f], f
    uv[8] = np.nan                                               # a missing joint: no crash, its bones skipped
    draw_skeleton(np.zeros((240, 240, 3), np.uint8), uv)


def test_side_view_looks_from_the_right():
    near, far = np.array([0.0, 0.0, 0.4]), np.array([0.0, 0.0, 0.6])
    R, t, span = side_view_transform(np.stack([near, far]))
    (un, vn), (uf, vf) = [project(np.eye(3), R @ p + t) for p in (near, far)]
    assert un < uf and abs(vn - vf) < 1e-9                       # depth runs left to right, the camera on the left
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert span >= 0.4


# -- frame pairing ------------------------------------------------------------------------
def msg(stamp, **body):
    return {"header": {"stamp_ns": stamp, "seq": 0, "frame_id": "camera"}, **body}


def test_keep_all_pairs_by_stamp_in_order_and_waits_for_a_slow_pipeline():
    s = FrameSync(keep_all=True, timeout_s=1.0)
    for i in range(4):
        s.add_image(msg(i, data=i), now=0.0)
        s.add_info(msg(i, K=i))
    assert s.pop(now=0.5) == []                                  # nothing paired yet, pipeline just slow
    s.add_keypoints(msg(1, hands=[]))
    s.add_pose(msg(1, hands=["p1"]), now=0.6)                    # frame 0 never gets a pose: the stream passed it
    out = s.pop(now=0.6)
    assert [f.stamp_ns for f in out] == [0, 1] and out[0].pose is None
    assert out[1].pose["hands"] == ["p1"] and out[1].keypoints is not None and out[1].info["K"] == 1
    s.add_pose(msg(2, hands=[]), now=0.7)                        # no keypoints: drawn after the grace period
    assert s.pop(now=0.71) == [] and [f.stamp_ns for f in s.pop(now=0.8)] == [2]
    assert s.pop(now=1.5) == []                                  # frame 3: the last pose came 0.8 s ago
    assert [f.stamp_ns for f in s.pop(now=1.8)] == [3]           # no pose for 1 s: drawn without
    s.add_pose(msg(3, hands=[]), now=1.9)                        # too late: ignored, nothing kept
    assert s.pop(now=2.0) == [] and not s.poses and not s.frames


def test_keep_all_holds_the_previous_pose_over_a_skipped_frame():
    s = FrameSync(keep_all=True, timeout_s=1.0, hold_s=0.1)
    ms = 1_000_000
    for i in range(4):
        s.add_image(msg(i * 33 * ms, data=i), now=0.0)
    for i in (0, 2):                                             # a latest-only detector skipped frames 1 and 3
        s.add_keypoints(msg(i * 33 * ms, hands=[i]))
        s.add_pose(msg(i * 33 * ms, hands=[i]), now=0.1)
    out = s.pop(now=0.1)
    assert [(f.pose["hands"], f.held) for f in out] == [([0], False), ([0], True), ([2], False)]
    assert out[1].keypoints["hands"] == [0]
    f3 = s.pop(now=1.2)                                          # frame 3: the pipeline stalled, no hold
    assert [(f.pose, f.held) for f in f3] == [(None, False)]


def test_live_draws_only_the_newest_paired_frame():
    s = FrameSync(keep_all=False, timeout_s=0.5)
    for i in range(5):
        s.add_image(msg(i, data=i), now=0.0)
    for i in (1, 3):                                             # the detector took frames 1 and 3
        s.add_keypoints(msg(i, hands=[]))
        s.add_pose(msg(i, hands=[]), now=0.1)
    assert [f.stamp_ns for f in s.pop(now=0.1)] == [3]           # 0-2 are dropped, never drawn late
    assert list(s.frames) == [4]
    assert s.pop(now=0.3) == []
    assert [f.stamp_ns for f in s.pop(now=0.7)] == [4]           # no pose for 0.5 s: the camera still shows


def test_flush_returns_every_held_frame():
    s = FrameSync(keep_all=True)
    for i in range(3):
        s.add_image(msg(i, data=i), now=0.0)
    assert [f.stamp_ns for f in s.pop(now=0.0, flush=True)] == [0, 1, 2]


# -- the node in graphs ---------------------------------------------------------------------
def video_frames(path):
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    return n


def test_demo_writes_one_annotated_frame_per_input_frame(tmp_path, run_dir):
    video, bag = tmp_path / "demo.mp4", tmp_path / "demo.mcap"
    r = handlaunch([ROOT / "launch/demo.yaml", f"video:={video}", f"bag:={bag}", "rate:=0"], run_dir, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert video_frames(video) == CLIP_FRAMES
    # every frame was paired with its pose (the detector runs on every frame of a recording)
    assert f"drew {CLIP_FRAMES} frame(s), {CLIP_FRAMES} with their pose" in r.stdout, r.stdout


def test_webcam_graph_writes_every_camera_frame(tmp_path, run_dir):
    """launch/webcam.yaml with a video file as the camera (it plays at its fps, then ends): a
    latest-only detector, yet the MP4 holds every camera frame; bag:= switches the recorder on
    (off by default: tests/test_launch.py)."""
    video, bag = tmp_path / "cam.mp4", tmp_path / "cam.mcap"
    r = handlaunch([ROOT / "launch/webcam.yaml", f"device:={ROOT / 'data/demo/hand_clip.mp4'}", f"video:={video}",
                    f"bag:={bag}"], run_dir, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert video_frames(video) == CLIP_FRAMES and bag.exists()


def test_sigint_leaves_a_finished_mp4(tmp_path, run_dir):
    video = tmp_path / "cut.mp4"
    proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", ROOT / "launch/demo.yaml", f"video:={video}",
                             f"bag:={tmp_path / 'cut.mcap'}", "rate:=0.5"], env=graph_env(run_dir),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 60
    while not video.exists() and time.monotonic() < deadline:   # the first frame is written
        time.sleep(0.1)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    assert "killing" not in out, out                             # stopped in time, not killed
    n = video_frames(video)
    assert 0 < n < CLIP_FRAMES, out
    assert f"wrote {n} to {video}" in out, out                   # every frame written is readable


def test_no_opengl_is_one_error_line(run_dir):
    env = graph_env(run_dir, GLCONTEXT_LINUX_LIBEGL="libEGL-missing.so.1")
    r = subprocess.run([sys.executable, "-m", "handmocap.nodes.visualizer"], env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "no OpenGL through EGL" in lines[0] and "mesh:=false" in lines[0], r.stderr

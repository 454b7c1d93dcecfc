"""The ik node: its maths in-process (mirroring, translation, every HandPose field), the
per-track smoothing, and the node in a real graph fed by `handbag play`."""
import importlib
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import graph_env
from handmocap import bus, camera_info, codec
from handmocap.bag import BagWriter, iter_messages
from handmocap.hand_model import HandModel
from handmocap.ik_solver import IKSolver
from handmocap.pose_data import PoseSampler
from handmocap.rotations import mirror_points, quat_angle_between
from handmocap.skeleton import normalize_joints

ik = importlib.import_module("handmocap.nodes.ik")
MODEL = HandModel.load()
SOLVER = IKSolver.load()
W, H = 640, 480
K = camera_info.default_K(W, H)
FIELDS = {"xyz": (21, 3), "root": (3,), "quat": (21, 4), "pose": (16, 3), "beta": (10,), "uv": (21, 2)}


def synthetic_hands(n, seed, handedness="right", depth=0.6):
    """n HandKeypoints hands of known pose and shape, seen by camera K; the true joints in
    metres (camera frame) and beta. A left hand is the mirror image of the right one."""
    d = PoseSampler(MODEL).sample(n, np.random.default_rng(seed))
    _, joints = MODEL.forward(d["quats"], d["beta"])
    xyz = joints - joints[:, 9:10] + np.array([0.03, -0.02, depth])
    if handedness == "left":
        xyz = mirror_points(xyz)
    uv = (xyz @ K.T)[..., :2] / xyz[..., 2:]
    hands = [{"track_id": 3, "handedness": handedness, "score": 0.9,
              "bbox": np.concatenate([u.min(0), u.max(0)]).astype(np.float32), "uv": u.astype(np.float32),
              "confidence": np.ones(21, np.float32), "xyz_rel": normalize_joints(x).astype(np.float32)}
             for u, x in zip(uv, xyz)]
    return hands, xyz, d


def test_pose_has_every_field_and_recovers_the_hand():
    hands, xyz, d = synthetic_hands(20, 0)
    errors, root_errors = [], []
    for hand, true_xyz, beta in zip(hands, xyz, d["beta"]):
        out = ik.pose_from_keypoints(hand, K, MODEL.rest_joints(beta), SOLVER, MODEL, beta)
        for name, shape in FIELDS.items():
            assert out[name].shape == shape and out[name].dtype == np.float32, name
        assert out["track_id"] == 3 and out["handedness"] == "right" and out["score"] == pytest.approx(0.9)
        assert isinstance(out["translation_valid"], bool)
        np.testing.assert_allclose(out["xyz"][9], out["root"], atol=1e-6)
        codec.encode({"header": codec.header(0), "hands": [out]}, "HandPose")      # schema-valid
        # xyz, quat, pose and beta agree: the model posed by pose (or quat) at beta is xyz
        for pose in (out["pose"], out["quat"]):
            _, joints = MODEL.forward(pose, beta)
            np.testing.assert_allclose(joints - joints[9] + out["root"], out["xyz"], atol=1e-5)
        errors.append(np.linalg.norm(out["xyz"] - true_xyz, axis=-1).mean())
        root_errors.append(np.linalg.norm(out["root"] - true_xyz[9]))
    assert np.median(root_errors) < 0.03, root_errors       # Eq. 5 with IKNet's wrist depth, 0.6 m away
    assert np.median(errors) < 0.04, errors


def test_left_hand_is_solved_in_the_right_model_and_mirrored_back():
    right, _, d = synthetic_hands(5, 1, "right")
    left, true_left, _ = synthetic_hands(5, 1, "left")
    for r, l, true_xyz, beta in zip(right, left, true_left, d["beta"]):
        out_r = ik.pose_from_keypoints(r, K, None, SOLVER, MODEL, beta)
        out_l = ik.pose_from_keypoints(l, K, None, SOLVER, MODEL, beta)
        assert out_l["handedness"] == "left"
        assert np.degrees(quat_angle_between(out_l["quat"], out_r["quat"])).max() < 0.1   # right-model rotations (float32)
        np.testing.assert_allclose(out_l["pose"], out_r["pose"], atol=1e-4)
        # the hand as seen: mirrored positions (K's principal point is at the image centre)
        np.testing.assert_allclose(out_l["xyz"], mirror_points(out_r["xyz"]), atol=1e-3)
        _, joints = MODEL.forward(out_l["quat"], beta, handedness="left")
        np.testing.assert_allclose(joints - joints[9] + out_l["root"], out_l["xyz"], atol=1e-5)
        assert np.linalg.norm(out_l["xyz"] - true_xyz, axis=-1).mean() < 0.05


def test_estimator_uses_track_shapes_smooths_and_resets_lost_tracks():
    hands, _, d = synthetic_hands(1, 2)
    hand = hands[0]
    rng = np.random.default_rng(3)
    jittered = [{**hand, "uv": hand["uv"] + rng.normal(0, 2.0, (21, 2)).astype(np.float32),
                 "xyz_rel": hand["xyz_rel"] + rng.normal(0, 0.02, (21, 3)).astype(np.float32)} for _ in range(60)]
    raw = ik.PoseEstimator(SOLVER, MODEL, {"smooth": False})
    smooth = ik.PoseEstimator(SOLVER, MODEL)
    beta = d["beta"][0]
    for est in (raw, smooth):
        est.set_shapes([{"track_id": 3, "beta": beta, "rest_xyz": normalize_joints(MODEL.rest_joints(beta))}])
    outs = {name: [est.update([h], K, i / 30.0)[0] for i, h in enumerate(jittered)]
            for name, est in (("raw", raw), ("smooth", smooth))}
    np.testing.assert_allclose(outs["smooth"][0]["beta"], beta.astype(np.float32))
    for field in ("root", "quat"):
        jitter = {k: np.abs(np.diff([o[field] for o in v[10:]], axis=0)).mean() for k, v in outs.items()}
        assert jitter["smooth"] < 0.5 * jitter["raw"], (field, jitter)
    # the track disappears for a frame: its filters start afresh (first output = unsmoothed)
    assert smooth.update([], K, 2.1) == []
    first = smooth.update([jittered[5]], K, 2.2)[0]
    np.testing.assert_allclose(first["root"], outs["raw"][5]["root"], atol=1e-6)
    # a hand with missing joints is skipped, the others are solved
    broken = {**hand, "track_id": 4, "xyz_rel": np.full((21, 3), np.nan, np.float32)}
    assert [o["track_id"] for o in smooth.update([broken, hand], K, 2.3)] == [3]


def write_keypoints_bag(path, hands):
    """A bag as the detector would leave it: /camera/info then /hand/keypoints per frame."""
    t0 = time.time_ns()
    with BagWriter(path) as bag:
        for i, hand in enumerate(hands):
            stamp = t0 + i * 33_000_000
            info = {"header": codec.header(i, "camera", stamp), "width": W, "height": H, "K": K,
                    "distortion": np.zeros(5), "source": "default-fov"}
            kp = {"header": codec.header(i, "camera", stamp), "width": W, "height": H,
                  "hands": [] if i == 3 else [hand]}                    # frame 3: no hand
            bag.write("/camera/info", "CameraInfo", codec.encode(info, "CameraInfo"), stamp, stamp)
            bag.write("/hand/keypoints", "HandKeypoints", codec.encode(kp, "HandKeypoints"), stamp, stamp)


def test_ik_node_in_a_graph_fed_by_handbag_play(tmp_path, run_dir):
    hands, _, _ = synthetic_hands(12, 4)
    hands[5] = {**hands[5], "handedness": "left", "track_id": 8}
    src, out = tmp_path / "keypoints.mcap", tmp_path / "pose.mcap"
    write_keypoints_bag(src, hands)
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  ik: {{node: ik, required: true}}
  recorder: {{node: recorder, params: {{output: {out}, topics: [/hand/pose]}}, required: true}}
""")
    env = graph_env(run_dir)
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.launch", str(lf)], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while not any(n.name == "ik" and n.ready for n in bus.read_node_files(run_dir).values()):
            assert time.monotonic() < deadline and graph.poll() is None, "ik node did not start"
            time.sleep(0.05)
        play = subprocess.run([sys.executable, "-m", "handmocap.bag_cli", "play", str(src)], env=env,
                              capture_output=True, text=True, timeout=30)
        assert play.returncode == 0, play.stdout + play.stderr
        log, _ = graph.communicate(timeout=30)
    finally:
        if graph.poll() is None:
            graph.kill()
    assert graph.returncode == 0, log
    poses = [codec.decode(p, t) for _, t, p, _ in iter_messages(out)]
    assert len(poses) == len(hands)                                         # one per keypoints message
    sent = [codec.decode(p, t) for _, t, p, _ in iter_messages(src, ["/hand/keypoints"])]
    assert [m["header"]["stamp_ns"] for m in poses] == [m["header"]["stamp_ns"] for m in sent]
    assert [len(m["hands"]) for m in poses] == [0 if i == 3 else 1 for i in range(len(hands))]
    for i, m in enumerate(poses):
        for h in m["hands"]:
            for name, shape in FIELDS.items():
                assert h[name].shape == shape and h[name].dtype == np.float32, name
            assert h["handedness"] == ("left" if i == 5 else "right")
            assert 0.3 < h["root"][2] < 1.2                               # translated with the bag's K

"""End to end: the demo chain (replay -> detector -> shape -> ik -> recorder, as launch/demo.yaml)
as real processes under handlaunch, on the project's rendered clip with known poses
(data/demo/hand_clip.mp4: 640x480, 30 fps, 90 frames of one right hand; ground truth in
hand_clip.npz from scripts/render_demo_clip.py), replayed in real time (rate 1 = 30 fps).
Everything is read back from the recorded bag.

Metrics (one hand in the clip; per frame the published hand nearest to the truth in the
image, by mean 2D joint distance, is the one scored; the others count as extra hands):
- 3D error, mm: mean over the 21 joints of |xyz - truth| after root and scale alignment
  (handmocap.training.metrics.align_to_ground_truth: the prediction normalized to |joint 0 - joint 9|
  = 1, scaled by the truth's |0-9| and moved onto the truth's joint 9; the paper's and
  `handeval score`'s protocol), then averaged over frames. Of /hand/pose `xyz` (IKNet + FK)
  and, for comparison, of /hand/keypoints `xyz_rel` (DetNet's own 3D).
- 2D error, px: mean over joints and frames of |uv - truth uv| of /hand/pose `uv`.
- root error, mm: median over frames of |root - truth joint 9| in the camera frame (Eq. 5's
  absolute translation; the clip's K is the default 60 degree field of view, which replay
  assumes too).
- handedness: share of frames whose scored hand says "right".
- extra hands: share of frames with more than one published hand (the clip has one).
- latency, ms: capture stamp -> receipt of /hand/pose by the recorder (its MCAP log time),
  p50/p95 over the frames after the first second (while 5 processes start on 2 cores the
  first frames queue up: measured 190-290 ms for frame 0, steady within ~8 frames), and the
  maximum over all frames, start-up included.

Tolerances: named constants below. The DetNet of this commit (models/detnet.onnx, an early
checkpoint) is poor, so the accuracy ones are set from what it measured on this clip with a
margin (measured values in the comments), not from targets; tighten them when the
retrained model lands (the README's figures are the targets). Latency bounds are loose on
purpose: they catch a graph that backs up (a 3 s clip then ages by seconds), not a few
milliseconds on a busy 2-core machine; exact latency figures are benchmarks/bench_e2e.py's.
"""
import shutil
import tempfile

import cv2
import numpy as np
import pytest

from conftest import DEMO_CLIP, DEMO_TRUTH, chain_yaml, handlaunch, pose_latencies_ms, read_bag
from handmocap.perception.hand_model import HandModel
from handmocap.training.metrics import align_to_ground_truth
from handmocap.perception.skeleton import ROOT, normalize_joints

# -- tolerances (measured with models/detnet.onnx of 2026-11-21 20:47, 16,000 iterations) ------
MAX_MEAN_3D_MM = 35.0          # pose xyz, root+scale aligned; measured 24.6 (DetNet's own xyz_rel: 24.3)
MAX_MEAN_2D_PX = 20.0          # pose uv; measured 13.3
MAX_MEDIAN_ROOT_MM = 150.0     # absolute translation; measured 75
MIN_RIGHT_HANDED_SHARE = 0.9   # measured 1.00
MAX_EXTRA_HAND_SHARE = 0.1     # measured 0.00
WARMUP_FRAMES = 30             # the first second: start-up transient, left out of p50/p95
MAX_LATENCY_P50_MS = 150.0     # after the first second; measured 20-28 on 2 cores at load 3-12
MAX_LATENCY_P95_MS = 400.0     # after the first second; measured 28-58
MAX_LATENCY_MS = 3000.0        # any frame, start-up included; measured 190-290 (frame 0)

W, H, N_FRAMES = 640, 480, 90


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The chain run once on the clip at 30 fps; returns (handlaunch result, bag messages)."""
    tmp = tmp_path_factory.mktemp("e2e")
    bag = tmp / "demo.mcap"
    (tmp / "demo.yaml").write_text(chain_yaml(DEMO_CLIP, bag, rate=1.0))
    run_dir = tempfile.mkdtemp(prefix="hm")
    try:
        r = handlaunch([tmp / "demo.yaml"], run_dir, timeout=120)
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
    assert r.returncode == 0, r.stdout + r.stderr
    return r, read_bag(bag)


@pytest.fixture(scope="module")
def truth():
    t = np.load(DEMO_TRUTH)
    assert t["xyz"].shape == (N_FRAMES, 21, 3) and str(t["handedness"]) == "right"
    return t


def frame_index(msgs):
    """{capture stamp ns: frame index} of the replayed images (their header seq counts frames)."""
    return {m["header"]["stamp_ns"]: m["header"]["seq"] for m, _ in msgs["/camera/image"]}


def scored_hands(msgs, topic, truth):
    """[(frame index, scored hand, number of hands)] of `topic`: per message the hand nearest
    to the truth in the image."""
    index = frame_index(msgs)
    out = []
    for m, _ in msgs[topic]:
        i = index[m["header"]["stamp_ns"]]
        if m["hands"]:
            d = [np.linalg.norm(h["uv"] - truth["uv"][i], axis=-1).mean() for h in m["hands"]]
            out.append((i, m["hands"][int(np.argmin(d))], len(m["hands"])))
    return out


def test_every_frame_gives_keypoints_and_a_pose_with_the_hand(demo, truth):
    r, msgs = demo
    assert "Traceback" not in r.stdout + r.stderr
    images = [m for m, _ in msgs["/camera/image"]]
    assert [m["header"]["seq"] for m in images] == list(range(N_FRAMES))
    assert all((m["width"], m["height"], m["data"].shape) == (W, H, (H, W, 3)) for m in images)
    stamps = [m["header"]["stamp_ns"] for m in images]
    for topic in ("/camera/info", "/hand/keypoints", "/hand/shape", "/hand/pose"):
        # one message per frame, in order, carrying the frame's capture stamp
        assert [m["header"]["stamp_ns"] for m, _ in msgs[topic]] == stamps, topic
    # every frame shows the hand (the truth's joints lie inside it): every pose has one
    in_view = np.all((truth["uv"] >= 0) & (truth["uv"] <= [W - 1, H - 1]), axis=(1, 2))
    assert in_view.all()
    hands_per_frame = [len(m["hands"]) for m, _ in msgs["/hand/pose"]]
    assert min(hands_per_frame) >= 1, hands_per_frame


def test_keypoints_and_pose_fields(demo):
    _, msgs = demo
    model = HandModel.load()
    f32 = {"keypoints": {"bbox": (4,), "uv": (21, 2), "confidence": (21,), "xyz_rel": (21, 3)},
           "pose": {"xyz": (21, 3), "root": (3,), "quat": (21, 4), "pose": (16, 3), "beta": (10,), "uv": (21, 2),
                    "confidence": (21,)}}
    keypoints = {m["header"]["stamp_ns"]: m for m, _ in msgs["/hand/keypoints"]}
    for m, _ in msgs["/hand/keypoints"]:
        assert (m["width"], m["height"]) == (W, H) and m["header"]["frame_id"] == "camera"
        for h in m["hands"]:
            for name, shape in f32["keypoints"].items():
                assert h[name].shape == shape and h[name].dtype == np.float32 and np.isfinite(h[name]).all(), name
            assert h["handedness"] in ("left", "right") and 0 <= h["score"] <= 1 and h["track_id"] >= 0
            # xyz_rel is root-relative and scale-normalized
            assert np.linalg.norm(h["xyz_rel"][ROOT]) < 1e-5
            assert np.linalg.norm(h["xyz_rel"][0] - h["xyz_rel"][ROOT]) == pytest.approx(1.0, abs=1e-3)
    for m, _ in msgs["/hand/pose"][::9]:
        kp = {h["track_id"]: h for h in keypoints[m["header"]["stamp_ns"]]["hands"]}
        for h in m["hands"]:
            for name, shape in f32["pose"].items():
                assert h[name].shape == shape and h[name].dtype == np.float32 and np.isfinite(h[name]).all(), name
            # the pose belongs to a hand the detector published in that frame, and keeps its 2D
            assert h["track_id"] in kp and h["handedness"] == kp[h["track_id"]]["handedness"]
            np.testing.assert_array_equal(h["uv"], kp[h["track_id"]]["uv"])
            np.testing.assert_array_equal(h["confidence"], kp[h["track_id"]]["confidence"])
            np.testing.assert_allclose(np.linalg.norm(h["quat"], axis=-1), 1.0, atol=1e-5)
            np.testing.assert_allclose(h["root"], h["xyz"][ROOT], atol=1e-6)
            if h["translation_valid"]:
                assert h["root"][2] > 0   # in front of the camera
            # quat, pose, beta and xyz agree: the model posed by either rotation field is xyz
            for rotations in (h["quat"], h["pose"]):
                _, joints = model.forward(rotations.astype(np.float64), h["beta"].astype(np.float64), h["handedness"])
                np.testing.assert_allclose(joints - joints[ROOT] + h["root"], h["xyz"], atol=2e-5)


def test_graph_keypoints_equal_the_in_process_detector(demo):
    """The graph adds transport, not arithmetic: the same HandDetector run in this process
    on the same decoded frames gives the same keypoints (catches frames lost, reordered or
    paired with the wrong stamp)."""
    from handmocap.perception.detector import HandDetector
    _, msgs = demo
    detector = HandDetector.load()
    cap = cv2.VideoCapture(str(DEMO_CLIP))
    for m, _ in msgs["/hand/keypoints"]:
        ok, frame = cap.read()
        assert ok
        mine = detector.process(frame, m["header"]["stamp_ns"] / 1e9)   # the image's stamp, as the node
        assert [h["track_id"] for h in m["hands"]] == [h["track_id"] for h in mine]
        for theirs, ours in zip(m["hands"], mine):
            np.testing.assert_allclose(theirs["uv"], ours["uv"], atol=1e-3)
            # (normalized here: HandDetector.process passes DetNet's raw 3D on, the node
            # normalizes it as the wire contract says)
            np.testing.assert_allclose(theirs["xyz_rel"], normalize_joints(ours["xyz_rel"]), atol=1e-5)


def accuracy(msgs, truth):
    """The module docstring's metrics of one run."""
    poses = scored_hands(msgs, "/hand/pose", truth)
    idx = np.array([i for i, _, _ in poses])
    xyz = np.stack([h["xyz"] for _, h, _ in poses]).astype(np.float64)
    err3 = np.linalg.norm(align_to_ground_truth(xyz, truth["xyz"][idx]) - truth["xyz"][idx], axis=-1) * 1e3
    kp = scored_hands(msgs, "/hand/keypoints", truth)
    kidx = np.array([i for i, _, _ in kp])
    rel = np.stack([h["xyz_rel"] for _, h, _ in kp]).astype(np.float64)
    err3_kp = np.linalg.norm(align_to_ground_truth(rel, truth["xyz"][kidx]) - truth["xyz"][kidx], axis=-1) * 1e3
    err2 = np.linalg.norm(np.stack([h["uv"] for _, h, _ in poses]) - truth["uv"][idx], axis=-1)
    root = np.linalg.norm(np.stack([h["root"] for _, h, _ in poses]) - truth["xyz"][idx, ROOT], axis=-1) * 1e3
    lat = pose_latencies_ms(msgs)[WARMUP_FRAMES:]
    return {"frames_scored": len(poses),
            "mean_3d_mm": float(err3.mean()), "median_frame_3d_mm": float(np.median(err3.mean(1))),
            "keypoints_mean_3d_mm": float(err3_kp.mean()),
            "mean_2d_px": float(err2.mean()), "median_frame_2d_px": float(np.median(err2.mean(1))),
            "median_root_mm": float(np.median(root)),
            "right_handed_share": float(np.mean([h["handedness"] == "right" for _, h, _ in poses])),
            "extra_hand_share": float(np.mean([n > 1 for _, _, n in poses])),
            "latency_p50_ms": float(np.percentile(lat, 50)), "latency_p95_ms": float(np.percentile(lat, 95)),
            "latency_max_ms": float(lat.max())}


def test_poses_match_the_ground_truth(demo, truth):
    _, msgs = demo
    a = accuracy(msgs, truth)
    print("\nend-to-end accuracy on data/demo/hand_clip.mp4:\n" + "\n".join(f"  {k:22s} {v:9.3f}" for k, v in a.items()))
    assert a["frames_scored"] == N_FRAMES
    assert a["mean_3d_mm"] <= MAX_MEAN_3D_MM, a
    assert a["mean_2d_px"] <= MAX_MEAN_2D_PX, a
    assert a["median_root_mm"] <= MAX_MEDIAN_ROOT_MM, a
    assert a["right_handed_share"] >= MIN_RIGHT_HANDED_SHARE, a
    assert a["extra_hand_share"] <= MAX_EXTRA_HAND_SHARE, a


def test_end_to_end_latency(demo):
    _, msgs = demo
    lat = pose_latencies_ms(msgs)
    assert len(lat) == N_FRAMES and (lat > 0).all()
    p50, p95 = np.percentile(lat[WARMUP_FRAMES:], [50, 95])
    print(f"\ncapture -> /hand/pose receipt at 30 fps after the first second: p50 {p50:.1f} ms, p95 {p95:.1f} ms; "
          f"max {lat.max():.1f} ms (frame {lat.argmax()})")
    assert p50 <= MAX_LATENCY_P50_MS and p95 <= MAX_LATENCY_P95_MS, np.round(lat, 1)
    assert lat.max() <= MAX_LATENCY_MS, np.round(lat, 1)

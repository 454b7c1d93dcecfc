"""HandTracker: every HandPose field from a frame, with a fake DetNet that sees a dot-drawn
projection of a known 3D hand (so the 3D answer is known), then with the real models."""
import cv2
import numpy as np
import pytest

from conftest import ROOT
from handmocap.perception import camera_info
from handmocap.runtime import codec
from handmocap.perception.detector import HandDetector
from handmocap.perception.hand_model import HandModel
from handmocap.training.pose_data import PoseSampler
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import normalize_joints
from handmocap.perception.tracker import HandTracker
from test_detector import DOT_TOL, FakeDetNet, FakeFinder, draw

W, H = 640, 480
K = camera_info.default_K(W, H)
MODEL = HandModel.load()
FIELDS = {"xyz": (21, 3), "root": (3,), "quat": (21, 4), "pose": (16, 3), "beta": (10,), "uv": (21, 2)}
IKNET = ROOT / "models" / "iknet.onnx"
needs_iknet = pytest.mark.skipif(not IKNET.is_file(), reason="models/iknet.onnx not present")


def known_hand(seed=3, depth=0.5):
    """Camera-frame joints (21,3) m of a sampled right hand, open enough for dots to stay apart."""
    d = PoseSampler(MODEL).sample(1, np.random.default_rng(seed))
    _, joints = MODEL.forward(d["quats"][0] * 0 + np.array([1.0, 0, 0, 0]), np.zeros(10))   # flat hand
    rot = cv2.Rodrigues(np.array([0.0, 0.0, np.pi]))[0]          # fingers up in the image
    xyz = (joints - joints[9]) @ rot.T + np.array([0.02, 0.0, depth])
    uv = (xyz @ K.T)[:, :2] / xyz[:, 2:]
    return xyz, uv


def tracker(xyz_right, **kw):
    # the fake DetNet answers the hand's camera-axes 3D whatever the crop, so its crops must not
    # turn (a turned crop's 3D is turned back: test_detector checks that with 2D lifted to 3D)
    det = HandDetector(FakeDetNet(normalize_joints(xyz_right)), FakeFinder(), upright_step=None)
    return HandTracker(detector=det, **kw)


@needs_iknet
def test_every_field_and_the_hand_in_metres():
    xyz, uv = known_hand()
    frame = draw(np.zeros((H, W, 3), np.uint8), uv)
    t = tracker(xyz, smooth=False, vertices=True)
    hands = t.process(frame, K)
    assert len(hands) == 1
    hand = hands[0]
    for name, shape in FIELDS.items():
        assert hand[name].shape == shape and hand[name].dtype == np.float32, name
    assert hand["handedness"] == "right" and 0 <= hand["score"] <= 1
    wire = {k: v for k, v in hand.items() if k not in ("xyz_rel", "vertices")}
    codec.encode({"header": codec.header(0), "hands": [wire]}, "HandPose")      # schema-valid
    np.testing.assert_allclose(hand["uv"], np.round(uv), atol=DOT_TOL)
    assert np.linalg.norm(hand["root"] - xyz[9]) < 0.03                         # Eq. 5 at 0.5 m
    assert np.linalg.norm(hand["xyz"] - xyz, axis=-1).mean() < 0.03
    v = hand["vertices"]
    assert v.shape == (MODEL.v_template.shape[0], 3) and np.linalg.norm(v.mean(0) - hand["root"]) < 0.06


@needs_iknet
def test_left_hand_is_the_mirror_image_and_tracks_keep_their_id():
    xyz, uv = known_hand()
    right = draw(np.zeros((H, W, 3), np.uint8), uv)
    left = np.ascontiguousarray(right[:, ::-1])
    out_r = tracker(xyz, smooth=False).process(right, K)[0]
    t = tracker(xyz, smooth=True)
    outs = [t.process(left, K, stamp_ns=i * 33_000_000)[0] for i in range(5)]
    assert {o["handedness"] for o in outs} == {"left"} and len({o["track_id"] for o in outs}) == 1
    # K's principal point is the image centre, so the mirrored frame shows the mirrored hand
    np.testing.assert_allclose(outs[0]["xyz"], mirror_points(out_r["xyz"]), atol=2e-3)


@needs_iknet
def test_without_K_the_default_field_of_view_is_used():
    xyz, uv = known_hand()
    frame = draw(np.zeros((H, W, 3), np.uint8), uv)
    a = tracker(xyz, smooth=False).process(frame)[0]
    b = tracker(xyz, smooth=False).process(frame, camera_info.default_K(W, H))[0]
    np.testing.assert_allclose(a["xyz"], b["xyz"], atol=1e-6)


DETNET, FINDER = ROOT / "models" / "detnet.onnx", ROOT / "models" / "finder.onnx"


@needs_iknet
def test_hand_length_sets_the_size_and_so_the_depth():
    """Scale-normalized keypoints cannot show size: the hand is as long as hand_length says,
    whatever shape the bone ratios give, and its depth follows (a hand 20% smaller at the same
    pixels is 20% nearer). The shape fit once shrank the hand by a third (issue 28)."""
    xyz, uv = known_hand(depth=0.5)
    frame = draw(np.zeros((H, W, 3), np.uint8), uv)
    average = MODEL.hand_length()
    for scale in (1.0, 0.8):
        t = tracker(xyz, smooth=False, hand_length=scale * average)
        for _ in range(30):                                    # the shape estimate settles in
            hand = t.process(frame, K)[0]
        assert MODEL.hand_length(hand["beta"]) == pytest.approx(scale * average, rel=1e-6)
        knuckle = np.linalg.norm(hand["xyz"][9] - hand["xyz"][0])
        assert knuckle == pytest.approx(scale * np.linalg.norm(xyz[9] - xyz[0]), rel=0.03)
        assert hand["root"][2] == pytest.approx(scale * 0.5, rel=0.05)


@pytest.mark.skipif(not (DETNET.is_file() and FINDER.is_file() and IKNET.is_file()),
                    reason="models/detnet.onnx, finder.onnx or iknet.onnx not committed yet")
def test_real_models_on_the_rendered_clip():
    truth = np.load(ROOT / "data" / "demo" / "hand_clip.npz")
    t = HandTracker()
    cap = cv2.VideoCapture(str(ROOT / "data" / "demo" / "hand_clip.mp4"))
    errors = []
    for i in range(len(truth["xyz"])):
        ok, frame = cap.read()
        hands = t.process(frame, truth["K"], stamp_ns=int(i * 1e9 / truth["fps"]))
        if hands:
            rel = hands[0]["xyz"] - hands[0]["xyz"][9]
            errors.append(np.linalg.norm(rel - (truth["xyz"][i] - truth["xyz"][i][9]), axis=-1).mean())
    assert len(errors) >= 0.9 * len(truth["xyz"])
    assert np.median(errors) < 0.03, np.median(errors)       # root-relative, metres

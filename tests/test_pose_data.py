"""IKNet's training data: pose sampler, emulated detector errors, real sequences."""
import numpy as np
import pytest

from conftest import SHARED_DATA
from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import FINGER_JOINTS, JointLimits
from handmocap.perception.kinematics import forward_kinematics
from handmocap.training.pose_data import (
    _FINGER_ROWS, _GESTURE_STATES, _STATE_TABLE, GESTURES, REAL_DUPLICATES, REAL_EVAL, REAL_TRAIN,
    PositionPairs, PoseSampler, corrupt_joints, load_real_sequences, read_sequence,
)
from handmocap.perception.skeleton import normalize_joints

MODEL = HandModel.load()


def test_samples_are_paired_normalized_and_within_limits():
    d = PoseSampler(MODEL).sample(2000, np.random.default_rng(0))
    np.testing.assert_allclose(d["xyz"][:, 9], 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d["xyz"][:, 0], axis=-1), 1, atol=1e-12)
    # joints are the model posed by the quaternions at the sample's beta
    np.testing.assert_allclose(normalize_joints(forward_kinematics(d["quats"], MODEL.rest_joints(d["beta"]))),
                               d["xyz"], atol=1e-9)
    _, joints = MODEL.forward(d["pose16"][:50], d["beta"][:50])
    np.testing.assert_allclose(normalize_joints(joints), d["xyz"][:50], atol=1e-9)
    assert JointLimits.for_model(MODEL).within(d["pose16"]).mean() >= 0.99
    assert d["quats"][..., 0].min() >= 0
    assert 1.4 < d["beta"].std() < 2.1            # the wide N(0, 3) draw
    # the wrist turns everywhere: palm normals point to all octants
    normal = np.cross(d["xyz"][:, 5] - d["xyz"][:, 0], d["xyz"][:, 17] - d["xyz"][:, 0])
    assert len({tuple(s) for s in np.sign(normal).astype(int)}) == 8


def test_gesture_templates_lie_inside_the_limits():
    """Clipping must not be what shapes a gesture: every template (before noise) is valid."""
    limits = JointLimits.for_model(MODEL)
    for name, states in zip(GESTURES, _GESTURE_STATES):
        angles = np.zeros((15, 3))
        for f in range(5):
            angles[_FINGER_ROWS[f]] = _STATE_TABLE[f][states[f]]
        lo, hi = limits.limits[..., 0], limits.limits[..., 1]
        assert np.all((angles >= lo - 1e-9) & (angles <= hi + 1e-9)), name
        assert limits.within(limits.pose_from_angles(angles)).all(), name
    assert _FINGER_ROWS.ravel().tolist() == [FINGER_JOINTS.index(j) for j in (1, 2, 3, 5, 6, 7, 9, 10, 11,
                                                                             13, 14, 15, 17, 18, 19)]


def test_sampler_is_deterministic_per_seed():
    a = PoseSampler(MODEL).sample(10, np.random.default_rng([3, 7]))
    b = PoseSampler(MODEL).sample(10, np.random.default_rng([3, 7]))
    c = PoseSampler(MODEL).sample(10, np.random.default_rng([3, 8]))
    np.testing.assert_array_equal(a["xyz"], b["xyz"])
    assert not np.allclose(a["xyz"], c["xyz"])


def test_corrupted_joints_are_normalized_and_noisier_with_larger_sigma():
    rng = np.random.default_rng(1)
    xyz = PoseSampler(MODEL).sample(500, rng)["xyz"]
    small = corrupt_joints(xyz, np.random.default_rng(2), sigma_max=0.01, depth_sigma_max=0.01, p_swap=0, p_collapse=0)
    large = corrupt_joints(xyz, np.random.default_rng(2))
    for noisy in (small, large):
        np.testing.assert_allclose(noisy[:, 9], 0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(noisy[:, 0], axis=-1), 1, atol=1e-12)
    err_small = np.linalg.norm(small - xyz, axis=-1).mean()
    err_large = np.linalg.norm(large - xyz, axis=-1)
    assert err_small < 0.02 < err_large.mean()
    depth_err, xy_err = np.abs(large - xyz)[..., 2].mean(), np.abs(large - xyz)[..., :2].mean()
    assert depth_err > 1.5 * xy_err                # a monocular detector errs most in depth


def test_swapped_and_collapsed_fingers():
    xyz = PoseSampler(MODEL).sample(50, np.random.default_rng(4))["xyz"]
    quiet = dict(sigma_max=0.0, depth_sigma_max=0.0)
    swapped = corrupt_joints(xyz, np.random.default_rng(5), p_swap=1.0, p_collapse=0.0, **quiet)
    # every hand has one pair of neighbouring fingers exchanged (knuckles stay)
    for clean, bad in zip(xyz, swapped):
        moved = np.nonzero(np.linalg.norm(bad - clean, axis=-1) > 1e-9)[0]
        assert len(moved) == 6 and not set(moved) & {0, 5, 9, 13, 17}
        fingers = sorted({(j - 1) // 4 for j in moved})
        assert len(fingers) == 2 and fingers[1] - fingers[0] == 1
        a, b = (np.array([f * 4 + k for k in (2, 3, 4)]) for f in fingers)
        np.testing.assert_allclose(bad[a], clean[b], atol=1e-12)
    collapsed = corrupt_joints(xyz, np.random.default_rng(6), p_swap=0.0, p_collapse=1.0, **quiet)
    spans_clean = np.linalg.norm(xyz[:, [4, 8, 12, 16, 20]] - xyz[:, [1, 5, 9, 13, 17]], axis=-1)
    spans_bad = np.linalg.norm(collapsed[:, [4, 8, 12, 16, 20]] - collapsed[:, [1, 5, 9, 13, 17]], axis=-1)
    shrunk = spans_bad < 0.55 * spans_clean
    assert np.all(shrunk.sum(axis=1) == 1)


def test_real_splits_are_disjoint_and_never_touch_the_detector_test_clips():
    assert not set(REAL_TRAIN) & set(REAL_EVAL)
    assert not (set(REAL_TRAIN) | set(REAL_EVAL)) & set(REAL_DUPLICATES)
    assert not any("temugeb_stereo" in name for name in REAL_TRAIN + REAL_EVAL)
    assert load_real_sequences(REAL_TRAIN, root="/nonexistent") == {}


@pytest.mark.skipif(not SHARED_DATA.exists(), reason=f"real data pack {SHARED_DATA} is absent")
def test_real_sequences_mirror_left_hands_and_normalize():
    name = "video/webcam/lujunwang_hand.mediapipe.npz"        # almost all "Left"
    raw = np.load(SHARED_DATA / name)
    world, found, hand = raw["world"][raw["found"]], raw["found"], raw["handedness"][raw["found"]]
    assert (hand == 1).mean() > 0.9
    xyz = read_sequence(SHARED_DATA / name)
    np.testing.assert_allclose(xyz[hand == 1], world[hand == 1] * [-1, 1, 1], atol=1e-6)
    np.testing.assert_allclose(xyz[hand == 0], world[hand == 0], atol=1e-6)
    assert len(xyz) == found.sum()
    seqs = load_real_sequences([name])
    np.testing.assert_allclose(seqs[name][:, 9], 0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(seqs[name][:, 0], axis=-1), 1, atol=1e-9)
    pairs = PositionPairs.from_sequences(seqs, MODEL)
    inputs, targets, rest = pairs.sample(20, np.random.default_rng(0))
    np.testing.assert_allclose(inputs, targets)                 # positional supervision: the joints themselves
    np.testing.assert_allclose(np.linalg.norm(rest[:, 0] - rest[:, 9], axis=-1), 1, atol=1e-9)

import numpy as np
from hypothesis import given, settings, strategies as st

from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.shape import RecentRows, ShapeFitter, ShapeTracker, _column_median, _median_of, _middle, bone_ratios

MODEL = HandModel.load()
FITTER = ShapeFitter(MODEL)
LIMITS = JointLimits.for_model(MODEL)
SIZE = MODEL.beta_names.index("hand_size")


def test_jacobian_matches_finite_differences():
    beta = np.random.default_rng(0).normal(size=10)
    r, jac = FITTER.ratios_and_jacobian(beta)
    eps = 1e-6
    numeric = np.stack([(FITTER.model_ratios(beta + eps * e) - FITTER.model_ratios(beta - eps * e)) / (2 * eps)
                        for e in np.eye(10)], -1)
    assert np.allclose(jac, numeric, atol=1e-7)
    assert np.allclose(r, bone_ratios(MODEL.rest_joints(beta)))


@settings(deadline=None, max_examples=25)
@given(st.integers(0, 2 ** 31))
def test_fit_reproduces_bone_ratios_of_posed_hands(seed):
    rng = np.random.default_rng(seed)
    beta = rng.normal(size=10)
    beta[SIZE] = 0.0        # size is not fitted (test_fit_leaves_the_size_alone)
    _, joints = MODEL.forward(LIMITS.sample(1, rng)[0], beta)
    xyz = (joints - joints[9]) / MODEL.ref_bone_length(beta) * rng.uniform(0.5, 2.0)   # any scale
    fitted = FITTER.fit(xyz)
    err = np.abs(FITTER.model_ratios(fitted) / bone_ratios(xyz) - 1)[FITTER.bones]
    assert err.mean() < 0.01
    assert fitted[SIZE] == 0.0
    # well-observed coefficients come back (finger lengths)
    for name in ("finger_length", "thumb_length", "index_length", "ring_length"):
        k = MODEL.beta_names.index(name)
        assert abs(fitted[k] - beta[k]) < 0.2


def test_fit_leaves_the_size_alone():
    """hand_size scales the hand (and shifts its proportions a little): bone ratios of a small
    or a large hand give hand_size 0, the ratios met by the other coefficients; a free fit had
    traded it against the rest (-4.75 on a real clip: a hand 30% too small)."""
    rng = np.random.default_rng(3)
    for size in (-3.0, 3.0):
        beta = np.zeros(10)
        beta[SIZE] = size
        fitted = FITTER.fit(MODEL.rest_joints(beta))
        assert fitted[SIZE] == 0.0
        err = np.abs(FITTER.model_ratios(fitted) / bone_ratios(MODEL.rest_joints(beta)) - 1)[FITTER.bones]
        assert err.mean() < 0.01
    # the size comes from a hand length instead, exactly, whatever the other coefficients
    for length in (0.15, 0.183, 0.21):
        sized = MODEL.sized(rng.normal(size=10), length)
        assert np.isclose(MODEL.hand_length(sized), length, atol=1e-9)
    assert np.isclose(MODEL.hand_length(MODEL.sized(np.zeros(10), MODEL.hand_length())), MODEL.hand_length())


def test_average_hand_gives_zero_beta():
    assert np.allclose(FITTER.fit(MODEL.rest_joints()), 0, atol=1e-6)
    assert np.allclose(ShapeFitter(MODEL, include_tips=False).fit(MODEL.rest_joints()), 0, atol=1e-6)


def test_tracker_converges_and_ignores_outliers():
    rng = np.random.default_rng(5)
    beta = np.zeros(10)
    beta[MODEL.beta_names.index("finger_length")] = 1.5
    beta[MODEL.beta_names.index("thumb_length")] = -1.5
    _, joints = MODEL.forward(LIMITS.sample(300, rng), beta)
    xyz = (joints - joints[:, 9:10]) / MODEL.ref_bone_length(beta) + rng.normal(0, 0.02, joints.shape)
    xyz[::10] = rng.normal(0, 1.0, (30, 21, 3))        # every 10th frame is garbage
    tracker = ShapeTracker(FITTER)
    errors = []
    for frame in xyz:
        est, n = tracker.update(frame)
        errors.append(np.abs(est - beta)[[1, 2]].max())
    assert n == 300
    assert errors[-1] < 0.35 and errors[-1] < errors[20]
    before = n
    assert tracker.update(np.full((21, 3), np.nan))[1] == before       # non-finite frames are skipped


def test_recent_rows_keep_the_last_window_in_order():
    rows = RecentRows(window=5, columns=2)
    for i in range(23):                          # wraps the buffer (twice the window) several times
        rows.append([i, -i])
        expect = np.arange(max(0, i - 4), i + 1)
        np.testing.assert_array_equal(rows.rows(), np.stack([expect, -expect], axis=1))
    assert len(rows) == 5
    rows.clear()
    assert len(rows) == 0 and rows.rows().shape == (0, 2)


def test_window_medians_are_numpys():
    rng = np.random.default_rng(6)
    for n in (8, 9, 600, 601):
        x = rng.random((n, 20))
        np.testing.assert_array_equal(_column_median(x), np.median(x, axis=0))
        lo, hi = _middle(x)
        np.testing.assert_array_equal(_median_of(np.sqrt(lo), np.sqrt(hi)), np.median(np.sqrt(x), axis=0))


def test_refreshing_the_robust_statistics_every_few_frames_changes_beta_little():
    """Past the first frames the median/MAD are recomputed every 8 frames (speed). With 5%
    joint noise and outlier frames, beta then differs from recomputing them every frame by
    much less than beta itself moves over 8 frames, and is as accurate."""
    rng = np.random.default_rng(7)
    beta = rng.normal(size=10)
    _, joints = MODEL.forward(LIMITS.sample(400, rng), beta)
    xyz = (joints - joints[:, 9:10]) / MODEL.ref_bone_length(beta) + rng.normal(0, 0.05, joints.shape)
    xyz[::13] = rng.normal(0, 1.0, xyz[::13].shape)
    every = ShapeTracker(FITTER, window=200, refresh_every=1, refit_every=1)
    sparse = ShapeTracker(FITTER, window=200, refit_every=1)
    exact = np.array([every.update(frame)[0] for frame in xyz])
    fast = np.array([sparse.update(frame)[0] for frame in xyz])
    np.testing.assert_array_equal(exact[:63], fast[:63])            # every frame while < 64 frames
    moved = np.abs(exact[72:] - exact[64:-8]).max(1)                # beta's own 8-frame motion
    assert np.percentile(np.abs(exact - fast).max(1)[72:], 90) < np.median(moved)
    rms = lambda b: np.sqrt(np.mean((b - beta) ** 2))
    assert abs(rms(fast[-1]) - rms(exact[-1])) < 0.05
    sparse.reset()
    assert sparse._robust is None and sparse.n_samples == 0


def test_refitting_beta_every_few_frames_holds_it_in_between_and_changes_it_little():
    """Past the first 64 frames beta is refitted every 8 frames (speed): in between it holds,
    at each refit it is what refitting every frame gives there, and over the run it stays
    within beta's own 8-frame motion of it."""
    rng = np.random.default_rng(8)
    beta = rng.normal(size=10)
    _, joints = MODEL.forward(LIMITS.sample(300, rng), beta)
    xyz = (joints - joints[:, 9:10]) / MODEL.ref_bone_length(beta) + rng.normal(0, 0.05, joints.shape)
    every, sparse = ShapeTracker(FITTER, window=200, refit_every=1), ShapeTracker(FITTER, window=200)
    exact = np.array([every.update(frame)[0] for frame in xyz])
    fast = np.array([sparse.update(frame)[0] for frame in xyz])
    np.testing.assert_array_equal(exact[:63], fast[:63])
    changes = np.flatnonzero(np.any(fast[64:] != fast[63:-1], axis=1)) + 64
    assert np.all(np.diff(changes) == 8)                                    # held in between
    np.testing.assert_allclose(fast[changes], exact[changes], atol=1e-12)   # the same fit at a refit
    moved = np.abs(exact[72:] - exact[64:-8]).max(1)
    assert np.percentile(np.abs(exact - fast).max(1)[72:], 90) <= np.max(moved)


def test_estimator_never_publishes_more_shapes_than_its_schema_takes():
    """Many short tracks within forget_after_s: the 16 seen last are kept (HandShape maxItems 16)."""
    from handmocap.runtime import codec
    from handmocap.perception.shape import MAX_SHAPES, ShapeEstimator
    est = ShapeEstimator(MODEL)
    xyz = (MODEL.rest_joints() - MODEL.rest_joints()[9]) / MODEL.ref_bone_length()
    for t in range(40):
        shapes = est.update([{"track_id": t, "handedness": "right", "xyz_rel": xyz}], t * 0.01)
    assert [s["track_id"] for s in shapes] == list(range(40 - MAX_SHAPES, 40))
    codec.encode({"header": codec.header(0), "shapes": shapes}, "HandShape")   # schema-valid

import pickle
import sys
import types

import numpy as np
import pytest

from handmocap.perception import kinematics as kin
from handmocap.perception.hand_model import BUNDLED_MODEL, MANO_TIP_VERTICES, HandModel
from handmocap.perception.joint_limits import NAMED_POSES, JointLimits, named_pose
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import MANO_ORDER, NUM_JOINTS

MODEL = HandModel.load()


def test_bundled_model_is_small_and_consistent():
    assert BUNDLED_MODEL.stat().st_size < 3e6
    m = MODEL
    assert m.num_betas == 10 and len(m.beta_names) == 10
    assert m.faces.min() >= 0 and m.faces.max() < len(m.v_template)
    assert np.allclose(m.weights.sum(1), 1.0, atol=1e-5) and (m.weights >= 0).all()
    # canonical frame: wrist at origin, middle MCP on -y, thumb on +x, fingertips curl towards -z (palm)
    j = m.rest_joints()
    assert np.allclose(j[0], 0, atol=1e-6)
    assert np.allclose(j[9, [0, 2]], 0, atol=1e-6) and j[9, 1] < -0.08
    assert j[4, 0] > 0.03 and j[20, 0] < -0.03
    assert 0.08 < m.ref_bone_length() < 0.12
    assert np.allclose(m.v_template[m.tip_vertex_ids], j[[4, 8, 12, 16, 20]], atol=1e-6)


def test_forward_single_and_batch_agree():
    rng = np.random.default_rng(0)
    poses = JointLimits.for_model(MODEL).sample(4, rng)
    betas = rng.normal(size=(4, 10))
    V, J = MODEL.forward(poses, betas)
    assert V.shape == (4, len(MODEL.v_template), 3) and J.shape == (4, NUM_JOINTS, 3)
    v1, j1 = MODEL.forward(poses[2], betas[2])
    assert np.allclose(V[2], v1) and np.allclose(J[2], j1)
    # the same pose given as 21 global quaternions gives the same hand
    v2, j2 = MODEL.forward(kin.relative_to_global_quats(poses[2]), betas[2])
    assert np.allclose(v1, v2, atol=1e-12) and np.allclose(j1, j2, atol=1e-12)
    # joints follow kinematics, tips are mesh vertices
    assert np.allclose(j1, kin.forward_kinematics_relative(poses[2], MODEL.rest_joints(betas[2])))
    assert np.allclose(v1[MODEL.tip_vertex_ids], j1[[4, 8, 12, 16, 20]], atol=1e-6)


def test_rest_pose_and_shape():
    v, j = MODEL.forward(None, None)
    assert np.allclose(v, MODEL.v_template) and np.allclose(j, MODEL.j_template)
    beta = np.zeros(10)
    beta[MODEL.beta_names.index("hand_size")] = 2.0
    assert MODEL.ref_bone_length(beta) > 1.1 * MODEL.ref_bone_length()
    beta = np.zeros(10)
    beta[MODEL.beta_names.index("finger_length")] = 2.0
    j_long = MODEL.rest_joints(beta)
    assert np.linalg.norm(j_long[12] - j_long[9]) > 1.05 * np.linalg.norm(j[12] - j[9])


def test_wrist_rotation_moves_hand_rigidly():
    pose = np.zeros((16, 3))
    pose[0] = [0.3, -1.2, 0.5]
    v, j = MODEL.forward(pose)
    d0 = np.linalg.norm(MODEL.v_template[:, None] - MODEL.v_template[None, :50], axis=-1)
    d1 = np.linalg.norm(v[:, None] - v[None, :50], axis=-1)
    assert np.allclose(d0, d1, atol=1e-9)


def test_left_hand_is_mirrored():
    pose = named_pose("pointing", MODEL)
    v, j = MODEL.forward(pose)
    vl, jl = MODEL.forward(pose, handedness="left")
    assert np.allclose(vl, mirror_points(v)) and np.allclose(jl, mirror_points(j))
    assert np.array_equal(MODEL.faces_for("left"), MODEL.faces[:, ::-1])


def test_named_poses_are_plausible_and_distinct():
    limits = JointLimits.for_model(MODEL)
    tips = []
    for name in NAMED_POSES:
        pose = named_pose(name, MODEL)
        assert limits.within(pose).all()
        tips.append(MODEL.forward(pose)[1][[8, 12]])
    assert len({tuple(np.round(t.ravel(), 3)) for t in tips}) == len(NAMED_POSES)


def test_joint_limits_angles_round_trip_and_reject():
    limits = JointLimits.for_model(MODEL)
    rng = np.random.default_rng(3)
    angles = limits.sample_angles(20, rng)
    pose = limits.pose_from_angles(angles)
    assert np.allclose(limits.angles(pose), angles, atol=1e-9)
    assert limits.within(pose).all()
    assert limits.within(kin.relative_to_global_quats(pose)).all()     # global quaternions read too
    bad = angles.copy()
    bad[:, 4, 0] = np.radians(150)      # index PIP flexed 150 degrees
    bad[:, 6, 1] = np.radians(60)       # middle MCP abducted 60 degrees
    ok = limits.within(limits.pose_from_angles(bad))
    assert not ok[:, 4].any() and not ok[:, 6].any() and ok[:, 0].all()


# ---------------------------------------------------------------- a synthetic MANO file
class _FakeCh:
    """Pickles like chumpy.ch.Ch: class reference plus a state dict holding 'x'."""
    __module__, __qualname__ = "chumpy.ch", "Ch"

    def __init__(self, x):
        self.x = x

    def __getstate__(self):
        return {"x": self.x, "_dirty_vars": set()}


class _FakeCsc:
    __module__, __qualname__ = "scipy.sparse.csc", "csc_matrix"
    def __init__(self, dense):
        cols = [np.nonzero(dense[:, c])[0] for c in range(dense.shape[1])]
        self.indices = np.concatenate(cols)
        self.indptr = np.concatenate([[0], np.cumsum([len(c) for c in cols])])
        self.data = dense.T[dense.T != 0]
        self._shape = dense.shape

    def __getstate__(self):
        return {"data": self.data, "indices": self.indices, "indptr": self.indptr, "_shape": self._shape, "maxprint": 50}


def write_fake_mano(path, monkeypatch):
    """A 778-vertex MANO_RIGHT.pkl whose skeleton is the bundled model's rest skeleton."""
    rng = np.random.default_rng(7)
    rest = MODEL.rest_joints()
    j_mano = rest[MANO_ORDER]                                     # (21,3) MANO order, tips last
    v = rng.normal(scale=0.01, size=(778, 3)) + rest[0]
    v[:16] = j_mano[:16]                                         # vertex k sits on MANO joint k
    v[list(MANO_TIP_VERTICES)] = j_mano[16:]
    regressor = np.zeros((16, 778))
    regressor[np.arange(16), np.arange(16)] = 1.0
    weights = np.zeros((778, 16))
    weights[np.arange(16), np.arange(16)] = 1.0
    weights[16:, 0] = 1.0
    for vid, distal in zip(MANO_TIP_VERTICES, (15, 3, 6, 12, 9)):    # tips move with the distal joint
        weights[vid] = 0.0
        weights[vid, distal] = 1.0
    shapedirs = rng.normal(scale=1e-3, size=(778, 3, 10))
    added = []
    for module, cls, name in (("chumpy.ch", _FakeCh, "Ch"), ("scipy.sparse.csc", _FakeCsc, "csc_matrix")):
        parts = module.split(".")
        for k in range(1, len(parts)):                 # parent packages, unless really installed
            parent = ".".join(parts[:k])
            if parent not in sys.modules:
                monkeypatch.setitem(sys.modules, parent, types.ModuleType(parent))
                added.append(parent)
        mod = types.ModuleType(module)
        setattr(mod, name, cls)
        monkeypatch.setitem(sys.modules, module, mod)
        added.append(module)
    data = {
        "v_template": _FakeCh(v), "shapedirs": _FakeCh(shapedirs), "posedirs": np.zeros((778, 3, 135)),
        "J_regressor": _FakeCsc(regressor), "weights": _FakeCh(weights), "f": np.array([[0, 1, 2], [1, 2, 3]]),
        "kintree_table": np.array([[2 ** 32 - 1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14], np.arange(16)]),
        "hands_mean": rng.normal(size=45), "hands_components": rng.normal(size=(45, 45)), "bs_style": "lbs",
    }
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=2)
    for module in added:                                          # the reader must not need them
        monkeypatch.delitem(sys.modules, module)
    return j_mano, regressor, shapedirs


def test_mano_pickle_is_read_without_chumpy(tmp_path, monkeypatch):
    path = tmp_path / "MANO_RIGHT.pkl"
    j_mano, regressor, shapedirs = write_fake_mano(path, monkeypatch)
    assert "chumpy.ch" not in sys.modules
    mano = HandModel.load(path)
    assert len(mano.v_template) == 778 and mano.num_betas == 10
    assert np.allclose(mano.rest_joints(), MODEL.rest_joints(), atol=1e-12)   # converted to project order
    beta = np.random.default_rng(0).normal(size=10)
    expected = np.concatenate([regressor @ shapedirs.reshape(778, -1), shapedirs[list(MANO_TIP_VERTICES)].reshape(5, -1)])
    assert np.allclose(mano.rest_joints(beta) - mano.rest_joints(), (expected.reshape(21, 3, 10) @ beta)[np.argsort(MANO_ORDER)])
    pose = JointLimits.for_model(MODEL).sample(1, np.random.default_rng(1))[0]
    v, j = mano.forward(pose)
    assert np.allclose(j, MODEL.forward(pose)[1], atol=1e-12)
    assert np.allclose(v[:16], j[MANO_ORDER[:16]], atol=1e-12)             # joint vertices follow their frames
    assert np.allclose(v[list(MANO_TIP_VERTICES)], j[MANO_ORDER[16:]], atol=1e-12)
    assert mano.mean_pose.shape == (16, 3) and np.allclose(mano.mean_pose[0], 0)


def test_rejects_bad_pose_shape():
    with pytest.raises(ValueError):
        MODEL.forward(np.zeros((15, 3)))


def test_renderer_projects_like_the_camera_model():
    pytest.importorskip("moderngl")
    from handmocap.perception.render import MeshRenderer
    try:
        renderer = MeshRenderer(160, 120)
    except Exception as exc:     # no EGL driver on this machine
        pytest.skip(f"no EGL context: {exc}")
    K = np.array([[150.0, 0, 80.0], [0, 150.0, 60.0], [0, 0, 1]])
    v, j = MODEL.forward()
    offset = np.array([0.0, 0.1, 0.6])
    rgb, depth = renderer.render([(v + offset, MODEL.faces)], K)
    assert rgb.shape == (120, 160, 3) and depth.shape == (120, 160)
    palm = j[[0, 5, 9, 13, 17]].mean(0) + offset            # a point inside the palm
    u, w = (K @ palm)[:2] / palm[2]
    assert abs(depth[int(round(w)), int(round(u))] - palm[2]) < 0.03
    assert depth[0, 0] == 0 and (rgb[0, 0] == 255).all()      # background
    assert 0.05 < (depth > 0).mean() < 0.6


def test_a_corrupt_or_missing_model_file_is_one_clear_error(tmp_path):
    cut = tmp_path / "hand_model.npz"
    cut.write_bytes(BUNDLED_MODEL.read_bytes()[:5000])
    with pytest.raises(ValueError, match="not a readable hand model file"):
        HandModel.load(cut)
    with pytest.raises(FileNotFoundError, match="not found"):
        HandModel.load(tmp_path / "missing.npz")
    pickled = tmp_path / "pickled.npz"           # object arrays: numpy's error would suggest allow_pickle
    np.savez(pickled, v_template=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="not an .npz of arrays") as e:
        HandModel.load(pickled)
    assert "allow_pickle" not in str(e.value)

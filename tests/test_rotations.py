import numpy as np
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from handmocap.perception import kinematics as kin
from handmocap.perception import rotations as rot
from handmocap.perception.hand_model import HandModel
from handmocap.perception.skeleton import MANO_ORDER, FROM_MANO_ORDER, NUM_JOINTS

finite = st.floats(-3.0, 3.0, allow_nan=False, width=64)
quats = arrays(np.float64, (4,), elements=finite).filter(lambda q: np.linalg.norm(q) > 1e-3)
axis_angles = arrays(np.float64, (3,), elements=st.floats(-1.8, 1.8, width=64))
poses16 = arrays(np.float64, (16, 3), elements=st.floats(-1.0, 1.0, width=64))
MODEL = HandModel.load()


def same_rotation(qa, qb, atol=1e-9):
    return np.allclose(rot.quat_to_matrix(qa), rot.quat_to_matrix(qb), atol=atol)


@given(quats)
def test_quat_matrix_round_trip(q):
    q = rot.quat_normalize(q)
    R = rot.quat_to_matrix(q)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(rot.matrix_to_quat(R), q, atol=1e-9) or np.isclose(abs(q[0]), 0, atol=1e-9)
    assert same_rotation(rot.matrix_to_quat(R), q)


@given(axis_angles)
def test_axis_angle_round_trips(r):
    assert np.allclose(rot.quat_to_axis_angle(rot.axis_angle_to_quat(r)), r, atol=1e-9)
    assert np.allclose(rot.matrix_to_axis_angle(rot.axis_angle_to_matrix(r)), r, atol=1e-8)


@given(quats, arrays(np.float64, (3,), elements=finite))
def test_quat_rotate_matches_matrix(q, v):
    assert np.allclose(rot.quat_rotate(rot.quat_normalize(q), v), rot.quat_to_matrix(q) @ v, atol=1e-9)


@given(quats, quats)
def test_product_inverse(a, b):
    a, b = rot.quat_normalize(a), rot.quat_normalize(b)
    assert np.allclose(rot.quat_to_matrix(rot.quat_multiply(a, b)), rot.quat_to_matrix(a) @ rot.quat_to_matrix(b), atol=1e-9)
    assert same_rotation(rot.quat_multiply(a, rot.quat_inverse(a)), np.array([1.0, 0, 0, 0]))


@given(quats, quats, st.floats(0.0, 1.0))
def test_slerp_endpoints_and_constant_speed(a, b, t):
    a, b = rot.quat_normalize(a), rot.quat_normalize(b)
    assert same_rotation(rot.quat_slerp(a, b, 0.0), a) and same_rotation(rot.quat_slerp(a, b, 1.0), b)
    total = rot.quat_angle_between(a, b)
    assert np.isclose(rot.quat_angle_between(a, rot.quat_slerp(a, b, t)), t * total, atol=1e-6)


@given(quats, axis_angles, arrays(np.float64, (3,), elements=finite))
def test_mirroring(q, r, p):
    q = rot.quat_normalize(q)
    assert np.allclose(rot.mirror_quat(rot.mirror_quat(q)), q)
    assert np.allclose(rot.mirror_axis_angle(rot.mirror_axis_angle(r)), r)
    assert np.allclose(rot.mirror_points(rot.mirror_points(p)), p)
    # the mirrored rotation acts on mirrored points: M R p = (M R M) (M p)
    assert np.allclose(rot.mirror_points(rot.quat_to_matrix(q) @ p), rot.quat_to_matrix(rot.mirror_quat(q)) @ rot.mirror_points(p), atol=1e-9)
    assert np.allclose(rot.axis_angle_to_matrix(rot.mirror_axis_angle(r)), rot.mirror_matrix(rot.axis_angle_to_matrix(r)), atol=1e-9)


def test_batched_shapes():
    q = rot.quat_normalize(np.random.default_rng(0).normal(size=(5, 7, 4)))
    assert rot.quat_to_matrix(q).shape == (5, 7, 3, 3)
    assert rot.matrix_to_quat(rot.quat_to_matrix(q)).shape == (5, 7, 4)
    assert rot.quat_slerp(q, q[:, ::-1], np.linspace(0, 1, 7)).shape == (5, 7, 4)


def test_fk_of_rest_pose_is_rest_joints():
    rest = MODEL.rest_joints(np.random.default_rng(1).normal(size=10))
    identity = np.tile([1.0, 0, 0, 0], (NUM_JOINTS, 1))
    assert np.allclose(kin.forward_kinematics(identity, rest), rest)
    assert np.allclose(kin.forward_kinematics_relative(np.zeros((16, 3)), rest), rest)


@settings(deadline=None, max_examples=50)
@given(poses16)
def test_relative_global_relative(pose):
    q = kin.relative_to_global_quats(pose)
    back = kin.global_quats_to_relative(q)
    assert np.allclose(rot.axis_angle_to_matrix(back), rot.axis_angle_to_matrix(pose), atol=1e-9)
    rest = MODEL.rest_joints()
    assert np.allclose(kin.forward_kinematics(q, rest), kin.forward_kinematics_relative(pose, rest), atol=1e-12)


@settings(deadline=None, max_examples=30)
@given(poses16)
def test_fk_preserves_bone_lengths(pose):
    from handmocap.perception.shape import bone_lengths
    rest = MODEL.rest_joints()
    assert np.allclose(bone_lengths(kin.forward_kinematics_relative(pose, rest)), bone_lengths(rest))


def test_mano_order_tables():
    assert sorted(MANO_ORDER) == list(range(21))
    x = np.arange(21 * 3).reshape(21, 3)
    assert np.array_equal(x[MANO_ORDER][FROM_MANO_ORDER], x)
    assert MANO_ORDER[13] == 1 and MANO_ORDER[16] == 4 and MANO_ORDER[1] == 5   # thumb1, thumb tip, index1
    p = np.arange(16 * 3).reshape(16, 3)
    assert np.array_equal(kin.pose16_from_mano(kin.pose16_to_mano(p)), p)

"""Forward kinematics of the 21-joint hand and conversions between rotation conventions.

Conventions (shared with HandModel and IKNet):

* Rest pose: the model's template joints `rest` (..., 21, 3). In the rest pose every
  joint frame is aligned with the model frame, so all rotations below are expressed in
  model axes (as in MANO / SMPL), not in bone-aligned axes.
* Joint frames ("relative", MANO-style): the 16 non-tip joints (skeleton.NON_TIP_JOINTS,
  in that order) each carry a rotation relative to their parent's frame:
  G_0 = R_0 (wrist: the global rotation of palm and forearm), G_i = G_parent(i) R_i.
  Pose (16, 3) axis-angle is this R_i.
* Bone rotations ("global", IKNet-style): 21 global rotations q_j. q_0 is the wrist's
  global rotation (palm and forearm; it carries the whole hand). For j >= 1, q_j is the
  global rotation of the bone parent(j) -> j, which is the frame of the parent joint:
  q_j = G_parent(j). Forward kinematics: x_0 = rest_0,
  x_j = x_parent(j) + q_j (rest_j - rest_parent(j)).
  With a rigid palm q_1 = q_5 = q_9 = q_13 = q_17 = q_0; the joint frames read from
  bone rotations use G_0 = q_0 and G_i = q_child(i) (child(i) = i + 1 for i >= 1), so
  those five are used only to place the five joints they end at.
"""
import numpy as np

from handmocap.perception.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_quat, quat_to_matrix
from handmocap.perception.skeleton import MANO_ORDER, NON_TIP_JOINTS, NUM_JOINTS, PARENTS

NON_TIP = np.array(NON_TIP_JOINTS)
# parent of each non-tip joint as an index into NON_TIP (-1 for the wrist)
FRAME_PARENTS = np.array([-1 if PARENTS[j] < 0 else NON_TIP_JOINTS.index(int(PARENTS[j])) for j in NON_TIP])
# for each of the 21 bone rotations, which joint frame it equals: q_0 = G_0, q_j = G_parent(j)
BONE_FRAME = np.array([0] + [NON_TIP_JOINTS.index(int(PARENTS[j])) for j in range(1, NUM_JOINTS)])
# for each joint frame, which bone rotation defines it: G_0 = q_0, G_i = q_(i+1)
FRAME_BONE = np.array([0] + [j + 1 for j in NON_TIP_JOINTS[1:]])
# bone rotations as HandModel.forward uses them (rigid palm: bones 1, 5, 9, 13, 17 take q_0):
# frames_to_bone_rotations(bone_rotations_to_frames(q)) == q[..., RIGID_PALM_BONES]
RIGID_PALM_BONES = FRAME_BONE[BONE_FRAME]
# joints by depth in the tree (1: wrist's children, ..., 4: tips): FK places a level at a time
_DEPTH = np.zeros(NUM_JOINTS, dtype=int)
for _j in range(1, NUM_JOINTS):
    _DEPTH[_j] = _DEPTH[PARENTS[_j]] + 1
FK_LEVELS = [np.flatnonzero(_DEPTH == d) for d in range(1, _DEPTH.max() + 1)]
# MANO's 16 rotating joints as indices into NON_TIP: pose_mano = pose16[..., POSE16_TO_MANO, :]
POSE16_TO_MANO = np.array([NON_TIP_JOINTS.index(int(j)) for j in MANO_ORDER[:16]])
POSE16_FROM_MANO = np.argsort(POSE16_TO_MANO)


def as_matrices(rot):
    """Rotations given as (..., K, 3) axis-angle, (..., K, 4) quaternions or (..., K, 3, 3)
    matrices -> (..., K, 3, 3). A (K, 3, 3) input is taken as matrices."""
    rot = np.asarray(rot, dtype=np.float64)
    if rot.shape[-2:] == (3, 3):
        return rot
    if rot.shape[-1] == 4:
        return quat_to_matrix(rot)
    if rot.shape[-1] == 3:
        return axis_angle_to_matrix(rot)
    raise ValueError(f"cannot read rotations of shape {rot.shape}")


def relative_to_frames(rel):
    """(..., 16, 3, 3) relative joint rotations -> (..., 16, 3, 3) global joint frames G."""
    rel = np.asarray(rel, dtype=np.float64)
    frames = [rel[..., 0, :, :]]
    for i in range(1, len(NON_TIP)):   # parents come before children
        frames.append(frames[FRAME_PARENTS[i]] @ rel[..., i, :, :])
    return np.stack(frames, axis=-3)


def frames_to_relative(frames):
    """(..., 16, 3, 3) global joint frames -> (..., 16, 3, 3) relative: R_i = G_parentᵀ G_i."""
    frames = np.asarray(frames, dtype=np.float64)
    parent = frames[..., np.maximum(FRAME_PARENTS, 0), :, :]
    rel = np.swapaxes(parent, -1, -2) @ frames
    rel[..., 0, :, :] = frames[..., 0, :, :]
    return rel


def frames_to_bone_rotations(frames):
    """(..., 16, 3, 3) joint frames -> (..., 21, 3, 3) bone rotations q (see module doc)."""
    return np.asarray(frames, dtype=np.float64)[..., BONE_FRAME, :, :]


def bone_rotations_to_frames(bones):
    """(..., 21, 3, 3) bone rotations -> (..., 16, 3, 3) joint frames (see module doc)."""
    return np.asarray(bones, dtype=np.float64)[..., FRAME_BONE, :, :]


def relative_to_global_quats(pose):
    """MANO-style relative pose (..., 16, 3) axis-angle (or (..., 16, 4) / (..., 16, 3, 3))
    -> (..., 21, 4) global bone quaternions, w >= 0."""
    return matrix_to_quat(frames_to_bone_rotations(relative_to_frames(as_matrices(pose))))


def global_quats_to_relative(quats):
    """(..., 21, 4) global bone quaternions (or (..., 21, 3, 3) matrices) -> (..., 16, 3)
    relative axis-angle pose."""
    return matrix_to_axis_angle(frames_to_relative(bone_rotations_to_frames(as_matrices(quats))))


def forward_kinematics(bones, rest):
    """Joint positions from bone rotations.

    bones: (..., 21, 3, 3) or (..., 21, 4) global bone rotations q_j.
    rest: (..., 21, 3) rest-pose joints (any unit). Returns (..., 21, 3), same unit;
    the wrist stays at rest[..., 0, :].
    """
    R = as_matrices(bones)
    rest = np.asarray(rest, dtype=np.float64)
    offsets = rest - rest[..., np.maximum(PARENTS, 0), :]          # rest bones parent -> j
    bone_vecs = (R @ offsets[..., None])[..., 0]
    joints = np.empty(np.broadcast_shapes(bone_vecs.shape, rest.shape))
    joints[..., 0, :] = rest[..., 0, :]
    for level in FK_LEVELS:          # x_j = x_parent(j) + q_j (rest_j - rest_parent(j)), a tree level at a time
        joints[..., level, :] = joints[..., PARENTS[level], :] + bone_vecs[..., level, :]
    return joints


def forward_kinematics_relative(pose, rest):
    """Joint positions (..., 21, 3) from a relative pose (..., 16, 3|4|3x3) and rest joints."""
    return forward_kinematics(frames_to_bone_rotations(relative_to_frames(as_matrices(pose))), rest)


def pose16_to_mano(pose16):
    """(..., 16, C) per-joint values in project order -> MANO's joint order."""
    return np.asarray(pose16)[..., POSE16_TO_MANO, :]


def pose16_from_mano(pose_mano):
    """(..., 16, C) per-joint values in MANO's joint order -> project order."""
    return np.asarray(pose_mano)[..., POSE16_FROM_MANO, :]


def joints_to_mano(xyz):
    """(..., 21, C) joints in project order -> MANO order (16 joints, then tips T I M R L)."""
    return np.asarray(xyz)[..., MANO_ORDER, :]

"""Inverse kinematics: global joint rotations from 3D joints (paper Sec. 3.3), no torch.

IKSolver runs IKNet in onnxruntime:

    solver = IKSolver.load()                 # models/iknet_int8.onnx; "float32": models/iknet.onnx
    quats = solver.solve(xyz_rel)            # (N,21,3) -> (N,21,4), w >= 0
    _, joints = HandModel.load().forward(quats[0], beta)

Two files of one network: models/iknet.onnx (float32, written by `handtrain iknet`) and
models/iknet_int8.onnx (static int8 with fixed activation ranges, made from it by
`python -m handmocap.training.quantize_iknet`; each row of a batch is computed on its own). The
int8 file is the default: a quarter of the weights to stream per hand (about 0.3 ms
instead of 1 ms at batch 1) for about 0.1 deg more rotation error (docs/models_history.md).

Input encoding (the paper's I = [X, D, X_ref, D_ref], 4 x 21 x 3 = 252 values):
X joints and X_ref rest joints, both root-relative (joint 9) and scale-normalized
(|x0 - x9| = 1); D, D_ref their bone vectors x_j - x_parent(j) (root row zero).

One step beyond the paper (iknet_inputs / iknet_outputs): X is first turned into a
canonical palm frame measured from the joints themselves (canonical_frame: y along the
reference bone, x across the knuckles), and the network's rotations are turned back.
The network then never sees the global orientation, which is exact geometry, not something
to learn: the same 6 x 1024 MLP spends its capacity on the fingers, and the quaternion
sign ambiguity (q and -q) no longer cuts through the training data at w = 0.

analytic_ik is the baseline for the evaluation table: the wrist from the palm joints
(Kabsch), then each finger bone the smallest rotation (no twist) that turns its rest
direction into the observed one, in its parent's frame.
"""
import warnings
from pathlib import Path

import numpy as np

from handmocap.perception import onnx_models
from handmocap.perception.kinematics import FRAME_BONE, PARENTS
from handmocap.perception.onnx_models import open_session
from handmocap.perception.rotations import matrix_to_quat, quat_left_matrix, quat_normalize, quat_to_matrix
from handmocap.perception.skeleton import NON_TIP_JOINTS, NUM_JOINTS, normalize_joints

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"
FLOAT32_MODEL = MODELS_DIR / "iknet.onnx"          # written by `handtrain iknet`
INT8_MODEL = MODELS_DIR / "iknet_int8.onnx"        # made from it by `python -m handmocap.training.quantize_iknet`
DEFAULT_MODEL = INT8_MODEL
MODEL_NAMES = {"int8": INT8_MODEL, "float32": FLOAT32_MODEL}   # short names for IKSolver.load / the ik node
PALM_JOINTS = [0, 1, 5, 9, 13, 17]          # rigid with the wrist frame (q_1 = q_5 = ... = q_0)
_WITH_RIGID_PALM = np.array([0 if j in PALM_JOINTS else j for j in range(21)])   # network row per bone
BONE_PARENT_FRAME = np.maximum(PARENTS, 0)  # q_0 = G_0, q_j = G_parent(j)
NUM_INPUTS = 4 * NUM_JOINTS * 3


def bone_vectors(xyz):
    """(..., 21, 3) joints -> (..., 21, 3) bones x_j - x_parent(j); row 0 is zero."""
    xyz = np.asarray(xyz, dtype=np.float64)
    return xyz - xyz[..., np.maximum(PARENTS, 0), :]


# (42, 21): joints then bone vectors, [X; D] = _JOINTS_AND_BONES @ X (entries 0, +-1: exact)
_JOINTS_AND_BONES = np.concatenate([np.eye(NUM_JOINTS),
                                    np.eye(NUM_JOINTS) - np.eye(NUM_JOINTS)[np.maximum(PARENTS, 0)]])
_JOINTS_AND_BONES[NUM_JOINTS] = 0.0                 # the root has no bone
_NEXT, _PREV = [1, 2, 0], [2, 0, 1]


def _cross(a, b):
    """(..., 3) x (..., 3) -> (..., 3) cross product (np.cross costs several times more on tiny arrays)."""
    return a[..., _NEXT] * b[..., _PREV] - a[..., _PREV] * b[..., _NEXT]


def _unit(v):
    """(..., 3) vectors -> unit vectors (zero vectors stay zero)."""
    return v / np.maximum(np.sqrt(np.sum(v * v, axis=-1, keepdims=True)), 1e-12)


def canonical_frame(xyz):
    """(..., 3, 3) palm frames, columns (e_x, e_y, e_z) in camera axes: e_y along 9 -> 0
    (the reference bone, toward the wrist), e_x across the knuckles 17 -> 5 made
    orthogonal to it, e_z = e_x x e_y. For the hand model at rest this is about identity."""
    xyz = np.asarray(xyz, dtype=np.float64)
    e_y = _unit(xyz[..., 0, :] - xyz[..., 9, :])
    across = xyz[..., 5, :] - xyz[..., 17, :]
    e_x = _unit(across - np.sum(across * e_y, axis=-1, keepdims=True) * e_y)
    return np.stack([e_x, e_y, _cross(e_x, e_y)], axis=-1)


def rest_features(rest):
    """(..., 21, 3) normalized rest joints -> (..., 42, 3) [X_ref; D_ref], the rest half of
    the network input (depends on the person only: callers may keep it between frames)."""
    return _JOINTS_AND_BONES @ np.asarray(rest, dtype=np.float64)


def iknet_inputs(xyz, rest, rest_part=None):
    """Network input (N, 252) float32 and palm frames F (N, 3, 3).

    xyz (N,21,3) joints (normalized here); rest (N,21,3) or (21,3) normalized rest joints
    (or rest_part, their rest_features, instead). The joints enter in the palm frame:
    x_c = Fᵀ x; input [X_c; D_c; X_ref; D_ref] row by row.
    """
    xyz = normalize_joints(xyz)
    frame = canonical_frame(xyz)
    features = np.empty((len(xyz), 4 * NUM_JOINTS, 3), dtype=np.float32)   # (N,84,3), filled in place
    features[:, :2 * NUM_JOINTS] = _JOINTS_AND_BONES @ (xyz @ frame)         # rows (Fᵀ x)ᵀ, then bones
    features[:, 2 * NUM_JOINTS:] = rest_features(rest) if rest_part is None else rest_part
    return features.reshape(len(xyz), NUM_INPUTS), frame


def iknet_outputs(raw, frame):
    """Raw network output (N, 84) in the palm frame -> (N,21,4) unit quaternions in camera
    axes (R = F R_c), w >= 0. The palm bones 0 -> 1, 5, 9, 13, 17 get the wrist's rotation,
    as the hand model's rigid palm has it (HandModel.forward uses q_0 for them)."""
    q_c = np.asarray(raw, dtype=np.float64).reshape(-1, NUM_JOINTS, 4)[:, _WITH_RIGID_PALM]
    left = quat_left_matrix(matrix_to_quat(frame))                           # (N,4,4): q_F * q = L q
    return quat_normalize(q_c @ np.swapaxes(left, -1, -2))


def model_path(path=None):
    """IKNet file for IKSolver.load: None -> DEFAULT_MODEL (int8); "int8" / "float32" -> the
    bundled files; anything else is a path."""
    if path is None:
        return DEFAULT_MODEL
    return MODEL_NAMES.get(str(path), Path(path))


def stale_quantization(session, path):
    """onnx_models.stale_quantization for an int8 IKNet file."""
    return onnx_models.stale_quantization(session, path, "python -m handmocap.training.quantize_iknet")


class IKSolver:
    """IKNet in onnxruntime. threads: intra-op threads (1 leaves the second core of a
    2-core CPU to the detector; the network is small enough that 2 gain little)."""

    def __init__(self, session, rest):
        self.session = session
        self.input_name = session.get_inputs()[0].name
        self.rest = normalize_joints(rest)
        self.rest_part = rest_features(self.rest)
        self._last_rest = (None, None)       # (rest as given, its rest_features): one person per call site

    @classmethod
    def load(cls, path=None, threads=1, model=None):
        """IKNet from `path`: None for the default (models/iknet_int8.onnx), "int8" or
        "float32" for the bundled files, or a file. The default rest pose is the hand model's
        (model, default the bundled one) at beta = 0. Warns when an int8 file is older than
        the float32 network beside it."""
        path = model_path(path)
        made_by = "python -m handmocap.training.quantize_iknet" if path == INT8_MODEL else "handtrain iknet"
        session = open_session(path, "IKNet", made_by, threads)
        stale = stale_quantization(session, path)
        if stale:
            warnings.warn(stale, stacklevel=2)
        if model is None:
            from handmocap.perception.hand_model import HandModel
            model = HandModel.load()
        return cls(session, model.rest_joints())

    def _rest_part(self, rest):
        """rest_features of the normalized rest (21,3) or (N,21,3); the last one is kept,
        since a tracked person's rest pose comes back unchanged frame after frame."""
        if rest is None:
            return self.rest_part
        rest = np.asarray(rest, dtype=np.float64)
        last, part = self._last_rest
        if last is not None and last.shape == rest.shape and np.array_equal(last, rest):
            return part
        part = rest_features(normalize_joints(rest))
        self._last_rest = (rest.copy(), part)
        return part

    def solve(self, xyz_rel, rest=None):
        """Global bone quaternions (N,21,4) (w,x,y,z), w >= 0, for joints xyz_rel (N,21,3)
        or (21,3) (root-relative, scale-normalized, camera axes, right hand); rest (21,3)
        or (N,21,3): the person's rest joints (any scale/origin; default the average hand).
        A (21,3) input gives a (1,21,4) output."""
        xyz = np.asarray(xyz_rel, dtype=np.float64).reshape(-1, NUM_JOINTS, 3)
        features, frame = iknet_inputs(xyz, None, rest_part=self._rest_part(rest))
        raw = self.session.run(None, {self.input_name: features})[0]
        return iknet_outputs(raw, frame)


# -------------------------------------------------------------------- analytic baseline
def _kabsch(src, dst):
    """(..., K, 3) point sets -> (..., 3, 3) rotation R minimising |R src - dst| (centred)."""
    src = src - src.mean(axis=-2, keepdims=True)
    dst = dst - dst.mean(axis=-2, keepdims=True)
    u, _, vt = np.linalg.svd(np.swapaxes(dst, -1, -2) @ src)
    d = np.sign(np.linalg.det(u @ vt))
    u = np.concatenate([u[..., :2], u[..., 2:] * d[..., None, None]], axis=-1)
    return u @ vt


def _swing(a, b):
    """(..., 3, 3) smallest rotation turning directions a into b (..., 3)."""
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    q = np.concatenate([1.0 + np.sum(a * b, axis=-1, keepdims=True), np.cross(a, b)], axis=-1)
    # opposite directions: any half turn about an axis orthogonal to a
    ortho = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0, 0], [0, 1.0, 0]))
    q = np.where(q[..., :1] < 1e-9, np.concatenate([np.zeros_like(q[..., :1]), ortho], axis=-1), q)
    return quat_to_matrix(quat_normalize(q))


def analytic_ik(xyz_rel, rest):
    """Baseline IK: (N,21,3) joints, (21,3) or (N,21,3) rest -> (N,21,4) global bone quaternions.

    Wrist frame G_0: Kabsch fit of the rest palm joints onto the observed ones. Each finger
    joint frame G_i = swing(G_parent (rest_(i+1) - rest_i) -> x_(i+1) - x_i) G_parent; bone
    rotations q_j = G_parent(j).
    """
    xyz = normalize_joints(np.asarray(xyz_rel, dtype=np.float64).reshape(-1, NUM_JOINTS, 3))
    rest = np.broadcast_to(normalize_joints(rest), xyz.shape)
    frames = np.empty(xyz.shape[:1] + (NUM_JOINTS, 3, 3))
    frames[:, 0] = _kabsch(rest[:, PALM_JOINTS], xyz[:, PALM_JOINTS])
    for i in NON_TIP_JOINTS[1:]:                  # parents first
        G = frames[:, PARENTS[i]]
        rest_dir = (G @ (rest[:, i + 1] - rest[:, i])[..., None])[..., 0]
        frames[:, i] = _swing(rest_dir, xyz[:, i + 1] - xyz[:, i]) @ G
    return matrix_to_quat(frames[:, BONE_PARENT_FRAME])


# bone j >= 1 that is not a palm bone ends at a finger joint's child: q_j = G_parent(j). In
# FINGER_JOINTS order the 15 finger frames are the rotations of bones 2,3,4, 6,7,8, ...
_FINGER_FRAME_BONES = np.array([j + 1 for j in NON_TIP_JOINTS[1:]])


def clamp_to_limits(quats, limits):
    """(N,21,4) global bone quaternions -> the same with every finger joint's (flexion,
    abduction, twist) clipped into `limits` (a JointLimits), keeping each finger bone
    pointing where the input points it as far as the limits allow; the wrist is kept. The
    result is normalized (w >= 0) and the five palm bones carry the wrist's rotation (the
    model's rigid palm).

    Down each finger, parents first: the joint's rotation relative to its (possibly clipped)
    parent is read in its anatomical frame as L = Rx(flexion) Ry(abduction) Rz(twist). The
    bone's direction L e_z fixes flexion and abduction, which are clipped; the twist (the
    bone's turn about itself) is clipped on its own, and the joints below then turn to
    point their bones where the input did, as far as their own limits allow (a DIP's twist
    moves no joint at all). Joints inside their limits under an unchanged parent keep their
    rotation exactly. Clipping the three Euler angles of the relative rotation
    independently (until session 14) moved the bone whenever IKNet's guessed twist was out
    of range: on real clips its index, ring and little finger joints came out turned by up
    to +-150 degrees, and the clip put those fingers somewhere else."""
    shape = np.shape(quats)
    q = quat_normalize(np.reshape(quats, (-1, NUM_JOINTS, 4)))               # (N,21,4)
    frames = quat_to_matrix(q[:, FRAME_BONE])                                 # (N,16,3,3) joint frames G
    n = len(q)
    G = frames[:, 1:].reshape(n, 5, 3, 3, 3)                                  # (N, finger, level, 3, 3)
    g, levels = frames[:, :1], []                                             # the wrist, for all five
    for level in range(3):                                                    # down the five chains at once
        joints = slice(level, None, 3)                                        # this level of each finger
        rel = np.swapaxes(g, -1, -2) @ G[:, :, level]                         # (N,5,3,3) Gpᵀ G
        # Rx(flexion) Ry(abduction) sends the bone (local e_z) where it points, Rz(twist) turns it
        angles = limits.angles_from_relative(rel, joints)
        angles = np.clip(angles, limits.limits[joints, :, 0], limits.limits[joints, :, 1])
        g = g @ limits.relative_from_angles(angles, joints)
        levels.append(g)
    q[:, _FINGER_FRAME_BONES] = matrix_to_quat(np.stack(levels, axis=2).reshape(n, 15, 3, 3))
    q[:, PALM_JOINTS[1:]] = q[:, :1]
    return q.reshape(shape)

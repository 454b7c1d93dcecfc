"""Training and evaluation data for IKNet: plausible hand poses, their joints, emulated
detector errors and real 3D joint sequences (paper Sec. 3.3, "MoCap data" and "3DPosData").

Everything is numpy, vectorised over a batch, and made on the fly from a seed.

Pose samples (PoseSampler.sample) pair 21 global bone quaternions with the joints they
put the hand model in, both in the conventions of handmocap.perception.kinematics:
    pose16 (N,16,3)  relative axis-angle        quats (N,21,4) global bone rotations, w >= 0
    beta   (N,10)    shape                      rest  (N,21,3) rest joints at beta, normalized
    xyz    (N,21,3)  posed joints, normalized (root joint 9 at the origin, |x0 - x9| = 1)
The finger angles come from a mixture (fingers independent of each other, as the paper's
augmentation assumes):
* uniform within the anatomical limits (JointLimits), joint by joint;
* per-finger templates (straight, curled, half-closed, hooked, pinching, ...) with noise;
* whole-hand gestures that uniform sampling rarely hits: fists, grasps, pinches, the OK
  sign and the counting gestures, each a template per finger, with noise.
Angles are clipped to the limits, then the pose is moved toward the rest pose by
quaternion interpolation (slerp from the identity scales each relative axis-angle vector),
the wrist gets a uniformly random global rotation, and beta ~ N(0, 3) (variance 3: the
paper's wide shape draw; beta_k ~ N(0, 1) spans adult hands in the bundled model).

Emulated detector errors (corrupt_joints): per-joint Gaussian noise, extra depth noise
(a monocular detector's worst axis) with a per-finger depth offset, and occasionally a
finger swapped with its neighbour or collapsed toward its knuckle; the result is
normalized again, as a detector's output is.

Real sequences (load_real_sequences): MediaPipe world landmarks of the clips in
../shared/data beside the repository (not ground truth: roughly metric, viewpoint-dependent bone lengths),
left hands mirrored into the right-hand model, normalized. REAL_TRAIN clips may be used as
positional supervision; REAL_EVAL clips are held back. temugeb_stereo is never read here:
it is an evaluation split of the detector.
"""
import json
import pickle
from pathlib import Path

import numpy as np

from handmocap.perception.ik_solver import iknet_inputs, normalize_joints
from handmocap.perception.joint_limits import FINGER_JOINTS, JointLimits
from handmocap.perception.kinematics import forward_kinematics, relative_to_global_quats
from handmocap.perception.rotations import matrix_to_axis_angle, matrix_to_quat, mirror_points, quat_to_matrix
from handmocap.perception.skeleton import REF_BONE

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
BETA_STD = np.sqrt(3.0)

# -------------------------------------------------------------------- angle templates
# (flexion, abduction, twist) degrees for the 3 joints of a finger, base to tip
FINGER_STATES = {
    "straight": ((0, 0, 0), (0, 0, 0), (0, 0, 0)),
    "curled": ((85, 0, 0), (100, 0, 0), (65, 0, 0)),        # in a fist
    "half": ((45, 0, 0), (60, 0, 0), (40, 0, 0)),           # around a cylinder
    "hook": ((5, 0, 0), (95, 0, 0), (70, 0, 0)),            # carrying a bag
    "table": ((80, 0, 0), (5, 0, 0), (5, 0, 0)),            # MCP only, fingers straight
    "pinch": ((45, 0, 0), (50, 0, 0), (25, 0, 0)),          # tip toward the thumb's tip
    "back": ((-25, 0, 0), (0, 0, 0), (0, 0, 0)),            # hyperextended
}
THUMB_STATES = {
    "out": ((-10, 10, 0), (0, 0, 0), (0, 0, 0)),
    "tucked": ((25, 20, 15), (45, 0, 0), (60, 0, 0)),       # across the curled fingers
    "pinch": ((30, 40, 15), (20, 0, 0), (25, 0, 0)),        # opposed, tip toward the index tip
    "across": ((45, 10, 10), (50, 0, 0), (40, 0, 0)),       # folded onto the palm ("four")
    "up": ((-15, 30, 0), (0, 0, 0), (0, 0, 0)),             # thumbs-up, abducted
    "grasp": ((20, 35, 10), (25, 0, 0), (30, 0, 0)),        # around a cylinder
}
# whole-hand gestures: (thumb, index, middle, ring, little) states
GESTURES = {
    "fist": ("tucked", "curled", "curled", "curled", "curled"),
    "one": ("tucked", "straight", "curled", "curled", "curled"),
    "two": ("tucked", "straight", "straight", "curled", "curled"),
    "three": ("tucked", "straight", "straight", "straight", "curled"),
    "three_thumb": ("out", "straight", "straight", "curled", "curled"),
    "four": ("across", "straight", "straight", "straight", "straight"),
    "five": ("out", "straight", "straight", "straight", "straight"),
    "thumbs_up": ("up", "curled", "curled", "curled", "curled"),
    "ok": ("pinch", "pinch", "straight", "straight", "straight"),
    "pinch": ("pinch", "pinch", "half", "half", "half"),
    "cylinder": ("grasp", "half", "half", "half", "half"),
    "hook": ("out", "hook", "hook", "hook", "hook"),
    "horns": ("tucked", "straight", "curled", "curled", "straight"),
    "shaka": ("out", "curled", "curled", "curled", "straight"),
    "flat_mcp": ("out", "table", "table", "table", "table"),
}
NOISE_DEG = np.array([10.0, 5.0, 3.0])       # template noise per (flexion, abduction, twist)
SPREAD_DEG = 12.0                            # MCP abduction spread added to gestures (fan of fingers)
_FINGERS = ((1, 2, 3), (5, 6, 7), (9, 10, 11), (13, 14, 15), (17, 18, 19))
_FINGER_ROWS = np.array([[FINGER_JOINTS.index(j) for j in f] for f in _FINGERS])   # (5,3) rows of angles
_STATE_NAMES = (tuple(THUMB_STATES),) + (tuple(FINGER_STATES),) * 4
_STATE_TABLE = [np.radians(np.array([THUMB_STATES[s] for s in THUMB_STATES], dtype=np.float64))] + \
    [np.radians(np.array([FINGER_STATES[s] for s in FINGER_STATES], dtype=np.float64))] * 4  # (S,3,3) each
_GESTURE_STATES = np.array([[_STATE_NAMES[f].index(s) for f, s in enumerate(g)] for g in GESTURES.values()])


def random_rotations(n, rng):
    """(n, 3) axis-angle of rotations uniform over SO(3) (normalized Gaussian quaternions)."""
    q = rng.normal(size=(n, 4))
    return matrix_to_axis_angle(quat_to_matrix(q))


class PoseSampler:
    """Plausible hand poses of one hand model, with joints, made on the fly.

    p_uniform / p_gesture: shares of samples whose fingers are uniform within the limits /
    a whole-hand gesture; the rest pick a template state per finger independently.
    p_interpolate: share of samples moved toward rest by slerp with t ~ U(0, 1).
    """

    def __init__(self, model, p_uniform=0.35, p_gesture=0.3, p_interpolate=0.4, beta_std=BETA_STD):
        self.model = model
        self.limits = JointLimits.for_model(model)
        self.p_uniform, self.p_gesture, self.p_interpolate = p_uniform, p_gesture, p_interpolate
        self.beta_std = beta_std

    def sample_angles(self, n, rng):
        """(n, 15, 3) anatomical finger angles (radians) from the mixture, within the limits."""
        uniform = self.limits.sample_angles(n, rng)
        kind = rng.random(n)
        per_finger = np.stack([rng.integers(len(t), size=n) for t in _STATE_TABLE], axis=1)     # (n,5)
        gesture = _GESTURE_STATES[rng.integers(len(_GESTURE_STATES), size=n)]                   # (n,5)
        states = np.where((kind < self.p_uniform + self.p_gesture)[:, None], gesture, per_finger)
        templ = np.zeros((n, 15, 3))
        for f in range(5):
            templ[:, _FINGER_ROWS[f]] = _STATE_TABLE[f][states[:, f]]
        templ += np.radians(NOISE_DEG) * rng.normal(size=templ.shape)
        mcp = _FINGER_ROWS[1:, 0]                                   # index..little MCP abduction fan
        templ[:, mcp, 1] += np.radians(SPREAD_DEG) * rng.random((n, 1)) * np.array([1.0, 0.2, -0.6, -1.2])
        angles = np.where((kind < self.p_uniform)[:, None, None], uniform, templ)
        return np.clip(angles, self.limits.limits[..., 0], self.limits.limits[..., 1])

    def sample(self, n, rng):
        """A dict of n paired samples: pose16, quats, beta, rest, xyz (see module doc)."""
        angles = self.sample_angles(n, rng)
        pose16 = self.limits.pose_from_angles(angles)                                   # (n,16,3)
        t = np.where(rng.random(n) < self.p_interpolate, rng.random(n), 1.0)
        pose16 = pose16 * t[:, None, None]                                              # slerp from rest
        pose16[:, 0] = random_rotations(n, rng)
        quats = relative_to_global_quats(pose16)
        beta = self.beta_std * rng.normal(size=(n, self.model.num_betas))
        rest = self.model.rest_joints(beta)
        xyz = forward_kinematics(quats, rest)
        return {"pose16": pose16, "quats": quats, "beta": beta,
                "rest": normalize_joints(rest), "xyz": normalize_joints(xyz)}


# -------------------------------------------------------------------- detector errors
def corrupt_joints(xyz, rng, sigma_max=0.08, depth_sigma_max=0.15, p_swap=0.05, p_collapse=0.05):
    """Emulate a 3D joint detector's errors on normalized joints (N,21,3) -> (N,21,3).

    Per sample: isotropic noise sigma ~ U(0, sigma_max) per joint; depth (z) noise
    ~ U(0, depth_sigma_max) per joint plus a per-finger depth offset of the same size;
    with p_swap a finger swaps places with its neighbour; with p_collapse a finger's
    joints are pulled toward its knuckle (a finger lost behind the others). Units are the
    reference bone (0.05 = 5 mm on a 10 cm palm). The output is normalized again.
    """
    xyz = np.array(xyz, dtype=np.float64)
    n = len(xyz)
    sigma = sigma_max * rng.random((n, 1, 1))
    noisy = xyz + sigma * rng.normal(size=xyz.shape)
    depth = depth_sigma_max * rng.random((n, 1))
    finger_offset = np.repeat(depth * rng.normal(size=(n, 5)), 4, axis=1)                 # (n,20)
    noisy[:, :, 2] += depth * rng.normal(size=(n, 21))
    noisy[:, 1:, 2] += finger_offset
    chains = np.array([[1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12], [13, 14, 15, 16], [17, 18, 19, 20]])
    swap = np.nonzero(rng.random(n) < p_swap)[0]
    first = rng.integers(1, 4, size=len(swap))                     # swap index-middle, middle-ring or ring-little
    for i, f in zip(swap, first):
        a, b = chains[f], chains[f + 1]
        noisy[i, np.concatenate([a[1:], b[1:]])] = noisy[i, np.concatenate([b[1:], a[1:]])]
    collapse = np.nonzero(rng.random(n) < p_collapse)[0]
    which = rng.integers(0, 5, size=len(collapse))
    amount = rng.uniform(0.5, 1.0, size=len(collapse))
    for i, f, a in zip(collapse, which, amount):
        base = noisy[i, chains[f][0]]
        noisy[i, chains[f][1:]] += a * (base - noisy[i, chains[f][1:]])
    return normalize_joints(noisy)


# -------------------------------------------------------------------- real sequences
# positional supervision / held back for evaluation (never temugeb_stereo: the detector's test split)
REAL_TRAIN = (
    "video/dex_retargeting/human_joint_right.pkl",
    "video/webcam/lujunwang_hand.mediapipe.npz",
    "video/webcam/lujunwang_hand2.mediapipe.npz",
    "video/webcam/huytung228_hand.mediapipe.npz",
    "video/webcam/huytung228_volctl.mediapipe.npz",
    "video/webcam/sushensanthush_hand.mediapipe.npz",
)
REAL_EVAL = (
    "video/tfjs_asl_hand/asl_hand_3d.full.json",
    "video/webcam/alimostafa_hand.mediapipe.npz",
    "video/webcam/huytung228_1hand.mediapipe.npz",
)
# the same frames as a file above, in another form: never read (would leak across the split)
REAL_DUPLICATES = ("video/dex_retargeting/human_hand_video.mediapipe.npz",
                   "video/tfjs_asl_hand/asl_hand.25fps.mediapipe.npz")


def read_sequence(path):
    """(F, 21, 3) right-hand joints (left hands mirrored x -> -x) from one real-data file."""
    path = Path(path)
    if path.suffix == ".pkl":           # dex-retargeting: list of (21,3), a right hand in a wrist frame
        with open(path, "rb") as fh:
            return np.asarray(pickle.load(fh), dtype=np.float64)
    if path.suffix == ".json":          # tfjs reference world landmarks (F,21,3), one right hand
        return np.asarray(json.loads(path.read_text()), dtype=np.float64)
    data = np.load(path)
    world, found, left = data["world"].astype(np.float64), data["found"], data["handedness"] == 1
    world = np.where(left[..., None, None], mirror_points(world), world)
    return world[found]                 # (hands found, 21, 3), both slots


def load_real_sequences(names, root=SHARED_DATA):
    """{name: (F,21,3) normalized right-hand joints} for the files that exist under root;
    frames with a degenerate reference bone are dropped. Empty when root is absent."""
    out = {}
    for name in names:
        path = Path(root) / name
        if not path.exists():
            continue
        xyz = read_sequence(path)
        ref = np.linalg.norm(xyz[:, REF_BONE[1]] - xyz[:, REF_BONE[0]], axis=-1)
        keep = np.isfinite(xyz).all(axis=(1, 2)) & (ref > 1e-3)
        out[name] = normalize_joints(xyz[keep])
    return out


class PositionPairs:
    """Input joints paired with target joints (and the rest pose to pose the model in):
    supervision through forward kinematics only (L_xyz).

    Sources: real sequences (input = target = MediaPipe joints, rest from the bone ratios
    of each frame via ShapeFitter), or, once a trained detector exists, its predictions on
    rendered images of known poses (an .npz with `pred` (N,21,3), `target` (N,21,3) and
    optionally `rest` (N,21,3), all normalized): from_npz. That file replaces the
    emulated noise of corrupt_joints (train_iknet --noisy-source).
    """

    def __init__(self, inputs, targets, rest):
        self.inputs, self.targets, self.rest = (np.asarray(a, dtype=np.float64) for a in (inputs, targets, rest))

    def __len__(self):
        return len(self.inputs)

    @classmethod
    def from_sequences(cls, sequences, model, max_abs_beta=3.0):
        from handmocap.perception.shape import ShapeFitter
        if not sequences:
            return cls(np.zeros((0, 21, 3)), np.zeros((0, 21, 3)), np.zeros((0, 21, 3)))
        xyz = np.concatenate(list(sequences.values()))
        fitter = ShapeFitter(model)
        beta = np.clip(np.array([fitter.fit(x) for x in xyz]), -max_abs_beta, max_abs_beta)
        return cls(xyz, xyz, normalize_joints(model.rest_joints(beta)))

    @classmethod
    def from_npz(cls, path, model):
        data = np.load(path)
        rest = data["rest"] if "rest" in data else np.broadcast_to(
            normalize_joints(model.rest_joints()), data["target"].shape)
        return cls(normalize_joints(data["pred"]), normalize_joints(data["target"]), rest)

    def sample(self, n, rng, rotate=True):
        """n random pairs (inputs, targets, rest), each pair under one random global rotation."""
        i = rng.integers(len(self), size=n)
        inputs, targets = self.inputs[i], self.targets[i]
        if rotate:
            R = quat_to_matrix(rng.normal(size=(n, 4)))[:, None]
            inputs, targets = (R @ inputs[..., None])[..., 0], (R @ targets[..., None])[..., 0]
        return inputs, targets, self.rest[i]


class BatchMaker:
    """Numpy batches: features (N,252) f32, targets in the palm frame of each input."""

    def __init__(self, model, noisy_pairs=None, real_pairs=None, share_noisy=0.35, share_real=0.15,
                 share_detector=1.0):
        self.sampler = PoseSampler(model)
        self.noisy_pairs, self.real_pairs = noisy_pairs, real_pairs
        self.share_noisy = share_noisy
        # of the noisy samples, the share taken from the detector's pairs; the rest emulated
        self.share_detector = share_detector if noisy_pairs is not None else 0.0
        self.share_real = share_real if real_pairs is not None and len(real_pairs) else 0.0

    def make(self, n, rng):
        n_real = int(round(self.share_real * n))
        n_noisy = int(round(self.share_noisy * n))
        n_detector = int(round(self.share_detector * n_noisy))
        n_pose = n - n_real - n_noisy
        poses = self.sampler.sample(n_pose + n_noisy - n_detector, rng)
        inputs, targets, rest = [poses["xyz"][:n_pose]], [poses["xyz"][:n_pose]], [poses["rest"][:n_pose]]
        if n_noisy > n_detector:
            clean = poses["xyz"][n_pose:]
            inputs.append(corrupt_joints(clean, rng))
            targets.append(clean)
            rest.append(poses["rest"][n_pose:])
        if n_detector:
            for a, b in zip((inputs, targets, rest), self.noisy_pairs.sample(n_detector, rng)):
                a.append(b)
        if n_real:
            for a, b in zip((inputs, targets, rest), self.real_pairs.sample(n_real, rng)):
                a.append(b)
        inputs, targets, rest = (np.concatenate(a) for a in (inputs, targets, rest))
        features, frame = iknet_inputs(inputs, rest)
        frame_t = np.swapaxes(frame, -1, -2)
        quat_c = np.zeros((n, 21, 4))
        quat_c[:n_pose] = matrix_to_quat(frame_t[:n_pose, None] @ quat_to_matrix(poses["quats"][:n_pose]))
        return {"features": features, "xyz": (targets @ frame).astype(np.float32), "rest": rest.astype(np.float32),
                "quat": quat_c.astype(np.float32), "has_quat": np.arange(n) < n_pose, "frame": frame}

"""Hand poses from keypoints: IKNet per hand, FK at the person's shape, global translation,
One Euro smoothing per track. The maths of the `ik` node and of HandTracker (no bus).

Per hand (pose_from_keypoints):
0. The joints IKNet reads are DetNet's xyz_rel with their x, y moved `xy_from_keypoints`
   (0.5) of the way onto the ones the 2D keypoints imply through K at DetNet's depths
   (translation.joints_through_keypoints): the heatmaps' 2D and the location maps' x, y err
   differently, and half of each measured better on held-out synthetic crops and on real
   clips (docs/models_history.md, "3D x, y from the 2D"). HandKeypoints' xyz_rel stays DetNet's.
1. A left hand's xyz_rel (the hand as seen) is mirrored (x -> -x) into the right-hand model.
2. IKNet (IKSolver; the static int8 file by default, "float32" on request) turns the joints
   into 21 global bone quaternions, given the rest pose of the person (the paper's X_ref,
   D_ref; the average hand until a shape is known). With clamp_to_limits the finger angles
   are then clipped into the anatomical limits of the average hand, down each finger,
   keeping each bone where IKNet points it as far as the limits allow
   (ik_solver.clamp_to_limits; docs/models_history.md, "The limits clamp keeps the bones").
3. Optional One Euro smoothing per track of the quaternions (sign-aligned with the last
   output, renormalized) and of the root translation; a track's filters are reset when the
   track is missing from a keypoints message or unseen for `reset_after_s`.
4. pose (16,3) relative axis-angle from the quaternions; joints by forward kinematics of the
   model at the track's beta (so xyz, quat, pose and beta agree exactly), mirrored back for
   a left hand; translation from uv and K with the model at beta as the metric scale: the
   root that puts all 21 posed joints onto the keypoints in the least-squares sense
   (translation.root_fitting_keypoints), else (fewer than 3 usable joints, or behind the
   camera) Eq. 5 (translation.camera_joints_from_keypoints, root and wrist only). On the
   rendered demo clip the all-joint fit has 38 mm mean root error (median 20) against Eq.
   5's 111 (75), and the posed joints land 18.8 px from the true 2D against 21.3 px:
   Eq. 5 rests on one bone of the posed skeleton, whose errors it turns into depth.
   `translation_valid` is False only where both failed (the hand-size fallback depth).
5. `confidence` (21,): DetNet's heatmap peaks, carried from HandKeypoints (hand_certainty).
`quat` and `pose` are those of the right-hand model (HandModel.forward(quat, beta,
handedness="left") draws the left hand); `xyz` and `root` are the hand as seen.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from handmocap.perception.ik_solver import clamp_to_limits
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.kinematics import RIGID_PALM_BONES, as_matrices, forward_kinematics, global_quats_to_relative
from handmocap.perception.one_euro import OneEuroFilter
from handmocap.perception.rotations import mirror_points, quat_normalize, quat_to_matrix
from handmocap.perception.skeleton import DEFAULT_HAND_LENGTH_M, REF_BONE, ROOT
from handmocap.perception.translation import camera_joints_from_keypoints, joints_through_keypoints, root_fitting_keypoints

@dataclass(frozen=True)
class PoseSettings:
    """Every setting of a PoseEstimator (the ik node's params), with its default and, beside it,
    what it does: the one place they are declared. __post_init__ refuses a value out of range
    (ValueError naming it). Filter cut-offs in Hz (handmocap/perception/one_euro.py), chosen on
    the detector's output on real clips by research/tune_smoothing.py (docs/models_history.md,
    "Pose smoothing"): lower cut-offs smooth more and lag more."""
    # finger angles clipped into anatomical limits (JointLimits), down each finger
    clamp_to_limits: bool = True
    # rotations and root smoothed per track by One Euro filters (False: every frame as read)
    smooth: bool = True
    # how far the x, y of the joints IKNet reads move from DetNet's 3D onto those the 2D
    # keypoints imply through K (0: DetNet's as they are)
    xy_from_keypoints: float = 0.5
    rot_min_cutoff: float = 1.0         # Hz, the rotations' filter at rest (on quaternion components)
    rot_beta: float = 1.5               # the rotations' cut-off rise with speed
    # Hz, the root's filter at rest: 0.5 Hz, first set on synthetic jitter, lagged behind real
    # motion (median 11 mm from the motion's zero-phase estimate); 2 Hz is 7 mm with a jitter 7x
    # below the unsmoothed output's
    root_min_cutoff: float = 2.0
    root_beta: float = 2.0              # the root's cut-off rise with speed (per m/s)
    d_cutoff: float = 1.0               # Hz, the filters' cut-off for the speed they adapt to
    reset_after_s: float = 0.5          # a track unseen this long starts its filters afresh
    # metres from the wrist crease to the middle fingertip, as a ruler measures it: the size of
    # every hand (scale-normalized keypoints cannot show size); default the adult average
    hand_length: float = DEFAULT_HAND_LENGTH_M

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type == "bool":
                if not isinstance(value, bool):
                    raise ValueError(f"{f.name}: expected true or false, got {value!r}")
            elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or \
                    value < 0 or (f.name.endswith("cutoff") and value == 0):   # a 0 Hz cut-off divides by zero
                raise ValueError(f"{f.name}: expected a number {'> 0' if f.name.endswith('cutoff') else '>= 0'}, "
                                 f"got {value!r}")
        if not 0.08 <= self.hand_length <= 0.30:   # 18 or 183 would be centimetres or millimetres
            raise ValueError(f"hand_length: expected metres from the wrist crease to the middle fingertip "
                             f"(adults: about 0.16 to 0.21), got {self.hand_length!r}")


def posed_joints(quats, model, beta, rest=None):
    """(21,3) joints in metres, right-hand model frame (wrist at the rest wrist), from bone
    quaternions (21,4) or matrices (21,3,3), with the model's rigid palm (as HandModel.forward).
    rest: the model's rest joints at beta (metres), when the caller has them."""
    bones = as_matrices(quats)[..., RIGID_PALM_BONES, :, :]
    return forward_kinematics(bones, model.rest_joints(beta) if rest is None else rest)


def solve_rotations(xyz_rel, handedness, rest, solver, limits=None):
    """Global bone quaternions of the right-hand model for hands' joints as seen: one hand's
    xyz_rel (21,3) and side "left"/"right" -> (21,4), or N hands' (N,21,3) and N sides ->
    (N,21,4), in one IKNet run and one clamp (IKNet's int8 is statically quantized: a hand's
    result does not depend on the others). rest: (21,3) or (N,21,3); with limits (a
    JointLimits), finger angles are clipped into them."""
    one = isinstance(handedness, str)
    xyz = np.array(xyz_rel, dtype=np.float64)
    xyz = xyz.reshape(-1, *xyz.shape[-2:])
    left = np.asarray([handedness] if one else handedness) == "left"
    xyz[left] = mirror_points(xyz[left])
    quats = solver.solve(xyz, rest)
    quats = quats if limits is None else clamp_to_limits(quats, limits)
    return quats[0] if one else quats


def pose_fields(hand, quats, beta, K, model):
    """HandPose hand (float32 arrays) from one HandKeypoints hand and its (already solved,
    maybe smoothed) right-model quaternions (21,4) at shape beta (B,): hands_pose_fields for one."""
    return hands_pose_fields([hand], np.asarray(quats)[None], np.asarray(beta)[None], K, model)[0]


def hands_pose_fields(hands, quats, betas, K, model):
    """HandPose hands (float32 arrays) from N HandKeypoints hands, their (already solved,
    maybe smoothed) right-model quaternions (N,21,4) and shapes betas (N,B), in one
    vectorised pass (per-call overheads once per frame, not per hand). root (before any
    smoothing) is the all-joint least-squares fit, or Eq. 5's where that fit is degenerate."""
    betas = np.asarray(betas, dtype=np.float64)
    rest = model.rest_joints(betas)                                         # (N,21,3) m
    R = quat_to_matrix(quats)                       # (N,21,3,3), shared by FK and the relative pose
    joints = posed_joints(R, model, betas, rest)                            # (N,21,3) m
    rel = joints - joints[:, ROOT:ROOT + 1]
    left = [i for i, h in enumerate(hands) if h["handedness"] == "left"]
    rel[left, :, 0] *= -1.0                                                 # a left hand mirrored back
    uv = np.stack([h["uv"] for h in hands]).astype(np.float64)              # (N,21,2) px
    root, valid = root_fitting_keypoints(K, uv, rel)                        # (N,3) m, (N,)
    if not valid.all():                  # Eq. 5 where the all-joint fit is degenerate (rare)
        for i in np.flatnonzero(~valid):
            ref_m = float(np.linalg.norm(rest[i, REF_BONE[1]] - rest[i, REF_BONE[0]]))   # = model.ref_bone_length
            _, root[i], valid[i] = camera_joints_from_keypoints(K, uv[i], rel[i] / ref_m, ref_m)
    xyz = (root[:, None] + rel).astype(np.float32)
    quat = quat_normalize(quats).astype(np.float32)
    pose = global_quats_to_relative(R).astype(np.float32)
    return [{"track_id": int(hand["track_id"]), "handedness": hand["handedness"], "score": float(hand["score"]),
             "confidence": np.asarray(hand["confidence"], dtype=np.float32),
             "xyz": xyz[i], "root": root[i].astype(np.float32), "quat": quat[i], "pose": pose[i],
             "beta": betas[i].astype(np.float32), "uv": uv[i].astype(np.float32),
             "translation_valid": bool(valid[i])} for i, hand in enumerate(hands)]


def hand_certainty(hand):
    """How sure the detector is of one HandKeypoints / HandPose hand's joints, 0-1: the mean
    of its 21 heatmap peaks (`confidence`), or its `score` (presence) in a HandPose recorded
    before the peaks were carried. The mean peak ranks strangers' hands by their 2D error
    (rank correlation -0.8 on the held-back people's clips; presence -0.65, and it is 1.0
    on most hands): research/confidence_vs_error.py, README "Using /hand/pose"."""
    peaks = hand.get("confidence")
    return float(np.mean(peaks)) if peaks is not None else float(hand["score"])


def surest_per_side(hands):
    """{side: that side's hand of highest hand_certainty} of a HandPose message's hands,
    those with finite joints and rotations only."""
    out = {}
    for hand in hands:
        if np.all(np.isfinite(hand["xyz"])) and np.all(np.isfinite(hand["quat"])):
            best = out.get(hand["handedness"])
            if best is None or hand_certainty(hand) > hand_certainty(best):
                out[hand["handedness"]] = hand
    return out


def joints_for_iknet(hand, K, xy_from_keypoints=PoseSettings.xy_from_keypoints):
    """(21,3) the joints IKNet reads for one HandKeypoints hand (as seen, camera axes):
    xyz_rel with x, y moved `xy_from_keypoints` of the way onto the ones its uv implies (0: xyz_rel)."""
    return hands_joints_for_iknet([hand], K, xy_from_keypoints)[0]


def hands_joints_for_iknet(hands, K, xy_from_keypoints=PoseSettings.xy_from_keypoints):
    """(N,21,3) joints_for_iknet of N HandKeypoints hands, in one vectorised call."""
    xyz_rel = np.stack([h["xyz_rel"] for h in hands]).astype(np.float64)
    if not xy_from_keypoints:
        return xyz_rel
    return joints_through_keypoints(K, np.stack([h["uv"] for h in hands]), xyz_rel, xy_from_keypoints)


def pose_from_keypoints(hand, K, rest, solver, model, beta=None, limits=None,
                        xy_from_keypoints=PoseSettings.xy_from_keypoints):
    """One HandKeypoints hand -> one HandPose hand, unsmoothed. rest: (21,3) rest joints of
    the person (None: the model's at beta); beta (10,) (None: the average hand); limits: a
    JointLimits to clip the finger angles into (None: IKNet's angles as they are);
    xy_from_keypoints: see joints_for_iknet."""
    beta = np.zeros(model.num_betas) if beta is None else np.asarray(beta, dtype=np.float64)
    rest = model.rest_joints(beta) if rest is None else rest
    quats = solve_rotations(joints_for_iknet(hand, K, xy_from_keypoints), hand["handedness"], rest, solver, limits)
    return pose_fields(hand, quats, beta, K, model)


class TrackSmoother:
    """One Euro filters of one track: quaternions (21,4) and root (3,)."""

    def __init__(self, s: PoseSettings):
        self.quat = OneEuroFilter(s.rot_min_cutoff, s.rot_beta, s.d_cutoff)
        self.root = OneEuroFilter(s.root_min_cutoff, s.root_beta, s.d_cutoff)
        self.last_t = None

    def quats(self, q, t):
        if self.quat.x is not None:       # q and -q are one rotation: stay on the last output's side
            q = np.where(np.sum(q * self.quat.x, axis=-1, keepdims=True) < 0, -q, q)
        self.last_t = t
        return quat_normalize(self.quat(q, t))


class PoseEstimator:
    """Every hand of a keypoints message -> HandPose hands; shapes and smoothing per track.
    settings: a PoseSettings (None: the defaults), with `changes` (its field names) applied on
    top; TypeError naming an unknown one."""

    def __init__(self, solver, model, settings: PoseSettings | None = None, **changes):
        try:
            self.settings = dataclasses.replace(settings or PoseSettings(), **changes)
        except TypeError:
            unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(PoseSettings)})
            raise TypeError(f"PoseEstimator has no setting {', '.join(unknown)} (PoseSettings' fields are "
                            f"its settings)") from None
        self.solver, self.model = solver, model
        self.shapes = {}          # track id -> (beta (10,), rest_xyz (21,3))
        self.limits = JointLimits.for_model(model) if self.settings.clamp_to_limits else None
        self.tracks = {}          # track id -> TrackSmoother
        self.average = np.zeros(model.num_betas)

    def set_shapes(self, shapes):
        self.shapes = {s["track_id"]: (np.asarray(s["beta"], np.float64), np.asarray(s["rest_xyz"], np.float64))
                       for s in shapes}

    def update(self, hands, K, t):
        """hands: HandKeypoints hands; K (3,3); t: capture time (s). Returns HandPose hands;
        hands with non-finite joints are skipped."""
        seen = {h["track_id"] for h in hands}
        for tid in [tid for tid, s in self.tracks.items()
                    if tid not in seen or t - s.last_t > self.settings.reset_after_s]:
            del self.tracks[tid]                                   # lost: start afresh
        hands = [h for h in hands if np.all(np.isfinite(h["xyz_rel"])) and np.all(np.isfinite(h["uv"]))]
        if not hands:
            return []
        betas, rests = [], []
        for hand in hands:
            beta, rest = self.shapes.get(hand["track_id"], (self.average, None))
            beta = self.model.sized(beta, self.settings.hand_length)   # the shape fit leaves size at 0
            betas.append(beta)
            rests.append(self.model.rest_joints(beta) if rest is None else rest)
        # every hand in one IKNet run, one clamp and one pass of the fields: per-call overheads
        # once per frame, not per hand
        quats = solve_rotations(hands_joints_for_iknet(hands, K, self.settings.xy_from_keypoints),
                                [h["handedness"] for h in hands], np.stack(rests), self.solver, self.limits)
        if not self.settings.smooth:
            return hands_pose_fields(hands, quats, betas, K, self.model)
        tracks = [self.tracks.setdefault(h["track_id"], TrackSmoother(self.settings)) for h in hands]
        out = hands_pose_fields(hands, np.stack([track.quats(q, t) for track, q in zip(tracks, quats)]),
                                betas, K, self.model)
        for track, fields in zip(tracks, out):
            root = track.root(fields["root"], t)
            fields["xyz"] = (fields["xyz"] - fields["root"] + root).astype(np.float32)
            fields["root"] = root.astype(np.float32)
        return out


def mesh_message(model, hands):
    """The body of a HandMesh message for HandPose hands: per hand its posed vertices (V,3)
    float32 metres in the camera frame (`hand_mesh`). The faces that go with them are
    `model.faces`, the right hand's winding: a left hand's vertices are mirrored, so its
    outward-facing triangles are `faces[:, ::-1]`."""
    return {"hands": [{"track_id": h["track_id"], "handedness": h["handedness"],
                       "vertices": hand_mesh(model, h)[0].astype(np.float32)} for h in hands]}


def hand_mesh(model, hand):
    """The posed mesh of one HandPose hand in the camera frame: vertices (V,3) metres, faces
    (F,3) int (winding flipped for a left hand, so it faces outward) and its 21 joints (21,3)
    metres. HandModel.forward at the hand's quat and beta, moved so that joint 9 sits at
    `root`: the joints then equal the hand's `xyz` (pose_fields builds them the same way)."""
    vertices, joints = model.forward(np.asarray(hand["quat"], np.float64), np.asarray(hand["beta"], np.float64),
                                     handedness=hand["handedness"])
    offset = np.asarray(hand["root"], np.float64) - joints[ROOT]
    return vertices + offset, model.faces_for(hand["handedness"]), joints + offset

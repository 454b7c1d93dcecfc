"""Anatomical joint limits of the 15 finger joints, a limit test and a plausible-pose sampler.

Local joint frames (from the model's rest joints, so they follow beta and fit any model):
* twist axis t_i: the rest bone leaving joint i (i -> i+1);
* flexion axis f_i: the normal of the plane the finger's rest joints curl in, summed
  cross products b_k x b_(k+1) of consecutive rest bones of that finger (the template's
  fingers are slightly curled), made orthogonal to t_i. Rotating about +f_i curls the
  finger further, towards the palm: positive flexion, negative is extension;
* abduction axis a_i = t_i x f_i. For the four fingers, positive abduction moves the
  finger towards the thumb side (radial deviation). The thumb's rest curl lies in the
  palm plane, so its flexion moves it across the palm towards the little finger and
  its positive abduction lifts it out of the palm plane on the palm side (palmar
  abduction); negative abduction is retroposition.
The frame F_i = [f_i a_i t_i] (columns, model axes). A relative joint rotation R_i
(model axes, MANO-style) reads in the local frame as L = F_iᵀ R_i F_i, decomposed as
L = Rx(flexion) Ry(abduction) Rz(twist) (intrinsic x-y-z Euler angles: flexion has its
full range, abduction stays within +-90 deg).

Angles are anatomical: flexion 0 is a straight joint. The template's rest curl (the
angle between the incoming and outgoing rest bones about f_i) is added to the flexion
read from the pose, so the limits below are the textbook ones. The wrist (joint 0)
carries the global orientation of hand and forearm and has no limit here.

Limits in degrees (flexion, abduction, twist), active range of a healthy adult hand, from
* Lee, J. & Kunii, T. (1995) "Model-based analysis of hand posture", IEEE CG&A 15(5);
* Lin, J., Wu, Y. & Huang, T. S. (2000) "Modeling the constraints of human hand motion",
  Proc. Workshop on Human Motion: MCP flexion 0..90, PIP 0..110, DIP 0..90,
  MCP abduction -15..15;
* Hume, M. C. et al. (1990) "Functional range of motion of the joints of the hand",
  J. Hand Surg. 15A: thumb MCP 56 and IP 80 deg flexion used in daily activities;
* Cobos, S. et al. (2008) "Efficient human hand kinematics for manipulation tasks",
  IROS: MCP hyperextension, thumb CMC (trapeziometacarpal) ranges, small axial twist.
Finger-specific abduction (index and little reach furthest) and a few degrees of
passive twist/sideways slack at the hinge joints follow Cobos et al.; the thumb CMC
ranges are broad because its two axes are not orthogonal and the literature spreads.
"""
import numpy as np

from handmocap.perception.kinematics import as_matrices, frames_to_relative
from handmocap.perception.rotations import matrix_to_axis_angle
from handmocap.perception.skeleton import NON_TIP_JOINTS, PARENTS

FINGER_JOINTS = NON_TIP_JOINTS[1:]          # the 15 joints with limits: 1,2,3,5,6,7,9,...

# joint: (flexion, abduction, twist) ranges in degrees
LIMITS_DEG = {
    1: ((-20, 50), (-15, 45), (-25, 25)),      # thumb CMC
    2: ((-10, 60), (-10, 10), (-10, 10)),      # thumb MCP
    3: ((-15, 85), (-5, 5), (-5, 5)),          # thumb IP
    5: ((-30, 90), (-10, 25), (-10, 10)),      # index MCP
    6: ((-5, 110), (-5, 5), (-5, 5)),          # index PIP
    7: ((-5, 90), (-5, 5), (-5, 5)),           # index DIP
    9: ((-30, 90), (-15, 15), (-8, 8)),        # middle MCP
    10: ((-5, 110), (-5, 5), (-5, 5)),
    11: ((-5, 90), (-5, 5), (-5, 5)),
    13: ((-30, 90), (-20, 10), (-8, 8)),       # ring MCP
    14: ((-5, 110), (-5, 5), (-5, 5)),
    15: ((-5, 90), (-5, 5), (-5, 5)),
    17: ((-30, 90), (-30, 10), (-10, 10)),     # little MCP
    18: ((-5, 110), (-5, 5), (-5, 5)),
    19: ((-5, 90), (-5, 5), (-5, 5)),
}
LIMITS = np.radians(np.array([LIMITS_DEG[j] for j in FINGER_JOINTS], dtype=np.float64))   # (15,3,2)

_FINGER_CHAINS = ((1, 2, 3, 4), (5, 6, 7, 8), (9, 10, 11, 12), (13, 14, 15, 16), (17, 18, 19, 20))


def local_frames(rest):
    """Joint frames and rest curl from rest joints (21,3).

    Returns frames (15,3,3) (columns f, a, t in model axes) and rest_flexion (15,)
    radians, the curl of the template at each joint (0 for the thumb CMC, whose
    incoming wrist->CMC segment is no anatomical bone).
    """
    rest = np.asarray(rest, dtype=np.float64)
    frames, rest_flexion = [], []
    for chain in _FINGER_CHAINS:
        bones = np.diff(rest[list(chain)], axis=0)
        curl = np.sum(np.cross(bones[:-1], bones[1:]), axis=0)
        curl /= np.linalg.norm(curl)
        for j in chain[:-1]:
            t = rest[j + 1] - rest[j]
            t /= np.linalg.norm(t)
            f = curl - (curl @ t) * t
            f /= np.linalg.norm(f)
            frames.append(np.stack([f, np.cross(t, f), t], axis=1))
            incoming = rest[j] - rest[PARENTS[j]]
            bend = np.arctan2(np.cross(incoming, t) @ f, incoming @ t)
            rest_flexion.append(0.0 if j == 1 else bend)
    order = [FINGER_JOINTS.index(j) for chain in _FINGER_CHAINS for j in chain[:-1]]
    frames = np.array(frames)[np.argsort(order)]
    rest_flexion = np.array(rest_flexion)[np.argsort(order)]
    return frames, rest_flexion


def _euler_xyz_to_matrix(angles):
    """(...,3) (x, y, z) angles -> (...,3,3) Rx(x) Ry(y) Rz(z), written out (one stack of
    nine products instead of three axis-angle -> quaternion -> matrix conversions)."""
    angles = np.asarray(angles, dtype=np.float64)
    c, s = np.cos(angles), np.sin(angles)
    cx, cy, cz = c[..., 0], c[..., 1], c[..., 2]
    sx, sy, sz = s[..., 0], s[..., 1], s[..., 2]
    sx_sy, cx_sy = sx * sy, cx * sy
    return np.stack([
        cy * cz, -cy * sz, sy,
        sx_sy * cz + cx * sz, cx * cz - sx_sy * sz, -sx * cy,
        sx * sz - cx_sy * cz, cx_sy * sz + sx * cz, cx * cy,
    ], axis=-1).reshape(angles.shape[:-1] + (3, 3))


def _matrix_to_euler_xyz(L):
    """(...,3,3) -> (...,3) angles with L = Rx(x) Ry(y) Rz(z), y in [-pi/2, pi/2]."""
    y = np.arcsin(np.clip(L[..., 0, 2], -1.0, 1.0))
    x = np.arctan2(-L[..., 1, 2], L[..., 2, 2])
    z = np.arctan2(-L[..., 0, 1], L[..., 0, 0])
    return np.stack([x, y, z], axis=-1)


class JointLimits:
    """Limits expressed in the local frames of one hand (a model and a beta).

    >>> limits = JointLimits.for_model(HandModel.load())
    >>> ok = limits.within(pose)            # (..., 15) bool
    >>> poses = limits.sample(100, rng)     # (100, 16, 3) relative axis-angle
    """

    def __init__(self, rest_joints, limits=LIMITS):
        self.frames, self.rest_flexion = local_frames(rest_joints)
        self.limits = np.asarray(limits, dtype=np.float64)          # (15,3,2) radians

    @classmethod
    def for_model(cls, model, beta=None):
        return cls(model.rest_joints(beta))

    def angles(self, pose):
        """(..., 15, 3) anatomical (flexion, abduction, twist) radians of a pose.

        pose: relative (...,16,3|4|3x3) or global bone rotations (...,21,4|3x3).
        """
        return self.angles_from_relative(_relative_matrices(pose)[..., 1:, :, :])

    def angles_from_relative(self, rel, joints=slice(None)):
        """(..., 15, 3, 3) relative rotations of the finger joints (model axes) -> (..., 15, 3)
        anatomical angles: L = Fᵀ R F read as Rx(flexion) Ry(abduction) Rz(twist). joints: an
        index into the 15 (FINGER_JOINTS order) when rel holds only those joints."""
        F = self.frames[joints]
        angles = _matrix_to_euler_xyz(np.swapaxes(F, -1, -2) @ rel @ F)
        angles[..., 0] += self.rest_flexion[joints]
        return angles

    def relative_from_angles(self, angles, joints=slice(None)):
        """(..., 15, 3) anatomical angles -> (..., 15, 3, 3) relative rotations R = F L Fᵀ of the
        finger joints (model axes); the inverse of angles_from_relative (joints: as there)."""
        angles = np.array(angles, dtype=np.float64)
        angles[..., 0] -= self.rest_flexion[joints]
        F = self.frames[joints]
        return F @ _euler_xyz_to_matrix(angles) @ np.swapaxes(F, -1, -2)

    def pose_from_angles(self, angles, wrist=None):
        """(..., 15, 3) anatomical angles (radians) -> (..., 16, 3) relative axis-angle pose.

        wrist: optional (..., 3) axis-angle global rotation of the hand (default none).
        """
        pose = matrix_to_axis_angle(self.relative_from_angles(angles))
        wrist = np.zeros(pose.shape[:-2] + (3,)) if wrist is None else np.broadcast_to(wrist, pose.shape[:-2] + (3,))
        return np.concatenate([wrist[..., None, :], pose], axis=-2)

    def within(self, pose, tolerance_deg=0.5):
        """(..., 15) bool: is each finger joint of the pose within its limits?"""
        a = self.angles(pose)
        tol = np.radians(tolerance_deg)
        return np.all((a >= self.limits[..., 0] - tol) & (a <= self.limits[..., 1] + tol), axis=-1)

    def sample_angles(self, n, rng=None):
        """(n, 15, 3) anatomical angles uniform within the limits."""
        rng = np.random.default_rng(rng)
        lo, hi = self.limits[..., 0], self.limits[..., 1]
        return lo + (hi - lo) * rng.random((n,) + lo.shape)

    def sample(self, n, rng=None, wrist=None):
        """(n, 16, 3) relative axis-angle poses with every finger joint uniform within its
        limits; the wrist rotation is `wrist` ((3,) or (n,3) axis-angle) or none."""
        return self.pose_from_angles(self.sample_angles(n, rng), wrist)


def _relative_matrices(pose):
    pose = np.asarray(pose, dtype=np.float64)
    is_matrix = pose.ndim >= 3 and pose.shape[-2:] == (3, 3)
    count = pose.shape[-3] if is_matrix else pose.shape[-2]
    if count == 16:
        return as_matrices(pose)
    from handmocap.perception.hand_model import HandModel   # the same pose reading as the model
    return frames_to_relative(HandModel.joint_frames(pose))


# Named poses as anatomical angles in degrees per finger joint (flexion, abduction, twist);
# joints not listed are straight.
_NAMED_DEG = {
    "flat": {},
    "fist": {1: (25, 20, 15), 2: (45, 0, 0), 3: (60, 0, 0),
             5: (85, 0, 0), 6: (100, 0, 0), 7: (65, 0, 0), 9: (85, 0, 0), 10: (100, 0, 0), 11: (65, 0, 0),
             13: (85, 0, 0), 14: (100, 0, 0), 15: (65, 0, 0), 17: (85, 0, 0), 18: (100, 0, 0), 19: (65, 0, 0)},
    "pointing": {1: (25, 20, 15), 2: (40, 0, 0), 3: (50, 0, 0),
                 5: (0, 5, 0), 6: (5, 0, 0), 7: (5, 0, 0), 9: (85, 0, 0), 10: (100, 0, 0), 11: (65, 0, 0),
                 13: (85, 0, 0), 14: (100, 0, 0), 15: (65, 0, 0), 17: (85, 0, 0), 18: (100, 0, 0), 19: (65, 0, 0)},
    "spread": {1: (-20, 10, 0), 2: (-5, 0, 0), 3: (-5, 0, 0), 5: (-5, 20, 0), 9: (-5, 0, 0),
               13: (-5, -15, 0), 17: (-5, -25, 0)},
}
NAMED_POSES = tuple(_NAMED_DEG)


def named_pose(name, model=None, beta=None):
    """(16, 3) relative axis-angle pose by name: 'flat', 'fist', 'pointing', 'spread'."""
    if model is None:
        from handmocap.perception.hand_model import HandModel
        model = HandModel.load()
    limits = JointLimits.for_model(model, beta)
    angles = np.zeros((15, 3))
    for j, deg in _NAMED_DEG[name].items():
        angles[FINGER_JOINTS.index(j)] = np.radians(deg)
    return limits.pose_from_angles(angles)


__all__ = ["JointLimits", "LIMITS", "LIMITS_DEG", "FINGER_JOINTS", "NAMED_POSES", "local_frames",
           "named_pose"]

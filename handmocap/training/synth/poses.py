"""Finger poses for the image engine.

When `handmocap.training.pose_data` is there (IKNet's pose sampler: uniform, per-finger templates
and whole-hand gestures — fists, grasps, pinches, OK, counting), its `sample_angles`
gives the anatomical finger angles (with a smaller uniform share, 10%: random-finger
hands look odd in pictures), 30% of them moved toward rest. Otherwise a curl model over
the anatomical angles of handmocap.perception.joint_limits:
* 25%: every joint uniform within its limits (coverage of odd poses);
* 75%: per finger a curl c in [0,1] (often near 0 or 1, neighbours correlated), MCP, PIP
  and DIP flexion following c with their own jitter, a shared spread, the thumb between
  open, resting and opposed, plus 5 degrees of noise.
All poses are within the joint limits. Wrist rotation is zero: the camera sampler
orients the hand.
"""
import numpy as np

from handmocap.perception.joint_limits import FINGER_JOINTS, JointLimits

_FINGERS = ((5, 6, 7), (9, 10, 11), (13, 14, 15), (17, 18, 19))
_FULL_CURL = np.radians([88.0, 100.0, 70.0])        # MCP, PIP, DIP flexion of a fist
_SPREAD = np.radians([18.0, 0.0, -14.0, -26.0])      # MCP abduction of each finger, fully spread
_THUMB_OPEN = np.radians([[-15, 10, 0], [-5, 0, 0], [-5, 0, 0]])
_THUMB_FIST = np.radians([[25, 20, 15], [45, 0, 0], [60, 0, 0]])
_THUMB_OPPOSED = np.radians([[40, 40, 20], [20, 0, 0], [25, 0, 0]])


def _external_sampler(model):
    """pose_data.PoseSampler(model).sample_angles, or None where that module is absent."""
    try:
        from handmocap.training.pose_data import PoseSampler as DataPoseSampler
    except ImportError:
        return None
    try:
        sampler = DataPoseSampler(model, p_uniform=0.1)
    except TypeError:
        sampler = DataPoseSampler(model)
    return getattr(sampler, "sample_angles", None)


class PoseSampler:
    """(n,16,3) relative axis-angle finger poses, wrist zero, within the joint limits."""

    def __init__(self, model, use_external=True):
        self.limits = JointLimits.for_model(model)
        self.external = _external_sampler(model) if use_external else None
        self.source = "handmocap.training.pose_data" if self.external else "curl model"

    def sample(self, n, rng):
        if self.external is not None:
            angles = self.external(n, rng)
            pose = self.limits.pose_from_angles(angles)
            toward_rest = np.where(rng.random(n) < 0.3, rng.random(n), 1.0)
            pose[:, 1:] *= toward_rest[:, None, None]
            return pose
        return self.limits.pose_from_angles(self.sample_angles(n, rng))

    def sample_angles(self, n, rng):
        """(n,15,3) anatomical angles, radians."""
        angles = np.zeros((n, 15, 3))
        idx = {j: FINGER_JOINTS.index(j) for j in FINGER_JOINTS}
        # finger curls: a shared tendency plus per-finger choice (straight / curled / between)
        shared = rng.random(n)
        kind = rng.random((n, 4))
        curl = np.where(kind < 0.3, rng.uniform(0, 0.15, (n, 4)),
                        np.where(kind < 0.6, rng.uniform(0.8, 1.05, (n, 4)), rng.random((n, 4))))
        mix = rng.uniform(0, 0.7, (n, 1))
        curl = np.clip(curl * (1 - mix) + shared[:, None] * mix, 0, 1.05)
        for f, chain in enumerate(_FINGERS):
            per_joint = np.clip(curl[:, f, None] + rng.normal(0, 0.12, (n, 3)), -0.3, 1.1)
            for k, j in enumerate(chain):
                angles[:, idx[j], 0] = per_joint[:, k] * _FULL_CURL[k]
            angles[:, idx[chain[0]], 1] = _SPREAD[f] * rng.uniform(-0.2, 1.0, n) * (1 - 0.6 * curl[:, f])
        # thumb: a blend of open, fist and opposed
        w = rng.dirichlet((0.7, 0.7, 0.7), n)
        thumb = (w[:, 0, None, None] * _THUMB_OPEN + w[:, 1, None, None] * _THUMB_FIST
                 + w[:, 2, None, None] * _THUMB_OPPOSED)
        for k, j in enumerate((1, 2, 3)):
            angles[:, idx[j]] = thumb[:, k]
        angles += rng.normal(0, np.radians(5), angles.shape)
        uniform = rng.random(n) < 0.25
        angles[uniform] = self.limits.sample_angles(int(uniform.sum()), rng)
        lo, hi = self.limits.limits[..., 0], self.limits.limits[..., 1]
        return np.clip(angles, lo, hi)

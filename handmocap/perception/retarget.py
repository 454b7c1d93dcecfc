"""/hand/pose -> robot joint positions with dex-retargeting (github.com/dexsuite/dex-retargeting).

dex-retargeting's examples retarget MediaPipe's world landmarks (its SingleHandDetector):
21 joints in MediaPipe's order (handmocap's order too: no reordering), metres, the wrist at
the origin, rotated into a wrist frame estimated from the wrist, index MCP and middle MCP and
then by a fixed per-hand matrix into what it calls the MANO convention:

    joint_pos = (p - p[0]) @ wrist_frame(p) @ OPERATOR2MANO[hand]           (21, 3) metres

Here p is /hand/pose `xyz` (metric, camera frame: only its shape matters, the rotation drops
out). In that frame, for either hand, the middle MCP lies on +z; the index MCP is on +y for a
right hand and on -y for a left one. The hand is picked by `handedness` (the anatomical hand,
as dex-retargeting's hand_type means it). Its configs' scaling_factor expects a hand in
metres of about the size MediaPipe gives: the ik node's hand_length sets it.

RobotHand (needs the `retarget` extra: pip install -e '.[retarget]') wraps one config:

    robot = RobotHand("allegro_hand_right", urdf_dir="~/dex-urdf/robots/hands")
    names, qpos = robot.joint_names, robot.retarget(hand["xyz"], "right")
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

# dex-retargeting's fixed rotations from its estimated wrist frame to its MANO convention
# (example/vector_retargeting/single_hand_detector.py), applied on the right: p @ M.
OPERATOR2MANO = {
    "right": np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "left": np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
}
WRIST, INDEX_MCP, MIDDLE_MCP = 0, 5, 9


def wrist_frame(xyz):
    """(3,3) rotation whose columns are the wrist frame's axes in xyz's frame: x from the middle
    MCP towards the wrist, y the normal of the plane (wrist, index MCP, middle MCP), z = x × y,
    with the sign of y chosen so that z points from the middle MCP towards the index MCP.
    xyz: (21,3) joints, any rigid frame, any unit."""
    xyz = np.asarray(xyz, dtype=np.float64)
    wrist, index, middle = xyz[WRIST], xyz[INDEX_MCP], xyz[MIDDLE_MCP]
    normal = np.cross(index - wrist, middle - wrist)   # the 3 points' plane (their SVD fit, exactly)
    normal /= np.linalg.norm(normal)
    x = wrist - middle
    x -= (x @ normal) * normal                          # Gram-Schmidt: x in the palm plane
    x /= np.linalg.norm(x)
    z = np.cross(x, normal)
    if z @ (index - middle) < 0:                        # z towards the index side
        normal, z = -normal, -z
    return np.stack([x, normal, z], axis=1)


def retargeting_joint_pos(xyz, handedness):
    """(21,3) joints (metres, MediaPipe order, e.g. /hand/pose xyz) -> dex-retargeting's
    joint_pos (21,3): wrist-relative, in its MANO-convention wrist frame."""
    xyz = np.asarray(xyz, dtype=np.float64)
    rel = xyz - xyz[WRIST]
    return rel @ wrist_frame(xyz) @ OPERATOR2MANO[handedness]


def ref_value(joint_pos, indices, retargeting_type):
    """What retargeting.retarget() takes, as dex-retargeting's examples form it: the joints
    themselves for POSITION retargeting, else vectors joint_pos[task] - joint_pos[origin] with
    indices (2, K) = (origin row, task row)."""
    indices = np.asarray(indices)
    if str(retargeting_type).upper().endswith("POSITION"):
        return joint_pos[indices, :]
    return joint_pos[indices[1], :] - joint_pos[indices[0], :]


def config_path(config) -> Path:
    """A dex-retargeting config: a .yml path, or the name of one bundled with dex-retargeting
    (its configs/teleop folder, e.g. "allegro_hand_right"). FileNotFoundError naming both."""
    path = Path(str(config)).expanduser()
    if path.suffix in (".yml", ".yaml"):
        if not path.is_file():
            raise FileNotFoundError(f"dex-retargeting config {path} not found")
        return path
    import dex_retargeting
    bundled = Path(dex_retargeting.__file__).parent / "configs" / "teleop"
    path = bundled / f"{config}.yml"
    if not path.is_file():
        names = sorted(p.stem for p in bundled.glob("*.yml"))
        raise FileNotFoundError(f"no dex-retargeting config {config!r}: a .yml path or one of {', '.join(names)}")
    return path


class RobotHand:
    """One robot hand driven by dex-retargeting (a SeqRetargeting: warm-started, low-pass
    filtered, so one instance per hand whose motion it follows).

    config: see config_path; urdf_dir: the folder the config's urdf_path is relative to (None:
    the config's own folder); max_ms: a time budget of the optimisation per call (None: until
    it converges; on Allegro 4 ms cut the p95 from 6.6 to 4.7 ms for 0.016 rad mean change,
    benchmarks/bench_retarget.py). RuntimeError naming the extra when dex-retargeting is absent;
    FileNotFoundError / ValueError naming the file when a config or URDF is wrong."""

    def __init__(self, config, urdf_dir=None, max_ms=None):
        try:
            from dex_retargeting.retargeting_config import RetargetingConfig
        except ImportError as e:
            raise RuntimeError(f"the retarget node needs dex-retargeting: pip install -e '.[retarget]' ({e})") from None
        path = config_path(config)
        urdf_dir = Path(urdf_dir).expanduser() if urdf_dir else path.parent
        if not urdf_dir.is_dir():
            raise FileNotFoundError(f"robot URDF folder {urdf_dir} not found")
        RetargetingConfig.set_default_urdf_dir(str(urdf_dir))
        self.retargeting = RetargetingConfig.load_from_file(str(path)).build()
        self.indices = self.retargeting.optimizer.target_link_human_indices
        self.kind = self.retargeting.optimizer.retargeting_type
        self.joint_names = list(self.retargeting.joint_names)
        if max_ms:   # nlopt stops there with its best so far: a bounded latency per hand
            self.retargeting.optimizer.opt.set_maxtime(float(max_ms) / 1000.0)

    def retarget(self, xyz, handedness):
        """Robot joint positions (J,) float64 (radians or metres, per joint; joint_names' order)
        for one hand's joints xyz (21,3) metres (/hand/pose xyz)."""
        joint_pos = retargeting_joint_pos(xyz, handedness)
        return np.asarray(self.retargeting.retarget(ref_value(joint_pos, self.indices, self.kind)), dtype=np.float64)

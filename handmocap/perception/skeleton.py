"""The one joint-order table of the project (docs/reference.md: the /hand/pose fields and frames).

21 joints, MediaPipe's and the paper's order: 0 wrist; 1-4 thumb (CMC, MCP, IP, tip);
5-8 index (MCP, PIP, DIP, tip); 9-12 middle; 13-16 ring; 17-20 little.
"""
import numpy as np

NUM_JOINTS = 21

JOINT_NAMES = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "little_mcp", "little_pip", "little_dip", "little_tip",
)

# Parent of each joint; the wrist (0) has none (-1).
PARENTS = np.array([-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19])

ROOT = 9                # joint that root-relative coordinates are centred on (middle MCP)
REF_BONE = (0, 9)       # bone whose length is 1 in scale-normalized coordinates

FINGER_TIPS = (4, 8, 12, 16, 20)
HAND_LENGTH_JOINTS = (0, 12)   # wrist -> middle fingertip: a ruler's hand length

# Average adult hand length (wrist crease to middle fingertip), metres: about 0.193 for men
# and 0.172 for women in anthropometric surveys; the bundled model's average hand (beta = 0)
# measures 0.183 (reference bone 0 -> 9: 0.102). The metric size of a hand whose owner gave
# none (scale-normalized joints cannot show size).
DEFAULT_HAND_LENGTH_M = 0.183

# (parent, child) pairs of the 20 bones, in child order 1..20.
BONES = tuple((int(PARENTS[j]), j) for j in range(1, NUM_JOINTS))

# The 16 joints that carry a rotation (all but the tips), in project order; MANO-style
# relative poses (16,3) list their rotations in this order.
NON_TIP_JOINTS = tuple(j for j in range(NUM_JOINTS) if j not in FINGER_TIPS)

# MANO's joint order (16 joints: wrist, index, middle, little, ring, thumb, then the tips
# thumb, index, middle, ring, little) as project joint ids: xyz_mano = xyz[..., MANO_ORDER, :]
# and xyz = xyz_mano[..., FROM_MANO_ORDER, :].
MANO_ORDER = np.array([0, 5, 6, 7, 9, 10, 11, 17, 18, 19, 13, 14, 15, 1, 2, 3, 4, 8, 12, 16, 20])
FROM_MANO_ORDER = np.argsort(MANO_ORDER)


def normalize_joints(xyz):
    """(..., 21, 3) joints -> root-relative (joint 9 at 0), scale-normalized (|0-9| = 1).

    Degenerate hands (zero reference bone) come back as NaN, which callers must reject.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    rel = xyz - xyz[..., ROOT:ROOT + 1, :]
    ref = np.linalg.norm(rel[..., REF_BONE[0], :], axis=-1)[..., None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return rel / np.where(ref > 0, ref, np.nan)

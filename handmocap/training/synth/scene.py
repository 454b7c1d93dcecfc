"""Where hands, cameras and occluders go; and the labels that follow from it.

Frames: a hand is posed in the model frame (metres, wrist at the origin, fingers -y,
palm -z; left hands mirrored across x), then placed in the OpenCV camera frame by
x_cam = R (x - c) + p, with c the centre of its joints' bounding box.

Crop mode (the detector's input, NOTES.md): a virtual full frame (640x480, horizontal
field of view 45-100 deg) sees the hand at 0.2-1.2 m anywhere in the frame; the crop is
the square around the hand's box (hand and finger vertices, no forearm) scaled by
`crop_scale` (1.3) x U(0.85, 1.2), its centre jittered by up to 8% of the box; it is
rendered directly at the crop size with K_crop = S (K_full shifted to the crop), so the
perspective of an off-centre hand in a real frame is kept.
Frame mode (a hand finder's input): the tile is the whole frame; the hand may be
anywhere, large or small, partly out of view.
"""
import numpy as np

from handmocap.perception.rotations import axis_angle_to_matrix, quat_to_matrix
from handmocap.perception.skeleton import REF_BONE, ROOT
from .mesh import FOREARM_END_Y

FULL_FRAME = (640, 480)


def sample_rotations(rng, n, uniform_share=0.1, side_share=0.3, pitched_share=0.0):
    """(n,3,3) model -> camera rotations covering palm, back, side, above, below.

    Like hands in front of a webcam: (1 - uniform_share): R = Rz(roll) Rx(pitch) Ry(yaw)
    with yaw (turn about the fingers' axis) near the palm or the back facing the camera
    (N(0 or 180 deg, 35 deg)), or for `side_share` of these uniform (side views);
    pitch N(0, 35 deg) within +-85 (fingers towards or away from the camera); roll
    N(0, 45 deg) (fingers up in the image) or, for 15%, any roll. uniform_share: uniform
    over SO(3) (coverage of every view).
    pitched_share: the share whose pitch is +-U(60, 88 deg) instead: fingers nearly along
    the line of sight, the hand foreshortened (a signer's palms held up towards the
    camera), which N(0, 35 deg) gives 2.8% of crops and held-back clips show on 7%.
    """
    facing = rng.normal(0, np.radians(35), n) + np.where(rng.random(n) < 0.5, 0.0, np.pi)
    yaw = np.where(rng.random(n) < side_share, rng.uniform(-np.pi, np.pi, n), facing)
    pitch = np.clip(rng.normal(0, np.radians(35), n), -np.radians(85), np.radians(85))
    if pitched_share > 0:       # drawn only when asked, so other sets keep their seeds' images
        steep = np.radians(rng.uniform(60, 88, n)) * np.where(rng.random(n) < 0.5, -1.0, 1.0)
        pitch = np.where(rng.random(n) < pitched_share, steep, pitch)
    roll = np.where(rng.random(n) < 0.15, rng.uniform(-np.pi, np.pi, n), rng.normal(0, np.radians(45), n))
    ex, ey, ez = np.eye(3)
    R = (axis_angle_to_matrix(roll[:, None] * ez) @ axis_angle_to_matrix(pitch[:, None] * ex)
         @ axis_angle_to_matrix(yaw[:, None] * ey))
    uniform = rng.random(n) < uniform_share
    q = rng.normal(size=(int(uniform.sum()), 4))
    R[uniform] = quat_to_matrix(q)
    return R


PALM_CENTRE = np.array([0.0, -0.05, 0.0])       # model frame, m: about the middle of the palm
HALF_TURN_Y = np.diag([-1.0, 1.0, -1.0])         # half a turn about the fingers' axis (model y)


def touching_placement(rng, R1, c1, p1):
    """Place a second hand palm to palm with the first: (R2, c2, p2) (m,3,3), (m,3), (m,3)
    for hands whose first hand is placed by R1, c1, p1 (x_cam = R (x - c) + p).

    Two hands rubbing, clasped or interlocking (hand washing, signs like LSM's "limpiar"),
    which a second hand dropped 9-20 cm away never shows. In the first hand's model frame
    the second one is turned half a turn about the fingers' axis (its palm faces the
    first's; for the other side's hand the thumbs then lie on the same side, as in
    clasped hands), turned about the palm's normal by N(0, 25 deg) (or, for a quarter,
    U(-100, 100 deg): fingers crossing), slid along the palm by up to a few cm and set
    2-3.5 cm from it (two palms' thickness). Where the fingers are curled they may pass
    through the other hand; the renderer's depth test still gives each pixel one hand.
    """
    m = len(R1)
    turn = np.where(rng.random(m) < 0.25, rng.uniform(-1.75, 1.75, m), rng.normal(0, np.radians(25), m))
    Q = HALF_TURN_Y @ axis_angle_to_matrix(turn[:, None] * np.array([0.0, 0.0, 1.0]))
    offset = np.stack([rng.uniform(-0.03, 0.03, m), rng.uniform(-0.05, 0.03, m), -rng.uniform(0.02, 0.035, m)], 1)
    # x_in_first = Q (x - pc) + pc + o, so x_cam = R1 Q (x - c2) + p1 with c2 = pc - Q^T (pc + o - c1)
    c2 = PALM_CENTRE - np.einsum("nji,nj->ni", Q, PALM_CENTRE + offset - c1)
    return R1 @ Q, c2, p1.copy()


def intrinsics(f, cx, cy):
    """(n,3,3) pinhole K from (n,) focal lengths and principal points, pixels."""
    K = np.zeros((len(f), 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = f
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = cx, cy, 1.0
    return K


def project(K, points):
    """(n,3,3) K and (n,P,3) camera-frame points -> (n,P,2) pixels."""
    p = points @ np.swapaxes(K, 1, 2).astype(points.dtype)
    return p[..., :2] / p[..., 2:3]


def toward_ray(p):
    """(n,3,3) rotations taking the optical axis (0, 0, 1) onto the ray to each point p (n,3)."""
    ray = p / np.linalg.norm(p, axis=1, keepdims=True)
    axis = np.cross([0.0, 0.0, 1.0], ray)                       # |axis| = sin(angle)
    sin = np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.arctan2(sin, ray[:, 2:3])
    return axis_angle_to_matrix(axis * np.where(sin > 1e-9, angle / np.maximum(sin, 1e-12), 0.0))


def place_hands(rng, joints_model, mode, tile, depth_range=(0.2, 1.2), fov_deg=(45, 100), pitched_share=0.0):
    """Sample rotation R (n,3,3), translation p (n,3) and full-frame K (n,3,3).

    joints_model: (n,21,3) posed joints in the model frame. Rotations whose forearm end
    would reach behind the camera (the arm would come out of the lens) are redrawn.
    pitched_share: see `sample_rotations`; when it is above 0, every rotation is drawn about
    the ray to the hand instead of the optical axis (a hand near the frame's edge of a wide
    lens, its fingers along the optical axis, is not foreshortened in the image).
    Returns R, centre c (n,3) in the model frame, p, K_full and the full frame's size.
    """
    n = len(joints_model)
    c = 0.5 * (joints_model.min(1) + joints_model.max(1))
    width, height = FULL_FRAME if mode == "crop" else (tile, tile)
    fov = np.radians(rng.uniform(*fov_deg, n))
    f = 0.5 * width / np.tan(0.5 * fov)
    K_full = intrinsics(f, np.full(n, (width - 1) / 2), np.full(n, (height - 1) / 2))
    lo, hi = np.log(depth_range[0]), np.log(depth_range[1])
    z = np.exp(rng.uniform(lo, hi, n))
    margin = 0.0 if mode == "crop" else 0.05
    u = rng.uniform(margin, 1 - margin, n) * width
    v = rng.uniform(margin, 1 - margin, n) * height
    p = np.stack([(u - K_full[:, 0, 2]) / f * z, (v - K_full[:, 1, 2]) / f * z, z], 1)
    along_ray = toward_ray(p) if pitched_share > 0 else np.broadcast_to(np.eye(3), (n, 3, 3))
    R = along_ray @ sample_rotations(rng, n, pitched_share=pitched_share)
    arm_end = np.array([0.0, FOREARM_END_Y, 0.0])
    for _ in range(20):
        bad = np.einsum("nij,nj->ni", R, arm_end - c)[:, 2] + p[:, 2] < 0.08
        if not bad.any():
            break
        R[bad] = along_ray[bad] @ sample_rotations(rng, int(bad.sum()), pitched_share=pitched_share)
    return R, c, p, K_full


def crop_intrinsics(rng, K_full, hand_uv, tile, crop_scale=1.3, scale_jitter=(0.85, 1.2), centre_jitter=0.08):
    """K of a square crop around projected hand vertices, rendered at `tile` px.

    hand_uv: (n,P,2) full-frame pixels of the hand's vertices.
    Returns K_crop (n,3,3) and the crop box (n,4) x0, y0, side, side in full-frame px.
    """
    n = len(K_full)
    lo, hi = hand_uv.min(1), hand_uv.max(1)
    size = (hi - lo).max(1)
    centre = 0.5 * (lo + hi) + rng.uniform(-centre_jitter, centre_jitter, (n, 2)) * size[:, None]
    side = size * crop_scale * rng.uniform(*scale_jitter, n)
    x0, y0 = centre[:, 0] - side / 2, centre[:, 1] - side / 2
    s = tile / side
    K = K_full.copy()
    K[:, 0, 0] *= s
    K[:, 1, 1] *= s
    # the crop convention of shared/data/README.md: full-frame (x0, y0) is crop pixel (0, 0)
    K[:, 0, 2] = (K_full[:, 0, 2] - x0) * s
    K[:, 1, 2] = (K_full[:, 1, 2] - y0) * s
    return K, np.stack([x0, y0, side, side], 1)


def normalized_root_relative(xyz):
    """(n,21,3) camera-frame joints -> root-relative (joint 9), |joint0 - joint9| = 1."""
    rel = xyz - xyz[:, ROOT:ROOT + 1]
    scale = np.linalg.norm(xyz[:, REF_BONE[1]] - xyz[:, REF_BONE[0]], axis=-1)
    return rel / scale[:, None, None]


def joint_visibility(uv, xyz, depth, ids, parts, own_id, radius, adjacent, tile):
    """(n,21) bool: the joint is inside the image and the nearest surface at its pixel
    is its own hand, on a segment next to the joint (adjacent (21,16) bool over parts),
    no nearer than the joint's depth minus `radius` (n,21) metres (the hand's thickness
    around that joint). Otherwise another object or another part of the same hand is in
    front of it. Also returns in_image (n,21) bool.
    """
    px = np.floor(uv + 0.5).astype(np.int64)
    in_image = np.all((px >= 0) & (px < tile), axis=-1)
    pxc = np.clip(px, 0, tile - 1)
    rows = np.arange(len(uv))[:, None]
    surface_z = depth[rows, pxc[..., 1], pxc[..., 0]]
    surface_id = ids[rows, pxc[..., 1], pxc[..., 0]]
    surface_part = parts[rows, pxc[..., 1], pxc[..., 0]]
    own_part = adjacent[np.arange(adjacent.shape[0]), np.minimum(surface_part, adjacent.shape[1] - 1)]
    visible = in_image & (surface_id == own_id) & own_part & (surface_z >= xyz[..., 2] - radius)
    return visible, in_image


def boxes(uv):
    """(n,P,2) pixels -> (n,4) boxes x0, y0, x1, y1."""
    return np.concatenate([uv.min(1), uv.max(1)], 1)

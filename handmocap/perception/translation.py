"""Global translation of the hand from 2D keypoints, root-relative 3D and camera intrinsics.

Paper Eq. 5: with a = K⁻¹ [u_r, v_r, 1] (root, joint 9), b = K⁻¹ [u_w, v_w, 1] (wrist,
joint 0), the wrist's depth z_w = z_r + c where c = l_ref * d_w (d_w: normalized
root-relative depth of the wrist, l_ref: reference bone 0 -> 9 in metres), the root depth
z_r solves
    | z_r a - (z_r + c) b | = l_ref
    <=> A z^2 + B z + C = 0,  A = |a - b|^2,  B = -2 c (a - b)·b,  C = c^2 |b|^2 - l_ref^2.
When C < 0 the roots have opposite signs and the positive one is the answer; when C >= 0
both have the same sign and the one nearer the fallback estimate below is taken.

Degenerate cases give valid = False and a finite fallback depth, never NaN:
* the 2D bone is (nearly) zero (hand seen along the reference bone): A ~ 0;
* the quadratic has no real root (noisy keypoints: the 2D bone is too long for l_ref);
* the root would be behind or almost at the camera (z < MIN_DEPTH_M).
Fallback: z = f * (3D spread of all joints across the image plane) / (2D spread), the
size ratio of the whole hand (pinhole: size in pixels = f * size in metres / depth); if
that is degenerate too (non-finite or collapsed input), DEFAULT_DEPTH_M.
"""
import numpy as np

from handmocap.perception.camera_info import project
from handmocap.perception.skeleton import REF_BONE, ROOT, normalize_joints

# Reference bone (wrist -> middle MCP) of an average adult hand, metres: the bundled
# model at beta = 0 measures 0.102 m; adult palm length (wrist crease to MCP3) is about
# 0.095-0.11 m. Pass the person's own length where it is known.
DEFAULT_REF_BONE_M = 0.10
MIN_DEPTH_M = 0.05      # nearer than this is not a hand in front of a camera
DEFAULT_DEPTH_M = 0.5   # arm's length, when nothing can be measured


def _k_matrix(K):
    K = np.asarray(K, dtype=np.float64)
    if K.shape[-2:] == (3, 3):
        return K
    fx, fy, cx, cy = np.moveaxis(K, -1, 0)
    zero, one = np.zeros_like(fx), np.ones_like(fx)
    return np.stack([np.stack([fx, zero, cx], -1), np.stack([zero, fy, cy], -1),
                     np.stack([zero, zero, one], -1)], -2)


def back_project(K, uv):
    """(..., 2) pixels -> (..., 3) rays K⁻¹ [u, v, 1] (z = 1)."""
    K = _k_matrix(K)
    uv = np.asarray(uv, dtype=np.float64)
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]) / K[..., 0, 0]
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def _eq5_roots(a, b, d_wrist, ref_bone_m):
    """Both roots of Eq. 5's quadratic for the rays a (root) and b (wrist) (..., 3): far (the
    larger), near (the smaller), the constant C (C < 0: opposite signs) and whether they are
    real with a non-degenerate bone."""
    ref = np.asarray(ref_bone_m, dtype=np.float64)
    c = ref * np.asarray(d_wrist, dtype=np.float64)
    ab = a - b
    A = np.sum(ab * ab, axis=-1)
    B = -2.0 * c * np.sum(ab * b, axis=-1)
    C = c * c * np.sum(b * b, axis=-1) - ref ** 2
    disc = B * B - 4.0 * A * C
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        far = (-B + sq) / (2.0 * A)
        near = (-B - sq) / (2.0 * A)
    return far, near, C, (A > 1e-10) & (disc >= 0)


def _checked(z, solvable):
    """z where it is a usable root depth (finite, solvable, in front of the camera), else NaN; and that mask."""
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & solvable & (z > MIN_DEPTH_M)
    return np.where(valid, z, np.nan), valid


def root_depth_from_intrinsics(K, uv_root, uv_wrist, d_wrist, ref_bone_m=DEFAULT_REF_BONE_M, near_depth=None):
    """Root depth by Eq. 5.

    K: (3,3) or (4,) fx,fy,cx,cy (or batched); uv_root, uv_wrist: (..., 2) pixels;
    d_wrist: (...,) wrist depth minus root depth in reference-bone units;
    ref_bone_m: reference bone length in metres (scalar or (...,));
    near_depth: (...,) depth used to choose between two positive roots (default: the
    larger root).
    Returns z_root (...,) metres (NaN where invalid) and valid (...,) bool.
    """
    far, near, C, solvable = _eq5_roots(back_project(K, uv_root), back_project(K, uv_wrist), d_wrist, ref_bone_m)
    return _checked(far if near_depth is None else _nearer_root(far, near, C, near_depth), solvable)


def _nearer_root(far, near, C, near_depth):
    """Of two positive roots (C >= 0), the one nearer near_depth; otherwise the far one."""
    with np.errstate(invalid="ignore"):
        pick_near = (C >= 0) & (np.abs(near - near_depth) < np.abs(far - near_depth))
    return np.where(pick_near, near, far)


def depth_from_hand_size(K, uv, xyz_rel, ref_bone_m=DEFAULT_REF_BONE_M):
    """Fallback root depth (...,) from the ratio of the hand's 3D and 2D spreads.

    uv (..., 21, 2) pixels, xyz_rel (..., 21, 3) root-relative normalized joints.
    Uses the x-y spread of the 3D joints (metres) and the 2D spread (pixels) with the
    mean focal length; ignores the small perspective differences across the hand.
    Returns (...,) depth, DEFAULT_DEPTH_M where not measurable.
    """
    K = _k_matrix(K)
    f = 0.5 * (K[..., 0, 0] + K[..., 1, 1])
    uv = np.asarray(uv, dtype=np.float64)
    xy = np.asarray(xyz_rel, dtype=np.float64)[..., :2] * np.asarray(ref_bone_m, dtype=np.float64)[..., None, None]
    spread_2d = np.sqrt(np.sum(np.var(uv, axis=-2), axis=-1))
    spread_3d = np.sqrt(np.sum(np.var(xy, axis=-2), axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = f * spread_3d / spread_2d
    ok = np.isfinite(z) & (z > MIN_DEPTH_M)
    return np.where(ok, z, DEFAULT_DEPTH_M)


def camera_joints_from_keypoints(K, uv, xyz_rel, ref_bone_m=DEFAULT_REF_BONE_M):
    """All 21 joints in camera metres from 2D keypoints and root-relative 3D.

    K: (3,3) or (4,); uv: (..., 21, 2) pixels; xyz_rel: (..., 21, 3) root-relative
    (joint 9 at the origin), scale-normalized (|joint 0 - joint 9| = 1), camera axes.
    Returns xyz (..., 21, 3) metres, root (..., 3), valid (...,) bool. Where Eq. 5 fails
    the root depth is the hand-size fallback and valid is False; the root's x, y always
    come from back-projecting its pixel at that depth.
    """
    uv = np.asarray(uv, dtype=np.float64)
    xyz_rel = np.asarray(xyz_rel, dtype=np.float64)
    ref = np.asarray(ref_bone_m, dtype=np.float64)
    wrist, root = REF_BONE[0], ROOT
    d_wrist = xyz_rel[..., wrist, 2] - xyz_rel[..., root, 2]
    fallback = depth_from_hand_size(K, uv, xyz_rel, ref)
    rays = back_project(K, uv[..., [root, wrist], :])                  # (..., 2, 3): root, wrist
    ray = rays[..., 0, :]
    ray = np.where(np.isfinite(ray), ray, np.array([0.0, 0.0, 1.0]))   # a NaN pixel must not spread
    rel = np.where(np.isfinite(xyz_rel), xyz_rel, 0.0)
    rel = ref[..., None, None] * (rel - rel[..., root:root + 1, :])

    def joints_at(z):
        root_xyz = ray * z[..., None]
        return root_xyz[..., None, :] + rel, root_xyz

    # Eq. 5 can have two positive roots (the bone tilted towards or away from the camera):
    # keep the one whose 21 joints reproject onto the keypoints best. The quadratic is solved
    # once; both candidates are scored in one pass (axis 0 of the stacked depths).
    far, near, C, solvable = _eq5_roots(rays[..., 0, :], rays[..., 1, :], d_wrist, ref)
    z_far, valid = _checked(far, solvable)
    z_near, _ = _checked(_nearer_root(far, near, C, 0.0), solvable)
    z_near = np.where(np.isfinite(z_near), z_near, z_far)
    candidates = np.stack([np.where(valid, z_far, fallback), np.where(valid, z_near, fallback)])   # (2, ...)
    err_far, err_near = _reprojection_error(K, joints_at(candidates)[0], uv)
    z = np.where(valid, np.where(err_near < err_far, z_near, z_far), fallback)
    xyz, root_xyz = joints_at(z)
    return xyz, root_xyz, valid


def _reprojection_error(K, xyz, uv):
    """(...,) mean pixel distance between the projection of xyz (..., 21, 3) and uv (..., 21, 2)."""
    px = project(_k_matrix(K), xyz)
    with np.errstate(invalid="ignore", divide="ignore"):
        dist = np.sqrt(np.sum((px - uv) ** 2, axis=-1))                         # (..., 21)
        seen = ~np.isnan(dist)           # np.nanmean's own sum / count, without its overhead
        err = np.sum(np.where(seen, dist, 0.0), axis=-1) / np.sum(seen, axis=-1)
    return np.where(np.isfinite(err), err, np.inf)


def root_fitting_keypoints(K, uv, rel_m):
    """Root position (..., 3) metres that puts the root-relative joints rel_m (..., 21, 3)
    metres (camera axes) onto the keypoints uv (..., 21, 2) pixels: linear least squares
    over every joint (the paper's Eq. 5 uses the root and wrist only). For a translation t,
    a joint p projects onto u when fx (p_x + t_x) - (u - cx) (p_z + t_z) = 0, and the same
    for v: 42 equations linear in t (the algebraic error, i.e. the pixel error weighted by
    the joint's depth, which varies little across a hand). Joints with a non-finite pixel
    are left out. Returns root (..., 3) and ok (...,) bool: False (root NaN) where fewer
    than 3 joints are usable or the root would be nearer than MIN_DEPTH_M.

    Solved in closed form: with du = u - cx, dv = v - cy over the n usable joints, the rows
    [fx, 0, -du] t = du p_z - fx p_x =: bu and [0, fy, -dv] t = dv p_z - fy p_y =: bv have
    normal equations whose first two rows give t_x = (sum bu + t_z sum du) / (fx n) and
    t_y = (sum bv + t_z sum dv) / (fy n); put into the third, t_z (sum (du^2 + dv^2) -
    ((sum du)^2 + (sum dv)^2) / n) = (sum du sum bu + sum dv sum bv) / n - sum (du bu + dv bv):
    the keypoints' spread fixes the depth. The least-squares solution itself, in a dozen
    array operations instead of the 42 x 3 system (per-call overheads: issue 51)."""
    K = _k_matrix(K)
    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    uv = np.asarray(uv, dtype=np.float64)
    p = np.asarray(rel_m, dtype=np.float64)
    seen = np.all(np.isfinite(uv), axis=-1) & np.all(np.isfinite(p), axis=-1)          # (..., 21)
    du = np.where(seen, uv[..., 0] - cx[..., None], 0.0)
    dv = np.where(seen, uv[..., 1] - cy[..., None], 0.0)
    p = np.where(seen[..., None], p, 0.0)
    n = seen.sum(-1)                                                                   # (...,)
    bu = du * p[..., 2] - fx[..., None] * p[..., 0]                                     # (..., 21), 0 where unseen
    bv = dv * p[..., 2] - fy[..., None] * p[..., 1]
    s_du, s_dv, s_bu, s_bv = du.sum(-1), dv.sum(-1), bu.sum(-1), bv.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.sum(du * du + dv * dv, axis=-1) - (s_du * s_du + s_dv * s_dv) / n
        tz = (s_du * s_bu + s_dv * s_bv) / n - np.sum(du * bu + dv * bv, axis=-1)
        tz = tz / spread
        t = np.stack([(s_bu + s_du * tz) / (fx * n), (s_bv + s_dv * tz) / (fy * n), tz], axis=-1)
    nearest = np.min(np.where(seen, p[..., 2], np.inf), axis=-1) + tz
    ok = (n >= 3) & np.all(np.isfinite(t), axis=-1) & (nearest > MIN_DEPTH_M)
    return np.where(ok[..., None], t, np.nan), ok


def joints_through_keypoints(K, uv, xyz_rel, weight=1.0):
    """Normalized root-relative joints (..., 21, 3) (camera axes, joint 9 at 0, |0-9| = 1)
    whose x, y are moved `weight` of the way (0: unchanged, 1: all the way) onto the ones
    the 2D keypoints uv (..., 21, 2) px imply at the depths of xyz_rel.

    Joint i lies on its ray r_i = K⁻¹ [u_i, v_i, 1] at depth Z_9 + s z_i (s: the metric
    reference bone, z_i its normalized relative depth), so divided by s and relative to
    joint 9 it is a (r_i - r_9) + z_i r_i, with the one unknown a = Z_9 / s (the distance
    in reference bones) fitted to xyz_rel's x, y by least squares; z stays z_i. DetNet's
    2D is read from heatmaps, its x, y from location maps: on held-out synthetic crops
    and real clips (docs/models_history.md, "3D x, y from the 2D") half of each beats either.
    Joints with a non-finite pixel keep xyz_rel's x, y; so does a hand whose fit fails."""
    p = np.asarray(xyz_rel, dtype=np.float64)
    r = back_project(_k_matrix(K)[..., None, :, :], uv)[..., :2]             # rays' x, y (z = 1), K per hand
    d = r - r[..., ROOT:ROOT + 1, :]                                           # (..., 21, 2)
    target = p[..., :2] - p[..., 2:] * r                                       # = a d where all agree
    seen = np.isfinite(np.sum(d + target, axis=-1))                            # (..., 21) pixel and joint
    d0, t0 = np.where(seen[..., None], d, 0.0), np.where(seen[..., None], target, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.sum(d0 * t0, axis=(-2, -1)) / np.sum(d0 * d0, axis=(-2, -1))    # (...,) distance in bones
    shift = weight * (a[..., None, None] * d - target)                         # x, y moved onto the rays
    moved = p.copy()
    moved[..., :2] += np.where(np.isfinite(shift), shift, 0.0)
    return normalize_joints(moved)

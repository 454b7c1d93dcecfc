"""Rotation maths: quaternions (w, x, y, z), rotation matrices, axis-angle vectors.

Every function works on numpy arrays with any number of leading batch dimensions:
quaternions are (..., 4), matrices (..., 3, 3), axis-angle vectors and points (..., 3).
Quaternions are unit quaternions; q and -q are the same rotation, and functions that
return quaternions return the one with w >= 0 unless they say otherwise. Rotations act
on column vectors: p' = R @ p, and quat_multiply(a, b) rotates by b first, then by a.

Mirroring (left hands): a left hand is handled as the mirror image of a right hand
across the camera's x axis, M = diag(-1, 1, 1). A point maps to M p; a rotation R maps
to M R M, which is again a rotation. For the axis-angle vector r = theta * axis this is
r -> (r_x, -r_y, -r_z), and for a quaternion (w, x, y, z) -> (w, x, -y, -z): the axis of
rotation is a pseudo-vector, so it picks up det(M) = -1 on top of M. Mirroring twice is
the identity.
"""
import numpy as np

_EPS = 1e-12


def quat_normalize(q):
    """(..., 4) -> (..., 4) unit quaternions with w >= 0."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
    # one scale per quaternion: 1/|q|, negated where w < 0 (q and -q are one rotation)
    return q * (np.where(q[..., :1] < 0, -1.0, 1.0) / np.maximum(norm, _EPS))


# Hamilton product as a bilinear form: (a * b)_k = sum_ij _PRODUCT[k, i, j] a_i b_j
_PRODUCT = np.zeros((4, 4, 4))
for _k, _i, _j, _sign in [(0, 0, 0, 1), (0, 1, 1, -1), (0, 2, 2, -1), (0, 3, 3, -1),
                          (1, 0, 1, 1), (1, 1, 0, 1), (1, 2, 3, 1), (1, 3, 2, -1),
                          (2, 0, 2, 1), (2, 1, 3, -1), (2, 2, 0, 1), (2, 3, 1, 1),
                          (3, 0, 3, 1), (3, 1, 2, 1), (3, 2, 1, -1), (3, 3, 0, 1)]:
    _PRODUCT[_k, _i, _j] = _sign
_PRODUCT_FLAT = _PRODUCT.reshape(4, 16).T.copy()          # (16, 4): outer(a, b).ravel() @ it


def quat_multiply(a, b):
    """Hamilton product a * b of (..., 4) quaternions (broadcasting): rotate by b, then a.
    Computed as the 16 products a_i b_j (one outer product) summed with signs (one matmul):
    two numpy calls instead of sixteen products and a stack, exact (coefficients are +-1)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    outer = a[..., :, None] * b[..., None, :]                                  # (..., 4, 4)
    return outer.reshape(outer.shape[:-2] + (16,)) @ _PRODUCT_FLAT


_LEFT = np.swapaxes(_PRODUCT, 0, 1).reshape(4, 16).copy()                   # (i, k*4 + j)


def quat_left_matrix(q):
    """(..., 4) -> (..., 4, 4) L(q) with q * p = L(q) @ p: applying one rotation to many
    quaternions is then one matmul (p rows: p @ L(q)ᵀ)."""
    q = np.asarray(q, dtype=np.float64)
    return (q @ _LEFT).reshape(q.shape[:-1] + (4, 4))


def quat_conjugate(q):
    """(..., 4) conjugate; for unit quaternions this is the inverse rotation."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_inverse(q):
    """(..., 4) inverse of any non-zero quaternion."""
    q = np.asarray(q, dtype=np.float64)
    return quat_conjugate(q) / np.maximum(np.sum(q * q, axis=-1, keepdims=True), _EPS)


def quat_rotate(q, v):
    """Rotate (..., 3) vectors by (..., 4) unit quaternions (broadcasting)."""
    q, v = np.asarray(q, dtype=np.float64), np.asarray(v, dtype=np.float64)
    w, u = q[..., :1], q[..., 1:]
    # v' = v + 2w (u x v) + 2 u x (u x v): the sandwich product without building q v q*
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


# R = I + P @ _Q2M with P = (2 / |q|^2) outer(q, q) flattened (w, x, y, z order):
# R00 = 1 - (P_yy + P_zz), R01 = P_xy - P_wz, R02 = P_xz + P_wy, and so on
_Q2M = np.zeros((16, 9))
for _r, _terms in enumerate([((2, 2, -1), (3, 3, -1)), ((1, 2, 1), (0, 3, -1)), ((1, 3, 1), (0, 2, 1)),
                             ((1, 2, 1), (0, 3, 1)), ((1, 1, -1), (3, 3, -1)), ((2, 3, 1), (0, 1, -1)),
                             ((1, 3, 1), (0, 2, -1)), ((2, 3, 1), (0, 1, 1)), ((1, 1, -1), (2, 2, -1))]):
    for _i, _j, _sign in _terms:
        _Q2M[4 * _i + _j, _r] = _sign
_EYE_FLAT = np.eye(3).ravel()


def quat_to_matrix(q):
    """(..., 4) quaternions (any norm: divided out here) -> (..., 3, 3) rotation matrices.
    One outer product and one matmul with a constant (16, 9) table (exact: +-1 entries)."""
    q = np.asarray(q, dtype=np.float64)
    scale = 2.0 / np.maximum(np.sum(q * q, axis=-1), _EPS * _EPS)               # (...,)
    outer = (q[..., :, None] * q[..., None, :]) * scale[..., None, None]      # (..., 4, 4)
    return (_EYE_FLAT + outer.reshape(q.shape[:-1] + (16,)) @ _Q2M).reshape(q.shape[:-1] + (3, 3))


# Shepperd's method: the symmetric 4x4 matrix K = 4 q qᵀ read off R, K_flat = _M2Q_CONST + R_flat @ _M2Q.
# Diagonal 4w^2 = 1 + m00 + m11 + m22, 4x^2 = 1 + m00 - m11 - m22, ...; off-diagonal 4wx = m21 - m12, ...
_M2Q = np.zeros((9, 16))
_M2Q_CONST = np.zeros(16)
for _row, _col, _terms in [(0, 0, ((0, 1), (4, 1), (8, 1))), (1, 1, ((0, 1), (4, -1), (8, -1))),
                           (2, 2, ((0, -1), (4, 1), (8, -1))), (3, 3, ((0, -1), (4, -1), (8, 1))),
                           (0, 1, ((7, 1), (5, -1))), (0, 2, ((2, 1), (6, -1))), (0, 3, ((3, 1), (1, -1))),
                           (1, 2, ((3, 1), (1, 1))), (1, 3, ((2, 1), (6, 1))), (2, 3, ((7, 1), (5, 1)))]:
    for _m, _sign in _terms:
        _M2Q[_m, 4 * _row + _col] = _M2Q[_m, 4 * _col + _row] = _sign
    if _row == _col:
        _M2Q_CONST[5 * _row] = 1.0


def matrix_to_quat(R):
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions, w >= 0.

    Shepperd's method: row i of K = 4 q qᵀ is 4 q_i q; the row whose diagonal entry
    (4 q_i^2) is largest is taken and normalized, so it stays accurate for every rotation
    angle, including 180 degrees. K comes from R in one matmul with a constant table.
    """
    R = np.asarray(R, dtype=np.float64)
    K = _M2Q_CONST + R.reshape(-1, 9) @ _M2Q                                   # (M,16): K flattened
    best = np.argmax(K[:, ::5], axis=-1)                                       # (M,) largest 4 q_i^2
    q = K.reshape(-1, 4, 4)[np.arange(len(K)), best]                           # (M,4) rows 4 q_i q
    return quat_normalize(q).reshape(R.shape[:-2] + (4,))


def axis_angle_to_quat(r):
    """(..., 3) axis-angle vectors (angle = norm, radians) -> (..., 4) quaternions."""
    r = np.asarray(r, dtype=np.float64)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a, with its Taylor series near 0 so that tiny rotations stay exact
    k = np.where(angle > 1e-6, np.sin(half) / np.maximum(angle, _EPS), 0.5 - angle ** 2 / 48.0)
    return np.concatenate([np.cos(half), r * k], axis=-1)


def quat_to_axis_angle(q):
    """(..., 4) quaternions -> (..., 3) axis-angle vectors with angle in [0, pi]."""
    q = quat_normalize(q)
    w, v = q[..., :1], q[..., 1:]
    sin_half = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, w)
    k = np.where(sin_half > 1e-6, angle / np.maximum(sin_half, _EPS), 2.0 + sin_half ** 2 / 3.0)
    return v * k


def axis_angle_to_matrix(r):
    """(..., 3) axis-angle -> (..., 3, 3) rotation matrices."""
    return quat_to_matrix(axis_angle_to_quat(r))


def matrix_to_axis_angle(R):
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle, angle in [0, pi]."""
    return quat_to_axis_angle(matrix_to_quat(R))


def quat_slerp(q0, q1, t):
    """Spherical linear interpolation along the shorter arc.

    q0, q1: (..., 4) unit quaternions; t: scalar or (...,) in [0, 1] (broadcast against
    the batch dims). Returns (..., 4); t=0 gives q0, t=1 gives q1 (up to sign).
    """
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)          # shorter arc
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6                  # nearly equal: linear interpolation is exact enough
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), _EPS)


def quat_angle_between(a, b):
    """(...,) rotation angle in radians of a^-1 b, for (..., 4) unit quaternions."""
    dot = np.abs(np.sum(np.asarray(a, dtype=np.float64) * np.asarray(b, dtype=np.float64), axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


MIRROR_X = np.diag([-1.0, 1.0, 1.0])


def mirror_points(p):
    """(..., 3) points or vectors mirrored across the camera x axis: x -> -x."""
    return np.asarray(p, dtype=np.float64) * np.array([-1.0, 1.0, 1.0])


def mirror_quat(q):
    """(..., 4) quaternion of R -> quaternion of M R M with M = diag(-1, 1, 1)."""
    return np.asarray(q, dtype=np.float64) * np.array([1.0, 1.0, -1.0, -1.0])


def mirror_axis_angle(r):
    """(..., 3) axis-angle of R -> axis-angle of M R M with M = diag(-1, 1, 1)."""
    return np.asarray(r, dtype=np.float64) * np.array([1.0, -1.0, -1.0])


def mirror_matrix(R):
    """(..., 3, 3) rotation R -> M R M with M = diag(-1, 1, 1)."""
    return MIRROR_X @ np.asarray(R, dtype=np.float64) @ MIRROR_X

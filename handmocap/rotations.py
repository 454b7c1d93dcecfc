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
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)
    return np.where(q[..., :1] < 0, -q, q)


def quat_multiply(a, b):
    """Hamilton product a * b of (..., 4) quaternions (broadcasting): rotate by b, then a."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


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


def quat_to_matrix(q):
    """(..., 4) quaternions (normalised here) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _EPS)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R):
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions, w >= 0.

    Uses whichever of w, x, y, z is largest to divide by (Shepperd's method), so it stays
    accurate for every rotation angle, including 180 degrees.
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    # 4*w^2, 4*x^2, 4*y^2, 4*z^2
    sq = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                   1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    best = np.argmax(sq, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(sq, best[..., None], -1)[..., 0], _EPS))  # 2*|largest|
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s21, s02, s10 = R[..., 2, 1] + R[..., 1, 2], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 0] + R[..., 0, 1]
    candidates = np.stack([
        np.stack([s * s, d21, d02, d10], -1),
        np.stack([d21, s * s, s10, s02], -1),
        np.stack([d02, s10, s * s, s21], -1),
        np.stack([d10, s02, s21, s * s], -1),
    ], axis=-2) / (2.0 * s[..., None, None])
    q = np.take_along_axis(candidates, best[..., None, None], -2)[..., 0, :]
    return quat_normalize(q)


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

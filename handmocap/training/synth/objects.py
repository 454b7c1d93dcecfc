"""Occluding objects: small meshes (ball, box, cylinder) as triangle soups.

A template is (P*3, 6) floats: position and unit normal of each triangle corner, in a
unit object frame (sphere radius 1, box half-size 1, cylinder radius 1 and half-length
1 along z). `place` scales, rotates and moves templates into the camera frame and keeps
the scaled local position as the pattern coordinate ("rest") the shader reads.
"""
import numpy as np

KINDS = ("sphere", "box", "cylinder")


def _sphere(n_lat=10, n_lon=16):
    lat = np.linspace(0, np.pi, n_lat + 1)
    lon = np.linspace(0, 2 * np.pi, n_lon + 1)
    p = np.stack(np.meshgrid(lat, lon, indexing="ij"), -1)
    xyz = np.stack([np.sin(p[..., 0]) * np.cos(p[..., 1]), np.sin(p[..., 0]) * np.sin(p[..., 1]),
                    np.cos(p[..., 0])], -1)
    a, b, c, d = xyz[:-1, :-1], xyz[1:, :-1], xyz[1:, 1:], xyz[:-1, 1:]
    tri = np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3)
    return np.concatenate([tri, tri], 1)


def _box():
    tris = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = [k for k in range(3) if k != axis]
            corners = []
            for cu, cv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                c = np.zeros(3)
                c[axis], c[u], c[v] = sign, cu, cv
                corners.append(c)
            normal = np.zeros(3)
            normal[axis] = sign
            quad = np.array(corners)
            for tri in (quad[[0, 1, 2]], quad[[0, 2, 3]]):
                tris.append(np.concatenate([tri, np.tile(normal, (3, 1))], 1))
    return np.concatenate(tris)


def _cylinder(n=20):
    ang = np.linspace(0, 2 * np.pi, n + 1)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    tris = []
    for k in range(n):
        a, b = ring[k], ring[k + 1]
        corners = [a - [0, 0, 1], b - [0, 0, 1], b + [0, 0, 1], a + [0, 0, 1]]
        normals = [a, b, b, a]
        for idx in ((0, 1, 2), (0, 2, 3)):
            tris.append(np.concatenate([np.array([corners[i] for i in idx]),
                                        np.array([normals[i] for i in idx])], 1))
        for z in (-1.0, 1.0):
            cap = np.array([[0, 0, z], a + [0, 0, z], b + [0, 0, z]])
            tris.append(np.concatenate([cap, np.tile([0, 0, z], (3, 1))], 1))
    return np.concatenate(tris)


TEMPLATES = {"sphere": _sphere(), "box": _box(), "cylinder": _cylinder()}


def place(kind, scale, rotation, translation):
    """(P*3, 9) float32 vertices of one object in the camera frame: position, normal,
    pattern coordinate (the scaled object-frame position, metres).

    scale (3,) metres along the object's axes; rotation (3,3) object -> camera;
    translation (3,) metres, the object's centre in the camera frame.
    """
    t = TEMPLATES[kind]
    local = t[:, :3] * scale
    normal = t[:, 3:] / scale                     # normals transform with the inverse scale
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    pos = local @ rotation.T + translation
    return np.concatenate([pos, normal @ rotation.T, local], 1).astype(np.float32)

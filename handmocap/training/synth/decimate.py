"""A smaller draw mesh for the image engine: quadric-error edge collapse onto a vertex subset.

At 128 px a hand covers ~60-100 px; the full model's ~3600 triangles are mostly smaller
than a pixel, and llvmpipe's cost grows with the triangle count (set-up and binning), not
with pixels. `decimate` collapses edges in the order of Garland & Heckbert's quadric error
(the sum of squared distances to the planes of the faces around the merged vertices,
area-weighted) until `target_faces` remain. Each collapse keeps one of the edge's two
vertices (the one with the smaller error), so the draw mesh's vertices are a subset of
the model's: every kept vertex keeps its exact template position, shape offsets,
skinning weights, normal and material, and lies exactly on the full posed surface.

A collapse is refused when it would break the closed 2-manifold (the edge's endpoints
must share exactly two neighbours), flip or degenerate a face around it, or merge
vertices of different skinning parts or materials (`labels`, `features`), so segment
borders (used by the visibility labels) and nails stay where they are as long as possible.
"""
import heapq

import numpy as np


def face_planes(vertices, faces):
    """(F,4) unit plane (n, d) with n.x + d = 0 and (F,) area of each triangle."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    norm = np.linalg.norm(cross, axis=1)
    n = cross / np.maximum(norm, 1e-18)[:, None]
    return np.concatenate([n, -(n * a).sum(1, keepdims=True)], 1), 0.5 * norm


def vertex_quadrics(vertices, faces):
    """(V,4,4) sum over a vertex's faces of area * p p^T (p the face plane)."""
    planes, area = face_planes(vertices, faces)
    K = area[:, None, None] * planes[:, :, None] * planes[:, None, :]
    Q = np.zeros((len(vertices), 4, 4))
    for k in range(3):
        np.add.at(Q, faces[:, k], K)
    return Q


def decimate(vertices, faces, target_faces, labels=None, features=None, feature_cost=1e-4, min_normal_dot=0.2):
    """Collapse edges of a closed triangle mesh until at most `target_faces` remain.

    vertices (V,3) metres, faces (F,3) int (consistently wound), labels (V,) int: vertices
    with different labels are never merged; features (V,C) floats: merging vertices that
    differ costs feature_cost * |difference|^2 extra (m^2 units, like the quadric error).
    Returns kept (K,) int — the original ids of the surviving vertices, ascending — and
    new_faces (F',3) int indexing into `kept`, wound like the input.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.array(faces, np.int64)
    n_vertices = len(vertices)
    labels = np.zeros(n_vertices, np.int64) if labels is None else np.asarray(labels)
    features = np.zeros((n_vertices, 1)) if features is None else np.asarray(features, np.float64)
    Q = vertex_quadrics(vertices, faces)
    homogeneous = np.concatenate([vertices, np.ones((n_vertices, 1))], 1)
    vertex_faces = [set() for _ in range(n_vertices)]
    for f, tri in enumerate(faces):
        for v in tri:
            vertex_faces[v].add(f)
    face_alive = np.ones(len(faces), bool)
    vertex_alive = np.ones(n_vertices, bool)
    version = np.zeros(n_vertices, np.int64)
    heap = []

    def neighbours(v):
        return {int(u) for f in vertex_faces[v] for u in faces[f]} - {v}

    def push(a, b):
        if labels[a] != labels[b]:
            return
        Qab = Q[a] + Q[b]
        err_a = homogeneous[a] @ Qab @ homogeneous[a]
        err_b = homogeneous[b] @ Qab @ homogeneous[b]
        keep, gone, err = (a, b, err_a) if err_a <= err_b else (b, a, err_b)     # ties: as above
        err += feature_cost * float(np.sum((features[a] - features[b]) ** 2))
        heapq.heappush(heap, (err, keep, gone, version[keep], version[gone]))

    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1), axis=0)
    edges = edges[labels[edges[:, 0]] == labels[edges[:, 1]]]
    Qab = Q[edges[:, 0]] + Q[edges[:, 1]]
    err = np.stack([np.einsum("ei,eij,ej->e", homogeneous[edges[:, k]], Qab, homogeneous[edges[:, k]])
                    for k in range(2)], 1)
    first = np.argmin(err, 1)                         # keep the endpoint with the smaller error
    keep, gone = edges[np.arange(len(edges)), first], edges[np.arange(len(edges)), 1 - first]
    cost = err.min(1) + feature_cost * np.sum((features[edges[:, 0]] - features[edges[:, 1]]) ** 2, 1)
    heap = [(c, k, g, 0, 0) for c, k, g in zip(cost.tolist(), keep.tolist(), gone.tolist())]
    heapq.heapify(heap)

    def normals(tris):
        p = vertices[tris]                                            # (k,3,3)
        e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        return np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                         e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], 1)

    alive_faces = len(faces)
    while alive_faces > target_faces and heap:
        _, keep, gone, v_keep, v_gone = heapq.heappop(heap)
        if not (vertex_alive[keep] and vertex_alive[gone]) or version[keep] != v_keep or version[gone] != v_gone:
            continue
        shared = vertex_faces[keep] & vertex_faces[gone]
        if len(shared) != 2 or len(neighbours(keep) & neighbours(gone)) != 2:
            continue                                  # would not stay a 2-manifold
        moved = list(vertex_faces[gone] - shared)     # faces that swap `gone` for `keep`
        old = faces[moved]
        n_old, n_new = normals(old), normals(np.where(old == gone, keep, old))
        scale = np.linalg.norm(n_old, axis=1) * np.linalg.norm(n_new, axis=1)
        if np.any((scale < 1e-20) | ((n_old * n_new).sum(1) < min_normal_dot * scale)):
            continue                                  # a face would flip or degenerate
        for f in moved:
            faces[f][faces[f] == gone] = keep
        for f in shared:
            face_alive[f] = False
            for v in faces[f]:
                vertex_faces[v].discard(f)
        alive_faces -= len(shared)
        vertex_faces[keep].update(moved)
        vertex_faces[gone] = set()
        vertex_alive[gone] = False
        Q[keep] += Q[gone]
        version[keep] += 1                            # its old heap entries are stale now
        for u in neighbours(keep):
            push(keep, u)
    kept = np.flatnonzero(vertex_alive)
    remap = np.full(n_vertices, -1, np.int64)
    remap[kept] = np.arange(len(kept))
    new_faces = remap[faces[face_alive]]
    if (new_faces < 0).any():
        raise RuntimeError("decimation left a face on a removed vertex")
    return kept, new_faces.astype(np.int32)

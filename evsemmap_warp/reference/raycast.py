"""numpy twin of ``kernels/raycast.py``: brute-force Möller-Trumbore against every triangle."""

from __future__ import annotations

import numpy as np


def cast_rays(vertices, faces, origins, directions, max_distance: float):
    """Returns (distance [N] with -1 for a miss, face [N] with -1 for a miss, unit normal [N, 3])."""
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]  # [F, 3, 3]
    origins, directions = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
    n = len(origins)
    distance, face, normal = np.full(n, -1.0), np.full(n, -1, np.int64), np.zeros((n, 3))
    if n == 0 or len(v) == 0:
        return distance, face, normal
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    face_normals = np.cross(e1, e2)
    face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
    for i in range(n):
        p = np.cross(directions[i], e2)
        det = np.einsum("fj,fj->f", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origins[i] - v[:, 0]
        u = np.einsum("fj,fj->f", s, p) * inv
        q = np.cross(s, e1)
        w = (q @ directions[i]) * inv
        t = np.einsum("fj,fj->f", e2, q) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= 0) & (t < max_distance)
        if hit.any():
            best = np.flatnonzero(hit)[np.argmin(t[hit])]
            distance[i], face[i], normal[i] = t[best], best, face_normals[best]
    return distance, face, normal

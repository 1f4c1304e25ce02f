"""Brute-force twin of the S-BKI / S-CSM compatibility path, shaped like the original C++ loops.

The engine scatters point-centrically: each (point, owner block) pair adds to the cells of its
owner block and the 6 face neighbours. The C++ gathers block-centrically: every test block T sums,
over the blocks E of its extended block that hold points, the kernel of E's points on T's cells.
This file does the latter, literally, so the tests can check that the two agree.
"""

from __future__ import annotations

import numpy as np

from .scatter import sbki_sparse_kernel

BLOCK_AND_FACE_NEIGHBOURS = [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]


def blocks_containing(p: np.ndarray, size: np.float32) -> list[tuple[int, int, int]]:
    """The blocks of edge ``size`` whose closed box holds point ``p``, in float32 as the C++ tests it (a point on a
    face lies in both blocks)."""
    half = np.float32(size / np.float32(2.0))
    per_axis = []
    for axis in range(3):
        k0 = int(np.floor(float(p[axis]) / float(size) + 0.5))
        per_axis.append([k for k in (k0 - 1, k0, k0 + 1)
                         if np.float32(np.float32(k) * size) - half <= p[axis] <= np.float32(np.float32(k) * size) + half])
    return [(x, y, z) for x in per_axis[0] for y in per_axis[1] for z in per_axis[2]]


def sbki_insert(points, labels, *, resolution_m: float, block_depth: int, ell: float, sf2: float,
                counting: bool, num_classes: int) -> dict[tuple[int, int, int], tuple[np.ndarray, bool]]:
    """One S-BKI (or, with ``counting``, S-CSM) insertion of training points [N, 3] float32 with
    labels [N]. Returns {cell index: (evidence [K] float64, touched)} for every test-block cell.
    Cell indices follow the engine's grid: for S-CSM (block_depth 1) cell i is centered at i r."""
    points = np.asarray(points, dtype=np.float32)
    size = np.float32(np.float32(2 ** (block_depth - 1)) * np.float32(resolution_m))
    n = 2 ** (block_depth - 1)
    r = np.float32(resolution_m)
    members: dict[tuple[int, int, int], list[int]] = {}
    for i, p in enumerate(points):
        for b in blocks_containing(p, size):
            members.setdefault(b, []).append(i)
    test = {tuple(np.add(b, e)) for b in members for e in BLOCK_AND_FACE_NEIGHBOURS}
    cells: dict[tuple[int, int, int], tuple[np.ndarray, bool]] = {}
    for t in sorted(test):
        first = np.array(t) * n - n // 2
        local = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
        index = first + local
        center = np.array(t, dtype=np.float32) * size
        cell_xyz = (center - size / np.float32(2.0) + (local.astype(np.float32) + np.float32(0.5)) * r).astype(np.float32)
        ybar = np.zeros((len(index), num_classes))
        sources = [t] if counting else [tuple(np.add(t, e)) for e in BLOCK_AND_FACE_NEIGHBOURS]
        has_points = any(s in members for s in sources)
        for s in sources:
            for i in members.get(s, []):
                w = np.ones(len(index)) if counting else sbki_sparse_kernel(cell_xyz, np.broadcast_to(points[i], cell_xyz.shape), np.full(len(index), ell), sf2)
                ybar[:, int(labels[i])] += w
        touched = has_points if counting else True
        for j, idx in enumerate(map(tuple, index)):
            cells[idx] = (ybar[j], touched)
    return cells

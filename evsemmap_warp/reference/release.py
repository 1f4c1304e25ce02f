"""Brute-force twin of the EvSemMap release mode's block models, shaped like the C++ loops.

The engine (``kernels/release.py``) gathers per cell over its source blocks with a multiplicity
per block. The release trains one model per block holding points, on the points of its extended
block (a point on a shared face counts once per block it lies in), and lets each model predict
for every block of its extended block that holds points. This file does the latter, literally,
with the kernel evaluated in float32 trig as the C++ does, so the tests can check that the two agree.
"""

from __future__ import annotations

import math

import numpy as np

from .sbki import BLOCK_AND_FACE_NEIGHBOURS, blocks_containing

BELIEF_EPSILON = 1e-6


def release_kernel(cells: np.ndarray, point: np.ndarray, length: float, sf2: float) -> np.ndarray:
    """covSparseUnc of the release: float32 distances divided in double by ell * e, float32 formula."""
    d = np.sqrt(np.sum((cells - point) ** 2, axis=1, dtype=np.float32), dtype=np.float32)
    x = (d.astype(np.float64) / length).astype(np.float32)
    two_pi = np.float32(2.0) * np.float32(3.1415926)
    k = ((np.float32(2.0) + np.cos(x * two_pi)) * (np.float32(1.0) - x) / np.float32(3.0) + np.sin(x * two_pi) / two_pi) * np.float32(sf2)
    return np.maximum(k, 0).astype(np.float64)


def release_insert(points, class_weights, uncertainty, *, resolution_m: float, block_depth: int, length: float, sf2: float,
                   dempster: bool) -> dict[tuple[int, int, int], np.ndarray]:
    """One release insertion of training points [N, 3] float32 with per-class weights [N, K] (class
    probabilities, or belief masses with ``dempster``). Returns {cell index: row [K + 3]}: evidence
    (Bayes) or log commonality ratio sums (Dempster), weight sum, weight * u sum, contributions."""
    points = np.asarray(points, dtype=np.float32)
    size = np.float32(np.float32(2 ** (block_depth - 1)) * np.float32(resolution_m))
    n = 2 ** (block_depth - 1)
    r = np.float32(resolution_m)
    k = class_weights.shape[1]
    members: dict[tuple[int, int, int], list[int]] = {}
    for i, p in enumerate(points):
        for b in blocks_containing(p, size):
            members.setdefault(b, []).append(i)
    local = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cells: dict[tuple[int, int, int], np.ndarray] = {}
    for block in members:  # every block holding points gets all its cells
        for idx in map(tuple, np.array(block) * n - n // 2 + local):
            cells[idx] = np.zeros(k + 3)
    for model in sorted(members):
        train = [i for e in BLOCK_AND_FACE_NEIGHBOURS for i in members.get(tuple(np.add(model, e)), [])]
        for e in BLOCK_AND_FACE_NEIGHBOURS:
            target = tuple(np.add(model, e))
            if target not in members:
                continue
            first = np.array(target) * n - n // 2
            cell_xyz = ((first + local).astype(np.float32) + np.float32(0.5)) * r
            for i in train:
                w = release_kernel(cell_xyz, points[i], length, sf2)
                for j, idx in enumerate(map(tuple, first + local)):
                    if w[j] <= 0:
                        continue
                    row = cells[idx]
                    if dempster:
                        b = np.clip(class_weights[i] * min(w[j], 1.0), 0.0, 1.0 - BELIEF_EPSILON)
                        row[:k] += np.log1p(b / max(1.0 - b.sum(), BELIEF_EPSILON))
                    else:
                        row[:k] += w[j] * class_weights[i]
                    row[k] += w[j]
                    row[k + 1] += w[j] * uncertainty[i]
                    row[k + 2] += 1
    return cells



def gather_release_blocks(blocks, source_blocks, source_mult, point_start, points, class_weights, point_uncertainty, *,
                          length: float, sf2: float, resolution_m: float, cells_per_block: int) -> dict:
    """What the gather kernel computes from its tables (Bayes fusion): {cell index: row [K + 3]}."""
    n = cells_per_block
    local = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    k = class_weights.shape[1]
    out = {}
    for b, block in enumerate(blocks):
        index = np.asarray(block) * n - n // 2 + local
        centers = (index.astype(np.float32) + np.float32(0.5)) * np.float32(resolution_m)
        rows = np.zeros((len(index), k + 3))
        for o in range(source_blocks.shape[1]):
            s = source_blocks[b, o]
            if s < 0:
                continue
            for q in range(point_start[s], point_start[s + 1]):
                w = release_kernel(centers, points[q], length, sf2)
                hit = w > 0
                rows[hit, :k] += source_mult[b, o] * w[hit, None] * class_weights[q]
                rows[hit, k] += source_mult[b, o] * w[hit]
                rows[hit, k + 1] += source_mult[b, o] * w[hit] * point_uncertainty[q]
                rows[hit, k + 2] += source_mult[b, o]
        out.update({tuple(i): r for i, r in zip(index, rows)})
    return out


def block_models(blocks: np.ndarray, target_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``kernels.release.block_models``, literally: for each block and target offset, the
    index of the block there (-1 none) and how many occupied models hold it in their extended block
    while predicting for the block."""
    where = {tuple(b): i for i, b in enumerate(np.asarray(blocks).tolist())}
    source = np.full((len(blocks), len(target_offsets)), -1, np.int32)
    mult = np.zeros_like(source)
    for b, block in enumerate(np.asarray(blocks).tolist()):
        for o, offset in enumerate(np.asarray(target_offsets).tolist()):
            src = tuple(np.add(block, offset))
            if src not in where:
                continue
            source[b, o] = where[src]
            for face in BLOCK_AND_FACE_NEIGHBOURS:
                model = tuple(np.add(src, face))
                if model in where and np.abs(np.subtract(block, model)).sum() <= 1:
                    mult[b, o] += 1
    return source, mult


def snap_to_lines(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, ds: np.float32) -> np.ndarray:
    """coord_to_voxel_center_coord per axis and point, as the C++ loop is written."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    ds = np.float32(ds)
    out = np.empty_like(points)
    for axis in range(3):
        lo_a, hi_a = np.float32(lo[axis]), np.float32(hi[axis])
        stride = np.float32((hi_a - lo_a) / ds)
        for n, p in enumerate(points[:, axis]):
            out[n, axis] = hi_a
            i = int(np.float32((p - lo_a) / ds)) - 1
            while i <= int(stride):
                cur = np.float32(lo_a + np.float32(i) * ds)
                nxt = np.float32(lo_a + np.float32(i + 1) * ds)
                if np.float32(p - cur) < np.float32(nxt - p):
                    out[n, axis] = cur
                    break
                i += 1
    return out


def keep_first_per_block(cells: np.ndarray, cap: int) -> np.ndarray:
    """Mask keeping the first ``cap`` points (input order) of each cell index."""
    cells = np.asarray(cells, np.int64)
    n = len(cells)
    if n == 0:
        return np.zeros(0, bool)
    order = np.argsort(cells, kind="stable")
    sorted_cells = cells[order]
    starts = np.r_[0, np.flatnonzero(sorted_cells[1:] != sorted_cells[:-1]) + 1]
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    keep = np.zeros(n, bool)
    keep[order[rank < cap]] = True
    return keep


def snapped_block_keys(points, lo, hi, ds, block_size) -> np.ndarray:
    """Twin of ``snapped_block_keys``: the block of each ``snap_to_lines`` point, as the C++ hashes it
    [N, 3] (int64)."""
    snapped = snap_to_lines(points, lo, hi, np.float32(ds))
    return (snapped.astype(np.float64) / np.float64(block_size) + 524288.5).astype(np.int64) - 524288


def keep_first_sorted(order, run_rank, starts, cap: int) -> np.ndarray:
    """Twin of ``keep_first_sorted``: 1 for the first ``cap`` sorted points of each run, at their input
    positions [N] (int32)."""
    order, run_rank, starts = np.asarray(order, np.int64), np.asarray(run_rank, np.int64), np.asarray(starts, np.int64)
    keep = np.zeros(len(order), np.int32)
    keep[order] = (np.arange(len(order)) - starts[run_rank - 1] < cap).astype(np.int32)
    return keep


def compact_indices(keep) -> np.ndarray:
    """Twin of ``compact_indices``: the kept indices, ascending (int32)."""
    return np.flatnonzero(np.asarray(keep) == 1).astype(np.int32)


def take_points(points, index) -> np.ndarray:
    """Twin of ``take_points``: points[index]."""
    return np.asarray(points, np.float32)[np.asarray(index, np.int64)]


def sorted_rows(points, probabilities, uncertainty, kept, point_ids, order, *, dempster: bool):
    """Twin of ``sorted_rows_kernel(K, dempster)``: the rows in block order (points, class weights, and
    uncertainty), the weights the probabilities or clip(p - u / K, 0, 1)."""
    i = np.asarray(kept, np.int64)[np.asarray(point_ids, np.int64)[np.asarray(order, np.int64)]]
    p = np.asarray(probabilities, np.float64)[i]
    u = np.asarray(uncertainty, np.float64)[i]
    if dempster:
        p = np.clip(p - u[:, None] / p.shape[1], 0.0, 1.0)
    return np.asarray(points, np.float32)[i], p, u

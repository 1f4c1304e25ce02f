"""numpy twin of ``evsemmap_warp.kernels.scatter``.

Vectorised over (point, candidate voxel) pairs, accumulated in float64 by ``np.add.at`` on a
``np.unique`` inverse index: no hash table, no code shared with the kernel. It doubles as the
"vectorised numpy implementation" that ``tools/bench_integrate.py`` times beside the kernel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MODE_RADIUS = 0
MODE_OWN_VOXEL = 1
MODE_SBKI_BLOCKS = 2
MODE_SBKI_OWN_BLOCK = 3
MODE_STENCIL = 4
FUSION_BAYES = 0
FUSION_DEMPSTER = 1
SBKI_REACH_FACTOR = 1.05
BELIEF_EPSILON = 1e-6
FACE_OFFSETS = np.array([[0, 0, 0], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])


@dataclass
class ScatterResult:
    """Per touched voxel: index [V, 3], alpha increment [V, K], weight sum, weight * u sum, hits, weighted
    height sum (sum w (z - z_c), z_c the voxel center's height; 0 in the compat modes)."""

    voxel_index: np.ndarray
    alpha_increment: np.ndarray
    weight_sum: np.ndarray
    weighted_uncertainty_sum: np.ndarray
    hits: np.ndarray
    update_count: int
    weighted_height_sum: np.ndarray


def height_offsets(points: np.ndarray, voxels: np.ndarray, resolution: float, grid_offset: float) -> np.ndarray:
    """z - z_c per (point, voxel) pair [P] (m): a point's height above its voxel's center."""
    return np.asarray(points, np.float64)[:, 2] - ((voxels[:, 2] + 0.5) * resolution + grid_offset)


# c_n of the series below, n = 2..11 (enough for float64 at t < 1/4).
_SERIES = [1 / (3 * math.factorial(2 * n)) - 1 / math.factorial(2 * n + 1) for n in range(2, 12)]


def sparse_kernel(d: np.ndarray, length: np.ndarray, sigma0: float) -> np.ndarray:
    """k'(d, l, sigma0) in float64. Near d = l the closed form cancels, so there (t = 1 - d/l < 1/4)
    t f(a), f(a) = (2 + cos a) / 3 - sin(a) / a = sum_{n>=2} (-1)^n c_n a^(2n), a = 2 pi t, is summed."""
    x = np.asarray(d, dtype=np.float64) / length
    t = 1.0 - x
    a = 2.0 * np.pi * x
    out = np.maximum((2.0 + np.cos(a)) * t / 3.0 + np.sin(a) / (2.0 * np.pi), 0.0)
    near = (t > 0) & (t < 0.25)
    b2 = (2.0 * np.pi * t[near]) ** 2
    f = np.zeros_like(b2)
    for n, c in reversed(list(enumerate(_SERIES, start=2))):
        f = f * b2 + (-1) ** n * c
    out[near] = t[near] * b2 * b2 * f
    out[t <= 0] = 0.0
    return sigma0 * out


def sincos_float32(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Correctly rounded float32 sine and cosine of float32 arguments (what the kernel's
    ``sincos_float32`` computes): the float64 values rounded once."""
    a64 = np.asarray(a, dtype=np.float32).astype(np.float64)
    return np.sin(a64).astype(np.float32), np.cos(a64).astype(np.float32)


def sbki_sparse_kernel(cells: np.ndarray, points: np.ndarray, ell: np.ndarray, sf2: float) -> np.ndarray:
    """S-BKI's covSparse in float32, as the C++ evaluates it (with correctly rounded sine and cosine)."""
    ell32 = np.asarray(ell, dtype=np.float32)[..., None]
    diff = cells.astype(np.float32) / ell32 - points.astype(np.float32) / ell32
    d = np.sqrt(np.sum(diff * diff, axis=-1, dtype=np.float32), dtype=np.float32)
    pi = np.float32(3.1415926)
    a = d * np.float32(2.0) * pi
    sin_a, cos_a = sincos_float32(a)
    k = ((np.float32(2.0) + cos_a) * (np.float32(1.0) - d) / np.float32(3.0) + sin_a / (np.float32(2.0) * pi)) * np.float32(sf2)
    return np.maximum(k, np.float32(0.0)).astype(np.float64)


# ---------------------------------------------------------------------------- the weight rules, one per method
def sparse_weight(d: np.ndarray, lengths: np.ndarray, sigma0: float) -> np.ndarray:
    """S-BKI, EBS, the ablations and Dempster (clean): k'(d, l_i, sigma0) at distance d (m)."""
    return sparse_kernel(d, lengths, sigma0)


def count_weight(n: int) -> np.ndarray:
    """S-CSM: 1 per (point, voxel) pair."""
    return np.ones(n)


def sbki_compat_weight(voxels: np.ndarray, points: np.ndarray, lengths: np.ndarray, sigma0: float, resolution: float,
                       grid_offset: float) -> np.ndarray:
    """The original S-BKI: its float32 kernel of the float32 cell centers [P, 3] and points [P, 3]."""
    centers32 = (np.asarray(voxels).astype(np.float32) + np.float32(0.5)) * np.float32(resolution) + np.float32(grid_offset)
    return sbki_sparse_kernel(centers32, np.asarray(points).astype(np.float32), np.asarray(lengths).astype(np.float32), np.float32(sigma0))


def convbki_weight(stencil_rows: np.ndarray, class_weights: np.ndarray, stencil_weights: np.ndarray) -> np.ndarray:
    """ConvBKI: per pair, the stencil's per-class weights at its offset times the point's class weights [P, K]
    (their sum is the pair's weight; pairs whose sum is not positive add nothing)."""
    return np.asarray(stencil_weights, np.float64)[stencil_rows] * np.asarray(class_weights, np.float64)


def see_csom_weight(d: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """SEE-CSOM's triangular kernel max(0, 1 - d / l)."""
    return np.maximum(1.0 - np.asarray(d, np.float64) / np.maximum(np.asarray(lengths, np.float64), 1e-300), 0.0)


def weight_rule_values(mode: int, points, lengths, class_weights, pair_point, pair_cell, *, resolution: float, grid_offset: float,
                       sigma0: float, stencil_weights=None) -> np.ndarray:
    """The weight ``mode``'s rule gives each (point pair_point[k], voxel pair_cell[k]) pair, 0 where it
    screens the voxel out (ConvBKI's offsets of no mass), without the reach tests (the traversal's)."""
    points = np.asarray(points, np.float64)
    pid, cells = np.asarray(pair_point), np.asarray(pair_cell, np.int64)
    if mode == MODE_RADIUS:
        d = np.linalg.norm((cells + 0.5) * resolution + grid_offset - points[pid], axis=1)
        return sparse_weight(d, np.asarray(lengths, np.float64)[pid], sigma0)
    if mode in (MODE_OWN_VOXEL, MODE_SBKI_OWN_BLOCK):
        return count_weight(len(pid))
    if mode == MODE_SBKI_BLOCKS:
        return sbki_compat_weight(cells, points[pid], np.asarray(lengths)[pid], sigma0, resolution, grid_offset)
    half = round(len(stencil_weights) ** (1 / 3)) // 2
    side = 2 * half + 1
    o = cells - np.floor((points[pid] - grid_offset) / resolution).astype(np.int64) + half
    mass = convbki_weight((o[:, 0] * side + o[:, 1]) * side + o[:, 2], np.asarray(class_weights)[pid], stencil_weights).sum(axis=1)
    return np.where(mass > 0, mass, 0.0)


def block_of_voxel(index: np.ndarray, cells_per_block: int) -> np.ndarray:
    """Twin of ``kernels.scatter.block_of_voxel``: the S-BKI block (``cells_per_block`` cells a side) of each
    voxel index."""
    return np.floor_divide(index + cells_per_block // 2, cells_per_block)


def candidate_pairs(points, lengths, owners, mode, resolution, grid_offset, stencil_half=0):
    """All (point, voxel) pairs a point might reach: [P] point ids and [P, 3] voxel indices."""
    n = len(points)
    if mode == MODE_STENCIL:
        own = np.floor((points - grid_offset) / resolution).astype(np.int64)
        r = np.arange(-stencil_half, stencil_half + 1)
        offsets = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
        return np.repeat(np.arange(n), len(offsets)), (own[:, None, :] + offsets[None]).reshape(-1, 3)
    if mode == MODE_OWN_VOXEL:
        return np.arange(n), np.floor((points - grid_offset) / resolution).astype(np.int64)
    if mode == MODE_SBKI_OWN_BLOCK:
        return np.arange(n), owners.astype(np.int64)
    reach = lengths * (SBKI_REACH_FACTOR if mode == MODE_SBKI_BLOCKS else 1.0)
    lo = np.floor((points - reach[:, None] - grid_offset) / resolution).astype(np.int64)
    hi = np.floor((points + reach[:, None] - grid_offset) / resolution).astype(np.int64)
    span = int((hi - lo).max()) + 1 if n else 1
    offsets = np.stack(np.meshgrid(*[np.arange(span)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    point_ids = np.repeat(np.arange(n), len(offsets))
    voxels = np.repeat(lo, len(offsets), axis=0) + np.tile(offsets, (n, 1))
    inside = np.all(voxels <= hi[point_ids], axis=1)
    return point_ids[inside], voxels[inside]


def scatter_points(
    points: np.ndarray,
    labels: np.ndarray | None,
    class_weights: np.ndarray | None,
    lengths: np.ndarray,
    point_uncertainty: np.ndarray,
    owner_blocks: np.ndarray | None,
    mode: int,
    resolution: float,
    grid_offset: float,
    sigma0: float,
    cells_per_block: int,
    num_classes: int,
    fusion: int = FUSION_BAYES,
    stencil_weights: np.ndarray | None = None,
) -> ScatterResult:
    """What one ``scatter_points`` launch adds to the map (see the kernel's docstring)."""
    points = np.asarray(points, dtype=np.float64)
    lengths = np.asarray(lengths, dtype=np.float64)
    stencil_half = round(len(stencil_weights) ** (1 / 3)) // 2 if mode == MODE_STENCIL else 0
    pid, vox = candidate_pairs(points, lengths, owner_blocks, mode, resolution, grid_offset, stencil_half)
    per_class = None  # [P, K] additions where they are not weight * y
    if mode == MODE_STENCIL:
        side = 2 * stencil_half + 1
        own = np.floor((points - grid_offset) / resolution).astype(np.int64)
        o = vox - own[pid] + stencil_half
        rows = (o[:, 0] * side + o[:, 1]) * side + o[:, 2]
        per_class = convbki_weight(rows, np.asarray(class_weights, np.float64)[pid], stencil_weights)
        weight = per_class.sum(axis=1)
        keep = weight > 0
        pid, vox, weight, per_class = pid[keep], vox[keep], weight[keep], per_class[keep]
    elif mode in (MODE_OWN_VOXEL, MODE_SBKI_OWN_BLOCK):
        weight = count_weight(len(pid))
    else:
        centers = (vox + 0.5) * resolution + grid_offset
        if mode == MODE_RADIUS:
            d = np.linalg.norm(centers - points[pid], axis=1)
            keep = d < lengths[pid]
            weight = sparse_weight(d, lengths[pid], sigma0)
        else:
            block_dist = np.abs(block_of_voxel(vox, cells_per_block) - owner_blocks[pid]).sum(axis=1)
            weight = sbki_compat_weight(vox, points[pid], lengths[pid], sigma0, resolution, grid_offset)
            keep = (block_dist <= 1) & (weight > 0)
        pid, vox, weight = pid[keep], vox[keep], weight[keep]
        if fusion == FUSION_DEMPSTER:
            weight = np.minimum(weight, 1.0)
            beliefs = np.clip(np.asarray(class_weights, np.float64)[pid] * weight[:, None], 0.0, 1.0 - BELIEF_EPSILON)
            uncommitted = np.maximum(1.0 - beliefs.sum(axis=1), BELIEF_EPSILON)
            per_class = np.log1p(beliefs / uncommitted[:, None])

    uniq, inverse = unique_rows(vox)
    alpha = np.zeros((len(uniq), num_classes))
    if per_class is not None:
        for k in range(num_classes):
            alpha[:, k] = np.bincount(inverse, weights=per_class[:, k], minlength=len(uniq))
    elif labels is not None:
        flat = inverse * num_classes + np.asarray(labels)[pid]
        alpha = np.bincount(flat, weights=weight, minlength=len(uniq) * num_classes).reshape(len(uniq), num_classes)
    else:
        cw = np.asarray(class_weights, dtype=np.float64)[pid]
        for k in range(num_classes):
            alpha[:, k] = np.bincount(inverse, weights=weight * cw[:, k], minlength=len(uniq))
    weight_sum = np.bincount(inverse, weights=weight, minlength=len(uniq))
    unc_sum = np.bincount(inverse, weights=weight * np.asarray(point_uncertainty, dtype=np.float64)[pid], minlength=len(uniq))
    hits = np.bincount(inverse, minlength=len(uniq))
    keeps_heights = mode in (MODE_RADIUS, MODE_OWN_VOXEL, MODE_STENCIL)  # the clean modes; the compat modes' rows are the originals'
    offsets = height_offsets(points[pid], vox, resolution, grid_offset) if keeps_heights else np.zeros(len(pid))
    height_sum = np.bincount(inverse, weights=weight * offsets, minlength=len(uniq))
    return ScatterResult(uniq.reshape(-1, 3), alpha, weight_sum, unc_sum, hits, len(pid), height_sum)


def scatter_block_targets(
    points: np.ndarray,
    labels: np.ndarray,
    point_uncertainty: np.ndarray,
    owner_blocks: np.ndarray,
    target_lengths: np.ndarray,
    resolution: float,
    grid_offset: float,
    cells_per_block: int,
    num_classes: int,
) -> ScatterResult:
    """SEE-CSOM: every cell of every target block with a positive length gets max(0, 1 - d / l)."""
    n = cells_per_block
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    pid, vox, ell = [], [], []
    for j, offset in enumerate(FACE_OFFSETS):
        use = np.flatnonzero(target_lengths[:, j] > 0)
        first = (np.asarray(owner_blocks, np.int64)[use] + offset) * n - n // 2
        pid.append(np.repeat(use, len(cells)))
        vox.append((first[:, None, :] + cells[None]).reshape(-1, 3))
        ell.append(np.repeat(target_lengths[use, j], len(cells)))
    pid, vox, ell = np.concatenate(pid), np.concatenate(vox), np.concatenate(ell).astype(np.float64)
    centers = (vox + 0.5) * resolution + grid_offset
    weight = see_csom_weight(np.linalg.norm(centers - np.asarray(points, np.float64)[pid], axis=1), ell)
    uniq, inverse = unique_rows(vox)
    flat = inverse * num_classes + np.asarray(labels)[pid]
    alpha = np.bincount(flat, weights=weight, minlength=len(uniq) * num_classes).reshape(len(uniq), num_classes)
    weight_sum = np.bincount(inverse, weights=weight, minlength=len(uniq))
    unc_sum = np.bincount(inverse, weights=weight * np.asarray(point_uncertainty, np.float64)[pid], minlength=len(uniq))
    height_sum = np.bincount(inverse, weights=weight * height_offsets(np.asarray(points, np.float64)[pid], vox, resolution, grid_offset),
                             minlength=len(uniq))
    return ScatterResult(uniq.reshape(-1, 3), alpha, weight_sum, unc_sum, np.bincount(inverse, minlength=len(uniq)), len(pid), height_sum)


def unique_rows(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(index, axis=0, return_inverse=True) for int rows, via one int64 per row (much faster)."""
    if len(index) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    lo = index.min(axis=0)
    span = index.max(axis=0) - lo + 1
    packed = ((index[:, 0] - lo[0]) * span[1] + (index[:, 1] - lo[1])) * span[2] + (index[:, 2] - lo[2])
    keys, inverse = np.unique(packed, return_inverse=True)
    rows = np.stack([keys // (span[1] * span[2]), (keys // span[2]) % span[1], keys % span[2]], axis=1) + lo
    return rows, inverse.reshape(-1)


def insert_block_cells(blocks: np.ndarray, cells_per_block: int) -> np.ndarray:
    """Voxel indices [B * n^3, 3] of every cell of the given blocks."""
    n = cells_per_block
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    first = np.asarray(blocks, dtype=np.int64) * n - n // 2
    return (first[:, None, :] + cells[None]).reshape(-1, 3)

"""numpy twin of ``kernels/sorted_scatter.py``: the same stages, vectorised."""

from __future__ import annotations

import numpy as np

from .hash_table import pack_key, unpack_key
from .scatter import MODE_RADIUS, candidate_pairs, height_offsets, sparse_kernel


def radius_pairs(points, lengths, resolution, grid_offset):
    """Point ids, voxel indices and distances of the pairs with the voxel center within the length."""
    points, lengths = np.asarray(points, np.float64), np.asarray(lengths, np.float64)
    point_id, index = candidate_pairs(points, lengths, None, MODE_RADIUS, resolution, grid_offset)
    d = np.linalg.norm((index + 0.5) * resolution + grid_offset - points[point_id], axis=1)
    inside = d < lengths[point_id]
    return point_id[inside], index[inside], d[inside]


def count_pairs(points, lengths, resolution, grid_offset) -> np.ndarray:
    """Twin of ``kernels.sorted_scatter.count_pairs``: how many voxel centers lie strictly within each
    point's length [N] (points and lengths in m, relative to the map origin)."""
    point_id = radius_pairs(points, lengths, resolution, grid_offset)[0]
    return np.bincount(point_id, minlength=len(points))


def expand_pairs(points, lengths, resolution, grid_offset, sigma0):
    """Pairs in point order: keys, point ids, weights."""
    point_id, index, d = radius_pairs(points, lengths, resolution, grid_offset)
    order = np.argsort(point_id, kind="stable")
    weights = sparse_kernel(d, np.asarray(lengths, np.float64)[point_id], sigma0)
    return pack_key(index[order]), point_id[order], weights[order]


def mark_heads(sorted_keys: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.sorted_scatter.mark_heads``: 1 where a run of equal sorted keys starts, else 0 [N]
    int32."""
    return np.r_[True, sorted_keys[1:] != sorted_keys[:-1]].astype(np.int32) if len(sorted_keys) else np.zeros(0, np.int32)


def segment_starts(heads: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.sorted_scatter.segment_starts``: the positions of the heads, the first sorted pair
    of each distinct voxel."""
    return np.flatnonzero(heads)


def reduce_voxels(sorted_keys, pair_point, pair_weight, class_weights, point_uncertainty, points, resolution, grid_offset):
    """Per distinct key: its key, the class sums, weight sum, weight * u sum, count and weighted height sum
    (sum w (z - z_c), z_c its center's height; ``points`` [N, 3] m, on the lattice of ``resolution`` and
    ``grid_offset``)."""
    starts = segment_starts(mark_heads(sorted_keys))
    seg = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(sorted_keys)]))
    k = class_weights.shape[1]
    rows = np.zeros((len(starts), k + 4))
    offsets = height_offsets(np.asarray(points, np.float64)[pair_point], unpack_key(sorted_keys), resolution, grid_offset)
    np.add.at(rows, seg, np.column_stack([pair_weight[:, None] * class_weights[pair_point], pair_weight,
                                          pair_weight * point_uncertainty[pair_point], np.ones(len(seg)), pair_weight * offsets]))
    return sorted_keys[starts], rows

"""numpy twin of ``kernels/hashgrid_gather.py``: the reached voxels, then per voxel the sums of the
points whose length reaches its center (vectorised over (point, voxel) pairs; no hash grid)."""

from __future__ import annotations

import numpy as np

from .hash_table import pack_key
from .sorted_scatter import radius_pairs
from .scatter import height_offsets, sparse_kernel


def mark_reached(points, lengths, resolution, grid_offset) -> np.ndarray:
    """The distinct packed keys of the voxels the points reach, ascending."""
    return np.unique(pack_key(radius_pairs(points, lengths, resolution, grid_offset)[1]))


def gather_voxels(points, lengths, class_weights, point_uncertainty, resolution, grid_offset, sigma0):
    """Per reached voxel (ascending key): class sums [V, K], weight sum, weight * u sum, count, weighted height
    sum (sum w (z - z_c), z_c its center's height)."""
    point_id, index, d = radius_pairs(points, lengths, resolution, grid_offset)
    keys, inverse = np.unique(pack_key(index), return_inverse=True)
    w = sparse_kernel(d, np.asarray(lengths, np.float64)[point_id], sigma0)
    k = class_weights.shape[1]
    rows = np.zeros((len(keys), k + 4))
    offsets = height_offsets(np.asarray(points, np.float64)[point_id], index, resolution, grid_offset)
    np.add.at(rows, inverse.reshape(-1), np.column_stack([w[:, None] * class_weights[point_id], w, w * point_uncertainty[point_id], np.ones(len(w)),
                                                          w * offsets]))
    return keys, rows

"""SEE-CSOM's per-scan block statistics (docs/compatibility.md §3.2-3.3): which blocks may use which points,
and with which length. The scatter itself is ``kernels.scatter.scatter_block_targets``.

Blocks are 2x2x2 voxels (block_depth 2). Per block with points: class entropy
H = 1 - max_k n_k / N + ln(m) / (C ln C) (m distinct labels), length res * (3 + 2 H); a block with
H <= 0.3 is inferred from its own points only, otherwise from its own and its 6 face neighbours'
points. An empty block with >= 2 non-empty face neighbours ("sandwiched") is inferred from all its
neighbours' points with length 5 * res. Other empty blocks stay untouched.
"""

from __future__ import annotations

import numpy as np

from ..voxel_keys import pack_voxel_keys

CELLS_PER_BLOCK = 2
ENTROPY_GATE = 0.3  # hard-coded in the original
SANDWICH_NEIGHBOURS = 2
FACE_OFFSETS = np.array([[0, 0, 0], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])


def block_of_points(points: np.ndarray, resolution_m: float, grid_offset_m: float = 0.0) -> np.ndarray:
    """[N, 3] block index of each point (block b holds voxels 2b - 1 and 2b on each axis)."""
    voxel = np.floor((np.asarray(points, np.float64) - grid_offset_m) / resolution_m).astype(np.int64)
    return np.floor_divide(voxel + CELLS_PER_BLOCK // 2, CELLS_PER_BLOCK)


def _pack(blocks: np.ndarray) -> np.ndarray:
    """Block indices [..., 3] -> one sortable int64 each (the hash table's key packing)."""
    return pack_voxel_keys(blocks.reshape(-1, 3)).reshape(blocks.shape[:-1])


def block_entropy(histogram: np.ndarray, num_classes: int) -> np.ndarray:
    """H_B per block from its label histogram [B, C]."""
    total = histogram.sum(axis=1)
    distinct = (histogram > 0).sum(axis=1)
    return 1.0 - histogram.max(axis=1) / total + np.log(distinct) / (num_classes * np.log(num_classes))


def block_targets(points: np.ndarray, labels: np.ndarray, num_classes: int, resolution_m: float, grid_offset_m: float = 0.0):
    """(owner blocks [N, 3], target lengths [N, 7]): length > 0 where point i contributes to block
    owner + FACE_OFFSETS[j], 0 where it does not."""
    owners = block_of_points(points, resolution_m, grid_offset_m)
    n = len(points)
    lengths = np.zeros((n, 7))
    if n == 0:
        return owners.astype(np.int32), lengths
    keys = _pack(owners)
    block_keys, inverse = np.unique(keys, return_inverse=True)
    histogram = np.zeros((len(block_keys), num_classes), np.int64)
    np.add.at(histogram, (inverse.ravel(), np.asarray(labels, np.int64)), 1)
    entropy = block_entropy(histogram, num_classes)
    own_length = resolution_m * (3 + 2 * entropy)
    uses_neighbours = entropy > ENTROPY_GATE
    # Empty blocks next to occupied ones: how many occupied face neighbours each has.
    unique_blocks = owners[np.unique(inverse.ravel(), return_index=True)[1]]
    neighbour_keys = _pack(unique_blocks[:, None, :] + FACE_OFFSETS[None, 1:]).ravel()
    empty = neighbour_keys[~np.isin(neighbour_keys, block_keys)]
    empty_keys, empty_counts = np.unique(empty, return_counts=True)
    sandwiched = empty_keys[empty_counts >= SANDWICH_NEIGHBOURS]
    lengths[:, 0] = own_length[inverse.ravel()]
    for j in range(1, 7):
        target = _pack(owners + FACE_OFFSETS[j])
        pos = np.clip(np.searchsorted(block_keys, target), 0, len(block_keys) - 1)
        occupied = block_keys[pos] == target
        lengths[occupied, j] = np.where(uses_neighbours[pos[occupied]], own_length[pos[occupied]], 0.0)
        lengths[~occupied & np.isin(target, sandwiched), j] = 5 * resolution_m
    return owners.astype(np.int32), lengths

"""numpy twin of ``kernels/block_gather.py``: the S-BKI gather from its tables, literally."""

from __future__ import annotations

import numpy as np

from .device_counts import PAST_COUNT_KEY
from .scatter import SBKI_REACH_FACTOR, sbki_sparse_kernel


def gather_sbki_blocks(test_blocks, sources, point_start, points, labels, *, length: float, sigma0: float, resolution_m: float,
                       cells_per_block: int, num_classes: int, grid_offset_m: float = 0.0) -> dict:
    """{cell index: row [K + 2]}: evidence, weight sum, contributions, for every cell of every test block."""
    n = cells_per_block
    local = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    out = {}
    for b, block in enumerate(np.asarray(test_blocks)):
        index = block * n - n // 2 + local
        centers64 = (index + 0.5) * resolution_m + grid_offset_m
        centers32 = ((index.astype(np.float32) + np.float32(0.5)) * np.float32(resolution_m) + np.float32(grid_offset_m)).astype(np.float32)
        rows = np.zeros((len(index), num_classes + 2))
        for s in sources[b]:
            if s < 0:
                continue
            for q in range(point_start[s], point_start[s + 1]):
                near = np.sum((centers64 - points[q]) ** 2, axis=1) < (length * SBKI_REACH_FACTOR) ** 2
                w = sbki_sparse_kernel(centers32, np.broadcast_to(points[q], centers32.shape), np.full(len(index), length), sigma0)
                hit = near & (w > 0)
                rows[hit, labels[q]] += w[hit]
                rows[hit, num_classes] += w[hit]
                rows[hit, num_classes + 1] += 1
        out.update({tuple(i): r for i, r in zip(index, rows)})
    return out


def extended_block_tables(keys: np.ndarray, shifts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(test block keys [T] ascending, sources [T, F]) of distinct block ``keys`` [B] packed so that the
    block at offset f of key k has key k + shifts[f]: every t with a block at t + shifts[f] for some f,
    and the index of that block (-1: none), looked up block by block."""
    keys = np.asarray(keys, np.int64)
    index_of = {int(k): b for b, k in enumerate(keys)}
    tests = np.unique((keys[:, None] - np.asarray(shifts, np.int64)[None]).reshape(-1))
    sources = np.array([[index_of.get(int(t + s), -1) for s in shifts] for t in tests], np.int64).reshape(-1, len(shifts))
    return tests, sources


def extended_block_tables_wide(blocks: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(test blocks [T, 3] in key order, sources [T, F]) of distinct ``blocks`` [B, 3]: every t with a block
    at t + offsets[f] for some f, and the index of that block (-1: none), looked up block by block."""
    blocks = np.asarray(blocks, np.int64).reshape(-1, 3)
    offsets = np.asarray(offsets, np.int64).reshape(-1, 3)
    index_of = {tuple(block): b for b, block in enumerate(blocks.tolist())}
    tests = np.unique((blocks[:, None, :] - offsets[None]).reshape(-1, 3), axis=0)
    sources = np.array([[index_of.get(tuple(t + o), -1) for o in offsets.tolist()] for t in tests], np.int64).reshape(-1, len(offsets))
    return tests, sources


def block_bounds(blocks) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``block_bounds``: the blocks' per-axis minimum and maximum [3], [3] (int64)."""
    blocks = np.asarray(blocks, np.int64).reshape(-1, 3)
    return blocks.min(axis=0), blocks.max(axis=0)


def box_positions(blocks, lowest, span_y: int, span_z: int, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``box_positions``: row-major positions in the box from ``lowest`` of the first ``count`` blocks
    (None: all), then ``PAST_COUNT_KEY`` [P], and 0 .. P - 1."""
    blocks = np.asarray(blocks, np.int64).reshape(-1, 3)
    count = len(blocks) if count is None else count
    relative = blocks[:count] - np.asarray(lowest, np.int64)
    positions = (relative[:, 0] * span_y + relative[:, 1]) * span_z + relative[:, 2]
    return np.r_[positions, np.full(len(blocks) - count, PAST_COUNT_KEY, np.int64)], np.arange(len(blocks), dtype=np.int64)


def packed_box_positions(blocks, lowest, span_y: int, span_z: int, position_bits: int) -> np.ndarray:
    """Twin of ``packed_box_positions``: each block's position in the box << position_bits | its row [P] int64."""
    positions, rows = box_positions(blocks, lowest, span_y, span_z)
    return (positions << position_bits) | rows


def distinct_blocks(member_blocks, order, starts, grid_lowest, grid_shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twin of ``distinct_blocks``: each run's block in map and grid coordinates [B, 3] (int32) and the grid
    [grid_shape] of block indices (-1 elsewhere)."""
    firsts = np.asarray(order, np.int64)[np.asarray(starts, np.int64)[:-1]]
    blocks = np.asarray(member_blocks, np.int64)[firsts]
    grid_blocks = blocks - np.asarray(grid_lowest, np.int64)
    grid = np.full(tuple(grid_shape), -1, np.int32)
    grid[tuple(grid_blocks.T)] = np.arange(len(blocks))
    return blocks.astype(np.int32), grid_blocks.astype(np.int32), grid


def mark_test_blocks(grid_blocks, offsets, grid_shape) -> np.ndarray:
    """Twin of ``mark_test_blocks``: 1 (flat, row-major) at every block + offset [prod(grid_shape)] (int32)."""
    marked = np.zeros(tuple(grid_shape), np.int32)
    cells = (np.asarray(grid_blocks, np.int64)[:, None, :] + np.asarray(offsets, np.int64)[None]).reshape(-1, 3)
    marked[tuple(cells.T)] = 1
    return marked.reshape(-1)


def list_test_blocks(marked, grid, offsets, grid_lowest) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``list_test_blocks``: the marked cells in grid order, in map coordinates [T, 3], and their
    sources, the grid at cell + offset, [T, F]."""
    grid = np.asarray(grid)
    cells = np.stack(np.unravel_index(np.flatnonzero(np.asarray(marked)), grid.shape), axis=1)
    sources = np.stack([grid[tuple((cells + np.asarray(f)).T)] for f in np.asarray(offsets, np.int64)], axis=1) if len(cells) else np.zeros((0, len(offsets)), np.int32)
    return (cells + np.asarray(grid_lowest, np.int64)).astype(np.int32), sources


def sorted_block_points(points, labels, point_ids, order, length) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``sorted_block_points``: the pairs' points in block order divided by ell in float32, and
    their labels (int32)."""
    ids = np.asarray(point_ids, np.int64)[np.asarray(order, np.int64)]
    return np.asarray(points, np.float32)[ids] / np.float32(length), np.asarray(labels)[ids].astype(np.int32)


# The faces of a block in the order of its sources after the block itself: +x, -x, +y, -y, +z, -z.
FACE_OFFSETS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.int64)


def near_face_masks(scaled_points, point_start, blocks, *, cells_per_block: int, resolution: float, grid_offset: float, length: float,
                    reach2: float = 1.0) -> np.ndarray:
    """Twin of ``near_face_masks``: [ceil(P / 64), 6] int64, bit i of [w, f] set where sorted point 64 w + i
    (of block s, blocks[s], owning point_start[s]:point_start[s + 1]) lies, along face f's axis, less than
    sqrt(reach2) (over ell) from the box of the scaled cell centers of the test block blocks[s] - face f."""
    points = np.asarray(scaled_points, np.float32).reshape(-1, 3)
    starts = np.asarray(point_start, np.int64)
    owner = np.repeat(np.arange(len(starts) - 1), np.diff(starts))[:len(points)]
    n = cells_per_block
    words = -(-len(points) // 64)
    masks = np.zeros((words, 6), np.uint64)
    for f, offset in enumerate(FACE_OFFSETS):
        axis = int(np.flatnonzero(offset)[0])
        test_first = (np.asarray(blocks, np.int64)[owner, axis] - offset[axis]) * n - n // 2
        scaled = [((first.astype(np.float32) + np.float32(0.5)) * np.float32(resolution) + np.float32(grid_offset)) / np.float32(length)
                  for first in (test_first, test_first + n - 1)]
        x = points[:, axis]
        d = np.maximum(np.maximum(scaled[0] - x, x - scaled[1]), np.float32(0))
        for q in np.flatnonzero(d * d < np.float32(reach2)):
            masks[q // 64, f] |= np.uint64(1) << np.uint64(q % 64)
    return masks.view(np.int64)


def narrow_starts(wide) -> np.ndarray:
    """Twin of ``narrow_starts``: the starts as int32."""
    return np.asarray(wide, np.int64).astype(np.int32)

"""numpy twin of ``kernels/block_gather.py``: the S-BKI gather from its tables, literally."""

from __future__ import annotations

import numpy as np

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


def extended_block_tables(blocks: np.ndarray, grid: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(test blocks [T, 3] in grid order, sources [T, F]) for grid coordinates ``blocks`` (see the kernel)."""
    blocks = np.asarray(blocks, np.int64).reshape(-1, 3)
    marked = np.zeros(grid.shape, bool)
    for offset in offsets:
        marked[tuple((blocks + offset).T)] = True
    tests = np.argwhere(marked)
    sources = np.stack([grid[tuple((tests + offset).T)] for offset in offsets], axis=1) if len(tests) else np.zeros((0, len(offsets)), np.int64)
    return tests, sources

"""The release mode's per-scan preprocessing, as the released EvSemMap C++ does it (junwon-vision/EvSemMap,
docs/compatibility.md §4).

What ``SemanticBKIOctoMap::insert_pointcloud`` does before its models (with soft media and the
adaptive/threshold policy of the release's ``ebs`` and ``dempster`` configs):

1. the uncertainty cut: u = K / sum(alpha) in double; the threshold is the float32 value at index
   int(N * unc_thres) of the ascending u (stored as float32); points with double u <= it are kept (ties kept);
2. the "ds" step: each kept point is snapped per axis to the nearest line of a ds-grid anchored at the
   kept points' float32 bounding-box minimum (its search loop: ties go up, past the last line the
   maximum), the snapped point is hashed by its 0.4 m block, and each block keeps its first
   ds_multiplier + 1 points in input order (at their own, unsnapped coordinates);
3. no free-space samples: every mapped cell holds hits only.

The models and their updates (each block holding points trains on its own and its 6 face neighbours'
points and predicts for those of its face neighbours that hold points) are the gather kernel
``kernels.release``; ``release_blocks`` prepares its tables. This is the host path a CPU map takes; for a
GPU map the steps after the cut run as parallel kernels on the device (``methods.release_device``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import release
from ..voxel_keys import column_bounds, pack_voxel_keys
from .sbki_compat import dense_block_grid, group_by_block

# Offsets of the target blocks a point can reach through one model: L1 distance <= 2 (1 + 6 + 12 + 6).
TARGET_BLOCK_OFFSETS = np.array(
    [o for o in np.ndindex(5, 5, 5) if sum(abs(c - 2) for c in o) <= 2], dtype=np.int64) - 2
FACE_OFFSETS = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64)


def _models_by_mask() -> np.ndarray:
    """[25, 2^7]: for target offset o and a mask of which of a block's FACE_OFFSETS neighbours (and
    itself) hold points, how many of those models carry the points of block + o into the block: the
    models m with |m - o|_1 <= 1, i.e. block + o lies in m's extended block."""
    carries = np.abs(TARGET_BLOCK_OFFSETS[:, None, :] - FACE_OFFSETS[None, :, :]).sum(axis=2) <= 1  # [25, 7]
    bits = (np.arange(1 << len(FACE_OFFSETS))[:, None] >> np.arange(len(FACE_OFFSETS))) & 1  # [128, 7]
    return (carries.astype(np.int32) @ bits.T.astype(np.int32)).astype(np.int32)


MODELS_BY_MASK = _models_by_mask()

# The C++ hashes blocks as int64(x / (double) size + 524288.5): the nearest block center for |x| < 2^19 blocks.
_BLOCK_KEY_SHIFT = 524288.5


def kernel_length(length_m: float) -> float:
    """The release divides its float32 distances in double by ell * e, its ell a float32."""
    return float(np.float32(length_m)) * math.e


def uncertainty_cut(uncertainty: np.ndarray, keep_quantile: float) -> tuple[np.ndarray, float]:
    """The release's per-scan cut on u = K / sum(alpha) (double): keep u <= the float32 value at index
    int(N * keep_quantile) of the ascending u."""
    u = np.asarray(uncertainty, dtype=np.float64)
    n = len(u)
    if n == 0:
        return np.zeros(0, bool), float("nan")
    index = min(int(n * keep_quantile), n - 1)
    threshold = float(np.partition(u.astype(np.float32), index)[index])
    return u <= threshold, threshold


def snapped_points(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, ds: np.float32) -> np.ndarray:
    """coord_to_voxel_center_coord per axis, in float32 as the C++ loop runs it, for [N, 3] float32
    points (``kernels.release.snap_to_lines``; in numpy this took a fifth of the release mode's host work)."""
    snapped = wp.empty(len(points), dtype=wp.vec3, device="cpu")
    if len(points):
        wp.launch(release.snap_to_lines, dim=1, device="cpu", inputs=[
            wp.array(np.ascontiguousarray(points, dtype=np.float32), dtype=wp.vec3, device="cpu", copy=False), wp.vec3(*[float(v) for v in lo]),
            wp.vec3(*[float(v) for v in hi]), float(ds), snapped])
    return snapped.numpy().reshape(-1, 3)


def snapped_block_keys(points: np.ndarray, ds_resolution_m: float, block_size: np.float32) -> np.ndarray:
    """The block each point is counted in by the "ds" step: [N, 3] int64 (C++ key fields, offset removed)."""
    points = np.asarray(points, dtype=np.float32)
    lo, hi = column_bounds(points)
    return block_hash(snapped_points(points, lo, hi, np.float32(ds_resolution_m)), block_size)


def block_hash(points: np.ndarray, block_size: np.float32) -> np.ndarray:
    """The block [N, 3] (int64) the C++ hashes each float32 point [N, 3] into: int64(x / size + 524288.5) in
    double, the offset removed."""
    size = np.float64(np.float32(block_size))
    return (np.asarray(points, np.float32).astype(np.float64) / size + _BLOCK_KEY_SHIFT).astype(np.int64) - int(_BLOCK_KEY_SHIFT)


# Above this many cells the blocks' bounding box is too large for a dense count: the keys are ranked by
# a sort instead (int32 counts: 64 MB at this size).
MAX_DENSE_BLOCK_COUNTS = 1 << 24


def first_per_block(block_keys: np.ndarray, cap: int) -> np.ndarray:
    """Mask keeping the first ``cap`` points (input order) of each block key [N, 3], counted by
    ``kernels.release.keep_first_per_block`` on a dense grid over the keys' bounding box, or, when that
    box is too large, over the distinct keys (numbered by a sort)."""
    block_keys = np.asarray(block_keys, dtype=np.int64).reshape(-1, 3)
    n = len(block_keys)
    if n == 0:
        return np.zeros(0, bool)
    lo, hi = column_bounds(block_keys)
    span = hi - lo + 1
    if float(np.prod(span.astype(np.float64))) > MAX_DENSE_BLOCK_COUNTS:
        distinct, cells = np.unique(pack_voxel_keys(block_keys), return_inverse=True)
        cell_count = len(distinct)
    else:
        relative = block_keys - lo
        cells = (relative[:, 0] * span[1] + relative[:, 1]) * span[2] + relative[:, 2]
        cell_count = int(np.prod(span))
    keep = wp.empty(n, dtype=wp.uint8, device="cpu")
    wp.launch(release.keep_first_per_block, dim=1, device="cpu", inputs=[
        wp.array(cells.reshape(-1).astype(np.int32), dtype=int, device="cpu", copy=False), int(cap), wp.zeros(cell_count, dtype=int, device="cpu"), keep])
    return keep.numpy().astype(bool)


@dataclass
class ReleaseBlocks:
    """One scan's blocks and models for the gather kernel: the blocks holding points [B, 3] (key
    order), the (point, block) pairs sorted by block (``pair_order`` into the pairs, block s owning
    sorted pairs point_start[s]:point_start[s + 1]), and per block and TARGET_BLOCK_OFFSETS entry o
    the block at blocks[b] + o (-1 if it holds no points) and how many models carry its points into b."""

    blocks: np.ndarray
    pair_order: np.ndarray
    point_start: np.ndarray
    source_blocks: np.ndarray
    source_mult: np.ndarray


def release_blocks(member_blocks: np.ndarray, *, device: str = "cpu") -> ReleaseBlocks:
    """The gather kernel's tables for one scan's (point, block) memberships [P, 3], the per-block ones
    from ``kernels.release.block_models`` on ``device`` (``block_model_tables``)."""
    blocks, keys, order, point_start = group_by_block(member_blocks)
    grid, lo = dense_block_grid(blocks)
    source, mult = block_model_tables(blocks, keys, grid, lo, device)
    return ReleaseBlocks(blocks, order, point_start, source, mult)


def block_model_tables(blocks: np.ndarray, keys: np.ndarray, grid: np.ndarray | None, lo, device: str) -> tuple[np.ndarray, np.ndarray]:
    """``kernels.release.block_models`` over every block: the source blocks and model counts [B, 25],
    the blocks found on their dense grid (``dense_block_grid``) or, where there is none, by a binary
    search over their packed ``keys``."""
    n, m = len(blocks), len(TARGET_BLOCK_OFFSETS)
    if n == 0:
        return np.zeros((0, m), np.int32), np.zeros((0, m), np.int32)
    source = wp.empty((n, m), dtype=int, device=device)
    mult = wp.empty((n, m), dtype=int, device=device)
    if grid is not None:
        lookup = release.block_lookup(grid=wp.array(grid, dtype=int, device=device, copy=False), lo=lo)
    else:
        lookup = release.block_lookup(keys=wp.array(np.ascontiguousarray(keys, dtype=np.int64), dtype=wp.int64, device=device, copy=False))
    wp.launch(release.block_models_kernel(grid is not None), dim=n, device=device, inputs=[
        wp.array(blocks.astype(np.int32), dtype=wp.vec3i, device=device, copy=False), wp.array([n], dtype=int, device=device), lookup,
        wp.array(TARGET_BLOCK_OFFSETS.astype(np.int32), dtype=wp.vec3i, device=device, copy=False),
        wp.array(FACE_OFFSETS.astype(np.int32), dtype=wp.vec3i, device=device, copy=False),
        wp.array(MODELS_BY_MASK, dtype=int, device=device, copy=False), source, mult])
    return source.numpy(), mult.numpy()

"""The release mode's per-scan preprocessing after its uncertainty cut (``release_compat``: the "ds" snap,
the per-block cap, the memberships, the block models) and the gather kernel's rows, built on the map's
device by parallel kernels for maps on a GPU: the same inputs bit for bit as the host path
(tests/test_release_device.py holds them together on Warp's CPU backend). The range filter and the cut
(a quantile of the scan's uncertainty) stay on the host, so that only the points they keep are sent.

What still reads back per scan: the bounds of the snapped keys and of the memberships' blocks, the
kept and the block counts (small values that size the next arrays), and the blocks, for the key-range
check and the shards' split.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import release
from ..voxel_keys import column_bounds
from . import release_compat, sbki_device
from .sbki_device import inclusive_scan, last_value


def capped_points_on_device(points: wp.array, lo: np.ndarray, hi: np.ndarray, ds_resolution_m: float, block_size: np.float32,
                            cap: int) -> wp.array:
    """``release_compat.snapped_block_keys`` then ``release_compat.first_per_block`` on the points' device:
    the indices [M] (int, ascending) of the points [N] (float32 bounds lo, hi) each block keeps."""
    device = points.device
    n = points.shape[0]
    keys = wp.empty((n, 3), dtype=wp.int64, device=device)
    wp.launch(release.snapped_block_keys, dim=n, device=device, inputs=[
        points, wp.vec3(*[float(v) for v in lo]), wp.vec3(*[float(v) for v in hi]), float(np.float32(ds_resolution_m)),
        float(np.float64(np.float32(block_size))), keys])
    order, run_rank, starts, _ = sbki_device.sort_by_block(keys, *sbki_device.block_bounds_on_device(keys))
    keep = wp.empty(n, dtype=int, device=device)
    wp.launch(release.keep_first_sorted, dim=n, device=device, inputs=[order, run_rank, starts, int(cap), keep])
    slot = inclusive_scan(keep)
    kept = wp.empty(last_value(slot), dtype=int, device=device)
    wp.launch(release.compact_indices, dim=n, device=device, inputs=[keep, slot, kept])
    return kept


@dataclass
class DeviceReleaseInputs:
    """One scan's gather-kernel arrays on the device (``kernels.release.release_blocks``' fields) and its
    blocks on the host ([B, 3] int64)."""

    blocks: np.ndarray
    device_blocks: wp.array
    source_blocks: wp.array
    source_mult: wp.array
    point_start: wp.array
    points: wp.array
    class_weights: wp.array
    uncertainty: wp.array
    kept_points: int


def release_inputs_on_device(points: np.ndarray, probabilities: np.ndarray, uncertainty: np.ndarray, *, ds_resolution_m: float,
                             block_size: np.float32, cap: int, dempster: bool, device: str) -> DeviceReleaseInputs | None:
    """The release's inputs from the points its cut keeps (float32 [N, 3], their probabilities [N, K] and
    uncertainty [N], float64): the capped points, their memberships, the block models and the rows
    sorted by block; None where the host path would not use a dense grid (the caller takes the host path)."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    on_device = wp.array(points, dtype=wp.vec3, device=device)
    kept = capped_points_on_device(on_device, *column_bounds(points), ds_resolution_m, block_size, cap)
    kept_points = wp.empty(kept.shape[0], dtype=wp.vec3, device=device)
    wp.launch(release.take_points, dim=kept.shape[0], device=device, inputs=[on_device, kept, kept_points])
    point_ids, member_blocks = sbki_device.block_memberships_on_device(kept_points, block_size)
    groups = sbki_device.group_blocks_on_device(member_blocks)
    if groups is None:
        return None
    m = len(release_compat.TARGET_BLOCK_OFFSETS)
    source = wp.empty((groups.count, m), dtype=int, device=device)
    mult = wp.empty((groups.count, m), dtype=int, device=device)
    lookup = release.block_lookup(grid=groups.grid, lo=groups.grid_corner)
    wp.launch(release.block_models_kernel(True), dim=groups.count, device=device, inputs=[
        groups.blocks, lookup, wp.array(release_compat.TARGET_BLOCK_OFFSETS.astype(np.int32), dtype=wp.vec3i, device=device),
        wp.array(release_compat.FACE_OFFSETS.astype(np.int32), dtype=wp.vec3i, device=device),
        wp.array(release_compat.MODELS_BY_MASK, dtype=int, device=device), source, mult])
    pairs = member_blocks.shape[0]
    num_classes = probabilities.shape[1]
    sorted_points = wp.empty(pairs, dtype=wp.vec3, device=device)
    class_weights = wp.empty(pairs, dtype=release.vector_type(num_classes), device=device)
    sorted_uncertainty = wp.empty(pairs, dtype=wp.float64, device=device)
    wp.launch(release.sorted_rows_kernel(num_classes, dempster), dim=pairs, device=device, inputs=[
        on_device, wp.array(np.ascontiguousarray(probabilities, dtype=np.float64), dtype=wp.float64, device=device),
        wp.array(np.ascontiguousarray(uncertainty, dtype=np.float64), dtype=wp.float64, device=device),
        kept, point_ids, groups.order, sorted_points, class_weights, sorted_uncertainty])
    return DeviceReleaseInputs(groups.blocks.numpy().astype(np.int64), groups.blocks, source, mult, sbki_device.narrow_starts(groups),
                               sorted_points, class_weights, sorted_uncertainty, kept.shape[0])

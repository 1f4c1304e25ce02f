"""The release mode's per-scan preprocessing after its uncertainty cut (``release_compat``: the "ds" snap,
the per-block cap, the memberships, the block models) and the gather kernel's rows, built on the map's
device by parallel kernels for maps on a GPU: the same inputs bit for bit as the host path
(tests/test_release_device.py holds them together on Warp's CPU backend). The range filter and the cut
(a quantile of the scan's uncertainty) stay on the host, so that only the points they keep are sent.

No count is read back: each stage runs over room the host knows, its count on the device (``device_scratch``),
and the scan's status (the kept points' count, the pairs' total and whether they outgrew their room) comes
back with the gather's counters. The bounds of the snapped keys and of the memberships' blocks come from the
points' bounds on the host, and so does the key-range check of the blocks; the blocks themselves are read
back only for a map of several shards (their split) or where that box reaches past the key range. The
arrays are a scratch set's, kept from scan to scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import release
from ..voxel_keys import column_bounds
from . import release_compat, sbki_device
from .device_scratch import STATUS_KEPT_POINTS, DeviceScratch, Rows, inclusive_scan, last_of


def capped_points_on_device(points: wp.array, lo: np.ndarray, hi: np.ndarray, ds_resolution_m: float, block_size: np.float32,
                            cap: int, scratch: DeviceScratch | None = None) -> Rows:
    """``release_compat.snapped_block_keys`` then ``release_compat.first_per_block`` on the points' device:
    the indices (int, ascending) of the points [N] (float32 bounds lo, hi) each block keeps, their count on
    the device (also in the scan's status, ``STATUS_KEPT_POINTS``). ``scratch``: where the arrays are kept
    (None: new ones)."""
    device = points.device
    scratch = scratch or DeviceScratch(device).begin()
    n = points.shape[0]
    keys = scratch.empty((n, 3), wp.int64)
    wp.launch(release.snapped_block_keys, dim=n, device=device, inputs=[
        points, wp.vec3(*[float(v) for v in lo]), wp.vec3(*[float(v) for v in hi]), float(np.float32(ds_resolution_m)),
        float(np.float64(np.float32(block_size))), keys])
    # A snapped point stays within lo..hi (up to rounding): the keys lie within the hashes of lo and hi widened
    # by one, a box for the sort known without reading the keys' bounds back.
    key_lo, key_hi = release_compat.block_hash(np.stack([lo, hi]).astype(np.float32), block_size) + [[-1], [1]]
    order, run_rank, starts, _ = sbki_device.sort_by_block(Rows(keys, scratch.count(n)), key_lo, key_hi, scratch)
    keep = scratch.empty(n, int)
    wp.launch(release.keep_first_sorted, dim=n, device=device, inputs=[order, run_rank, starts, int(cap), keep])
    slot = inclusive_scan(keep, scratch)
    kept = scratch.empty(n, int)
    wp.launch(release.compact_indices, dim=n, device=device, inputs=[keep, slot, kept])
    return Rows(kept, scratch.bounded(last_of(slot), n, STATUS_KEPT_POINTS))


@dataclass
class DeviceReleaseInputs:
    """One scan's gather-kernel arrays on the device (``kernels.release.release_blocks``' fields), its
    blocks among them (``sbki_device.DeviceBlocks``)."""

    targets: sbki_device.DeviceBlocks
    source_blocks: wp.array
    source_mult: wp.array
    point_start: wp.array
    points: wp.array
    class_weights: wp.array
    uncertainty: wp.array


def release_inputs_on_device(points: np.ndarray, probabilities: np.ndarray, uncertainty: np.ndarray, *, ds_resolution_m: float,
                             block_size: np.float32, cap: int, dempster: bool, device: str,
                             scratch: DeviceScratch | None = None) -> DeviceReleaseInputs | None:
    """The release's inputs from the points its cut keeps (float32 [N, 3], N > 0, their probabilities [N, K]
    and uncertainty [N], float64): the capped points, their memberships, the block models and the rows
    sorted by block; None where the host path would not use a dense grid (the caller takes the host path).
    ``scratch``: where the arrays are kept (None: new ones)."""
    scratch = scratch or DeviceScratch(device).begin()
    points = np.ascontiguousarray(points, dtype=np.float32)
    n = len(points)
    on_device = scratch.upload(points, wp.vec3)
    lo, hi = column_bounds(points)
    kept = capped_points_on_device(on_device, lo, hi, ds_resolution_m, block_size, cap, scratch)
    kept_points = scratch.empty(n, wp.vec3)
    wp.launch(release.take_points, dim=n, device=device, inputs=[on_device, kept.array, kept.count, kept_points])
    point_ids, member_blocks = sbki_device.block_memberships_on_device(Rows(kept_points, kept.count), block_size, scratch)
    member_box = sbki_device.member_block_box(lo, hi, block_size)
    groups = sbki_device.group_blocks_on_device(member_blocks, scratch, member_box)
    if groups is None:
        return None
    m = len(release_compat.TARGET_BLOCK_OFFSETS)
    source = scratch.empty((groups.capacity, m), int)
    mult = scratch.empty((groups.capacity, m), int)
    lookup = release.block_lookup(grid=groups.grid, lo=groups.grid_corner)
    wp.launch(release.block_models_kernel(True), dim=groups.capacity, device=device, inputs=[
        groups.blocks, groups.count, lookup, scratch.upload(release_compat.TARGET_BLOCK_OFFSETS.astype(np.int32), wp.vec3i),
        scratch.upload(release_compat.FACE_OFFSETS.astype(np.int32), wp.vec3i),
        scratch.upload(release_compat.MODELS_BY_MASK, int), source, mult])
    pairs = member_blocks.capacity
    num_classes = probabilities.shape[1]
    sorted_points = scratch.empty(pairs, wp.vec3)
    class_weights = scratch.empty(pairs, release.vector_type(num_classes))
    sorted_uncertainty = scratch.empty(pairs, wp.float64)
    wp.launch(release.sorted_rows_kernel(num_classes, dempster), dim=pairs, device=device, inputs=[
        on_device, scratch.upload(np.ascontiguousarray(probabilities, dtype=np.float64), wp.float64),
        scratch.upload(np.ascontiguousarray(uncertainty, dtype=np.float64), wp.float64),
        kept.array, point_ids, groups.order, member_blocks.count, sorted_points, class_weights, sorted_uncertainty])
    return DeviceReleaseInputs(sbki_device.gated_targets(groups.blocks, groups.count, member_box, scratch), source, mult,
                               sbki_device.narrow_starts(groups, scratch), sorted_points, class_weights, sorted_uncertainty)

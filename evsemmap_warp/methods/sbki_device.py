"""S-BKI's per-scan training data (``sbki_compat.training_data``) built on the map's device by parallel
kernels, for maps on a GPU: the VoxelGrid of the hits and of their free samples, the range filter and
the free samples along each ray, the same points bit for bit as the host path (tests/test_sbki_device.py
holds the two together on Warp's CPU backend).

The host path runs the same steps as one-thread host kernels, one scan per worker thread, which is faster
on a CPU, where a launch runs on one core whatever its form; the forms here sort with Warp's stable radix
sort (``wp.utils.radix_sort_pairs``) and give each leaf, hit and point its own thread. Each VoxelGrid
orders its points by leaf stably and so keeps PCL's float32 summation order within a leaf.

What still reads back from the device per scan: the leaf counts of both VoxelGrids, the kept hits'
count, the longest ray and the free samples' count and bounds (small counters that size the next
arrays), and the training set itself, which the block memberships and the gather tables still build on
the host.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import block_gather, block_membership, free_space, voxel_grid
from ..voxel_keys import column_bounds
from . import sbki_compat


def _inclusive_scan(values: wp.array) -> wp.array:
    out = wp.empty_like(values)
    wp.utils.array_scan(values, out, inclusive=True)
    return out


def _last(values: wp.array) -> int:
    """The last value of a device array (one small read back)."""
    return int(values[values.shape[0] - 1:].numpy()[0])


def voxel_grid_on_device(points: wp.array, labels: wp.array | None, label_range: tuple[int, int] | None,
                         bounds: tuple[np.ndarray, np.ndarray], leaf_m: float) -> tuple[wp.array, wp.array | None]:
    """``sbki_compat.voxel_grid_downsample`` on the points' device: the centroids of the occupied leaves in
    ascending leaf order and, when ``labels`` are given (their (min, max) in ``label_range``), each leaf's
    majority label; ``bounds`` are the points' float32 per-axis (min, max). A grid PCL refuses leaves
    the points as they are."""
    n = points.shape[0]
    device = points.device
    grid = sbki_compat.leaf_grid(*bounds, leaf_m) if n else None
    if grid is None:
        return points, labels
    inverse_leaf, lowest, dims = grid
    # The radix sort takes room for 2n keys and values: the second half is its scratch.
    keys = wp.empty(2 * n, dtype=wp.int64, device=device)
    order = wp.empty(2 * n, dtype=wp.int64, device=device)
    wp.launch(voxel_grid.leaf_indices, dim=n, device=device, inputs=[
        points, float(inverse_leaf), *[int(x) for x in lowest], int(dims[0]), int(dims[1]), keys])
    wp.launch(voxel_grid.positions, dim=n, device=device, inputs=[order])
    key_bits = max(1, int(int(np.prod(dims)) - 1).bit_length())
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=key_bits)
    heads = wp.empty(n, dtype=int, device=device)
    wp.launch(voxel_grid.leaf_runs, dim=n, device=device, inputs=[keys, heads])
    leaf_rank = _inclusive_scan(heads)
    leaf_count = _last(leaf_rank)
    starts = wp.empty(leaf_count + 1, dtype=wp.int64, device=device)
    wp.launch(voxel_grid.leaf_starts, dim=n, device=device, inputs=[leaf_rank, starts])
    centroids = wp.empty(leaf_count, dtype=wp.vec3, device=device)
    wp.launch(voxel_grid.leaf_centroids_parallel, dim=leaf_count, device=device, inputs=[points, order, starts, leaf_count, centroids])
    if labels is None:
        return centroids, None
    label_min, label_max = label_range
    if label_min == label_max:  # one label (the free samples): it is every leaf's majority
        majority = wp.full(leaf_count, label_min, dtype=wp.int64, device=device)
        return centroids, majority
    span = label_max - label_min + 1
    label_keys = wp.empty(2 * n, dtype=wp.int64, device=device)
    positions = wp.empty(2 * n, dtype=wp.int64, device=device)
    wp.launch(voxel_grid.leaf_label_keys, dim=n, device=device, inputs=[order, leaf_rank, labels, label_min, span, label_keys, positions])
    wp.utils.radix_sort_pairs(label_keys, positions, n, end_bit=max(1, int(leaf_count * span - 1).bit_length()))
    majority = wp.empty(leaf_count, dtype=wp.int64, device=device)
    wp.launch(voxel_grid.leaf_majority_labels, dim=leaf_count, device=device, inputs=[label_keys, starts, leaf_count, label_min, span, majority])
    return centroids, majority


def _free_space_samples(hits: wp.array, direction: wp.array, ray_length: wp.array, origin: np.ndarray, f: np.float32) -> wp.array:
    """``sbki_compat.free_space_samples`` of hits whose rays are computed (``kernels.free_space.ray_geometry``)."""
    device = hits.device
    n = hits.shape[0]
    if n == 0:
        return wp.empty(0, dtype=wp.vec3, device=device)
    longest = wp.zeros(1, dtype=wp.float32, device=device)
    wp.launch(free_space.longest_ray, dim=n, device=device, inputs=[ray_length, longest])
    longest = np.float32(longest.numpy()[0])
    sbki_compat.check_free_samples(0.0, float(longest), f, origin)  # the steps' bound, before they are listed
    steps = wp.array(sbki_compat.ray_steps(f, longest), dtype=wp.float32, device=device)
    per_hit = wp.empty(n, dtype=int, device=device)
    rows_per_hit = wp.empty(n, dtype=int, device=device)
    wp.launch(free_space.samples_per_ray, dim=n, device=device, inputs=[ray_length, steps, float(f), per_hit, rows_per_hit])
    first_row = wp.empty(n, dtype=int, device=device)
    wp.utils.array_scan(rows_per_hit, first_row, inclusive=False)
    rows = _last(first_row) + _last(rows_per_hit)
    sbki_compat.check_free_samples(float(rows), float(longest), f, origin)
    out = wp.empty(rows, dtype=wp.vec3, device=device)
    wp.launch(free_space.ray_samples, dim=n, device=device, inputs=[
        direction, ray_length, wp.vec3(*origin.tolist()), float(f), steps, per_hit, first_row, out])
    return out


def training_data_on_device(
    points: np.ndarray,
    labels: np.ndarray,
    sensor_origin: np.ndarray,
    *,
    ds_resolution_m: float,
    free_resolution_m: float,
    max_range_m: float | None,
    device: str,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """``sbki_compat.training_data`` built on ``device``: the same points, labels and counts (read back)."""
    hits, hit_labels, free_points = training_arrays(points, labels, sensor_origin, ds_resolution_m=ds_resolution_m,
                                                    free_resolution_m=free_resolution_m, max_range_m=max_range_m, device=device)
    hits, hit_labels, free_points = hits.numpy(), hit_labels.numpy(), free_points.numpy()
    train_points = np.concatenate([hits, free_points]).astype(np.float32)
    train_labels = np.concatenate([hit_labels, np.full(len(free_points), sbki_compat.FREE_LABEL, np.int64)])
    return train_points, train_labels, {"hits": len(hits), "free_samples": len(free_points)}


def training_arrays(
    points: np.ndarray,
    labels: np.ndarray,
    sensor_origin: np.ndarray,
    *,
    ds_resolution_m: float,
    free_resolution_m: float,
    max_range_m: float | None,
    device: str,
) -> tuple[wp.array, wp.array, wp.array]:
    """The training set of ``sbki_compat.training_data`` on ``device``, in its two parts: the downsampled
    hits within range [H] (vec3), their labels [H] (int64) and the downsampled free samples [F] (vec3,
    label ``FREE_LABEL``)."""
    points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    labels = np.asarray(labels, dtype=np.int64)
    origin = np.asarray(sensor_origin, dtype=np.float32).reshape(3)
    if len(points) == 0:
        empty = wp.empty(0, dtype=wp.vec3, device=device)
        return empty, wp.empty(0, dtype=wp.int64, device=device), empty
    hits, hit_labels = voxel_grid_on_device(
        wp.array(points, dtype=wp.vec3, device=device), wp.array(labels, dtype=wp.int64, device=device),
        (int(labels.min()), int(labels.max())), column_bounds(points), ds_resolution_m)
    n = hits.shape[0]
    direction = wp.empty(n, dtype=wp.vec3, device=device)
    ray_length = wp.empty(n, dtype=wp.float32, device=device)
    wp.launch(free_space.ray_geometry, dim=n, device=device, inputs=[hits, wp.vec3(*origin.tolist()), direction, ray_length])
    if max_range_m is not None:
        keep = wp.empty(n, dtype=int, device=device)
        wp.launch(free_space.within_range, dim=n, device=device, inputs=[ray_length, float(np.float32(max_range_m)), keep])
        slot = _inclusive_scan(keep)
        kept = _last(slot)
        arrays = [wp.empty(kept, dtype=a.dtype, device=device) for a in (hits, hit_labels, direction, ray_length)]
        wp.launch(free_space.compact_rays, dim=n, device=device, inputs=[keep, slot, hits, hit_labels, direction, ray_length, *arrays])
        hits, hit_labels, direction, ray_length = arrays
    frees = _free_space_samples(hits, direction, ray_length, origin, np.float32(free_resolution_m))
    free_points = frees
    if frees.shape[0]:
        lowest = wp.full(3, np.inf, dtype=wp.float32, device=device)
        highest = wp.full(3, -np.inf, dtype=wp.float32, device=device)
        wp.launch(voxel_grid.point_bounds, dim=frees.shape[0], device=device, inputs=[frees, lowest, highest])
        free_points, _ = voxel_grid_on_device(frees, None, None, (lowest.numpy(), highest.numpy()), ds_resolution_m)
    return hits, hit_labels, free_points


def training_set(hits: wp.array, hit_labels: wp.array, free_points: wp.array) -> tuple[wp.array, wp.array]:
    """The training points [H + F] and labels of ``training_arrays``' parts, hits first, on their device."""
    device = hits.device
    h, f = hits.shape[0], free_points.shape[0]
    points = wp.empty(h + f, dtype=wp.vec3, device=device)
    labels = wp.full(h + f, sbki_compat.FREE_LABEL, dtype=wp.int64, device=device)
    if h:
        wp.copy(points, hits, count=h)
        wp.copy(labels, hit_labels, count=h)
    if f:
        wp.copy(points, free_points, dest_offset=h, count=f)
    return points, labels


def block_memberships_on_device(points: wp.array, block_size: np.float32) -> tuple[wp.array, wp.array]:
    """``sbki_compat.block_memberships`` on the points' device: point ids [M] (int64) and blocks [M, 3]
    (int64), shift by shift, points ascending within a shift."""
    device = points.device
    n = points.shape[0]
    nearest = wp.empty((n, 3), dtype=wp.int64, device=device)
    masks = wp.empty(n, dtype=int, device=device)
    pair_counts = wp.empty(n, dtype=int, device=device)
    wp.launch(block_membership.membership_masks_parallel, dim=n, device=device, inputs=[
        points, float(np.float32(block_size)), nearest, masks, pair_counts])
    first_pair = wp.empty(n, dtype=int, device=device)
    wp.utils.array_scan(pair_counts, first_pair, inclusive=False)
    pairs = _last(first_pair) + _last(pair_counts) if n else 0
    bits = wp.empty(2 * pairs, dtype=wp.int64, device=device)
    point_ids = wp.empty(2 * pairs, dtype=wp.int64, device=device)
    wp.launch(block_membership.membership_pairs_by_point, dim=n, device=device, inputs=[masks, first_pair, bits, point_ids])
    wp.utils.radix_sort_pairs(bits, point_ids, pairs, end_bit=5)
    blocks = wp.empty((pairs, 3), dtype=wp.int64, device=device)
    wp.launch(block_membership.membership_blocks, dim=pairs, device=device, inputs=[bits, point_ids, nearest, blocks])
    return (point_ids[:pairs] if pairs else wp.empty(0, dtype=wp.int64, device=device)), blocks


@dataclass
class DeviceGatherTables:
    """One scan's inputs of the S-BKI gather kernel on the device (``block_gather.sbki_blocks``'s arrays) and
    its test blocks on the host ([T, 3] int64, for the key-range check and the shards' split)."""

    test_blocks: np.ndarray
    tests: wp.array
    sources: wp.array
    point_start: wp.array
    scaled_points: wp.array
    labels: wp.array


def gather_tables_on_device(points: wp.array, labels: wp.array, block_size: np.float32, length_m: float) -> DeviceGatherTables | None:
    """``sbki_compat.block_memberships`` and ``sbki_compat.gather_tables`` of a training set on its device,
    and the points and labels sorted as the gather kernel reads them; None where the host path would not
    use a dense grid (blocks spread wider than ``sbki_compat.MAX_DENSE_LOOKUP_CELLS``): the caller takes
    the host path then."""
    device = points.device
    point_ids, member_blocks = block_memberships_on_device(points, block_size)
    pairs = member_blocks.shape[0]
    if pairs == 0:
        return None
    lowest = wp.full(3, np.iinfo(np.int64).max, dtype=wp.int64, device=device)
    highest = wp.full(3, np.iinfo(np.int64).min, dtype=wp.int64, device=device)
    wp.launch(block_gather.block_bounds, dim=pairs, device=device, inputs=[member_blocks, lowest, highest])
    lo, hi = lowest.numpy(), highest.numpy()
    grid_lo = lo - 3
    shape = hi + 4 - grid_lo
    if int(np.prod(shape.astype(np.float64))) > sbki_compat.MAX_DENSE_LOOKUP_CELLS:
        return None
    span = hi - lo + 1
    positions = wp.empty(2 * pairs, dtype=wp.int64, device=device)
    order = wp.empty(2 * pairs, dtype=wp.int64, device=device)
    wp.launch(block_gather.box_positions, dim=pairs, device=device, inputs=[
        member_blocks, wp.vec3l(*[int(x) for x in lo]), int(span[1]), int(span[2]), positions, order])
    wp.utils.radix_sort_pairs(positions, order, pairs, end_bit=max(1, int(int(np.prod(span)) - 1).bit_length()))
    heads = wp.empty(pairs, dtype=int, device=device)
    wp.launch(voxel_grid.leaf_runs, dim=pairs, device=device, inputs=[positions, heads])
    block_rank = _inclusive_scan(heads)
    block_count = _last(block_rank)
    starts = wp.empty(block_count + 1, dtype=wp.int64, device=device)
    wp.launch(voxel_grid.leaf_starts, dim=pairs, device=device, inputs=[block_rank, starts])
    grid = wp.full(tuple(int(x) for x in shape), -1, dtype=int, device=device)
    grid_blocks = wp.empty(block_count, dtype=wp.vec3i, device=device)
    grid_corner = wp.vec3l(*[int(x) for x in grid_lo])
    wp.launch(block_gather.distinct_blocks, dim=block_count, device=device, inputs=[member_blocks, order, starts, grid_corner, grid_blocks, grid])
    offsets = wp.array(sbki_compat.EXTENDED_BLOCK_OFFSETS.astype(np.int32), dtype=wp.vec3i, device=device)
    marked = wp.zeros(grid.size, dtype=int, device=device)
    wp.launch(block_gather.mark_test_blocks, dim=(block_count, offsets.shape[0]), device=device, inputs=[grid_blocks, offsets, grid, marked])
    slot = _inclusive_scan(marked)
    test_count = _last(slot)
    tests = wp.empty(test_count, dtype=wp.vec3i, device=device)
    sources = wp.empty((test_count, offsets.shape[0]), dtype=int, device=device)
    wp.launch(block_gather.list_test_blocks, dim=grid.size, device=device, inputs=[marked, slot, grid, offsets, grid_corner, tests, sources])
    point_start = wp.empty(block_count + 1, dtype=int, device=device)
    wp.launch(block_gather.narrow_starts, dim=block_count + 1, device=device, inputs=[starts, point_start])
    scaled_points = wp.empty(pairs, dtype=wp.vec3, device=device)
    sorted_labels = wp.empty(pairs, dtype=int, device=device)
    wp.launch(block_gather.sorted_block_points, dim=pairs, device=device, inputs=[
        points, labels, point_ids, order, float(np.float32(length_m)), scaled_points, sorted_labels])
    return DeviceGatherTables(tests.numpy().astype(np.int64), tests, sources, point_start, scaled_points, sorted_labels)


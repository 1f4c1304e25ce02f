"""S-BKI's per-scan preprocessing (``sbki_compat``) built on the map's device by parallel kernels, for maps
on a GPU: the training data (the VoxelGrid of the hits and of their free samples, the range filter, the
free samples along each ray), the block memberships and the gather kernel's tables, the same arrays bit
for bit as the host path (tests/test_sbki_device.py holds the two together on Warp's CPU backend).

The host path runs the same steps as one-thread host kernels, one scan per worker thread, which is faster
on a CPU, where a launch runs on one core whatever its form; the forms here sort with Warp's stable radix
sort (``wp.utils.radix_sort_pairs``) and give each leaf, hit and point its own thread. Each VoxelGrid
orders its points by leaf stably and so keeps PCL's float32 summation order within a leaf.

No count is read back: each stage's arrays have room the host knows, the count they hold stays on the
device, and every kernel runs over the room (``device_scratch``). The hits and their leaves have room for
the scan's points, the free samples and the (point, block) pairs room reserved from what earlier scans
needed (their bounds, every step of the longest ray per hit and 27 blocks per point, lie far above what
scans count), the blocks room for the pairs, the test blocks for 7 per block. The scan's status (the
reserved stages' totals, whether one ran out of room, the training set's count) is read back with the
gather's counters. The bounds it needs (of the longest ray, of the free samples' leaf grid, of the
memberships' and the test blocks, for their grid and the key-range check) come from a box the host knows,
the scan's points and sensor origin (``training_box``); they are read only where that box's leaf grid,
steps or block grid would be refused (or it reaches past the key range) and their own would not. The test
blocks are read back for a map of several shards, for their split (``DeviceBlocks``). Blocks spread wider
than a dense grid (``sbki_compat.MAX_DENSE_LOOKUP_CELLS``) take the host path from the training set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import block_gather, block_membership, device_counts, free_space, voxel_grid
from ..voxel_keys import column_bounds
from . import sbki_compat
from .device_scratch import STATUS_FREE_ROWS, STATUS_KEPT_POINTS, STATUS_PAIRS, DeviceScratch, Rows, counts_with_room, inclusive_scan, last_of

# The rows reserved per hit for its free samples, and per point for its (point, block) pairs, unless scans
# ran out of room (their bounds, every step of the longest ray per hit and 27 blocks per point, lie far
# above what scans count; most points lie in one block).
FREE_ROWS_GUESS_PER_HIT = 16
PAIRS_GUESS_PER_POINT = 1.25


def runs_of_sorted(keys: wp.array, capacity: int, count: wp.array, scratch: DeviceScratch) -> tuple[wp.array, wp.array, wp.array]:
    """The runs of equal values among the first count[0] (on the device) of ``capacity`` sorted ``keys``:
    each key's run number from 1 (an inclusive scan of the run heads, 0 past the count), the runs' starts
    [capacity + 1] (int64; the first R + 1 set) and the run count R (a [1] view on the device)."""
    device = keys.device
    heads = scratch.empty(capacity, int)
    wp.launch(voxel_grid.leaf_runs, dim=capacity, device=device, inputs=[keys, count, heads])
    run_rank = inclusive_scan(heads, scratch)
    starts = scratch.empty(capacity + 1, wp.int64)
    wp.launch(voxel_grid.leaf_starts, dim=capacity, device=device, inputs=[run_rank, count, starts])
    return run_rank, starts, last_of(run_rank)


def float_bounds_on_device(points: Rows, scratch: DeviceScratch) -> tuple[np.ndarray, np.ndarray]:
    """The per-axis float32 (min, max) of the counted points (vec3; +inf, -inf for none), read back once."""
    bounds = scratch.empty((2, 3), wp.float32)
    bounds[0].fill_(np.inf)
    bounds[1].fill_(-np.inf)
    wp.launch(voxel_grid.point_bounds, dim=points.capacity, device=points.array.device, inputs=[points.array, points.count, bounds[0], bounds[1]])
    lowest, highest = bounds.numpy()
    return lowest, highest


def voxel_grid_on_device(points: Rows, labels: wp.array | None, label_range: tuple[int, int] | None,
                         bounds: tuple[np.ndarray, np.ndarray], leaf_m: float, scratch: DeviceScratch | None = None) -> tuple[Rows, wp.array | None]:
    """``sbki_compat.voxel_grid_downsample`` on the points' device: the centroids of the occupied leaves in
    ascending leaf order (as many rows as the points have room for, their count on the device) and, when
    ``labels`` are given (their (min, max) in ``label_range``), each leaf's majority label; ``bounds`` are
    float32 per-axis (min, max) of a box holding the points. A grid PCL refuses leaves the points as they
    are. ``scratch``: where the arrays are kept (None: new ones)."""
    n = points.capacity
    device = points.array.device
    scratch = scratch or DeviceScratch(device).begin()
    grid = sbki_compat.leaf_grid(*bounds, leaf_m) if n and np.all(np.isfinite(bounds)) else None
    if grid is None:
        return points, labels
    inverse_leaf, lowest, dims = grid
    # The radix sort takes room for 2n keys and values: the second half is its scratch.
    keys = scratch.empty(2 * n, wp.int64)
    order = scratch.empty(2 * n, wp.int64)
    wp.launch(voxel_grid.leaf_indices, dim=n, device=device, inputs=[
        points.array, points.count, float(inverse_leaf), *[int(x) for x in lowest], int(dims[0]), int(dims[1]), keys])
    wp.launch(voxel_grid.positions, dim=n, device=device, inputs=[order])
    key_bits = max(1, int(sbki_compat.box_cells(dims) - 1).bit_length())
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=key_bits)
    leaf_rank, starts, leaf_count = runs_of_sorted(keys, n, points.count, scratch)
    centroids = scratch.empty(n, wp.vec3)
    wp.launch(voxel_grid.leaf_centroids_parallel, dim=n, device=device, inputs=[points.array, order, starts, leaf_count, centroids])
    if labels is None:
        return Rows(centroids, leaf_count), None
    label_min, label_max = label_range
    if label_min == label_max:  # one label: it is every leaf's majority
        return Rows(centroids, leaf_count), scratch.full(n, label_min, wp.int64)
    span = label_max - label_min + 1
    label_keys = scratch.empty(2 * n, wp.int64)
    positions = scratch.empty(2 * n, wp.int64)
    wp.launch(voxel_grid.leaf_label_keys, dim=n, device=device, inputs=[order, leaf_rank, labels, points.count, label_min, span, label_keys, positions])
    wp.utils.radix_sort_pairs(label_keys, positions, n, end_bit=max(1, int(n * span - 1).bit_length()))
    majority = scratch.empty(n, wp.int64)
    wp.launch(voxel_grid.leaf_majority_labels, dim=n, device=device, inputs=[label_keys, starts, leaf_count, label_min, span, majority])
    return Rows(centroids, leaf_count), majority


def training_box(points: np.ndarray, sensor_origin: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """float32 (lowest, highest) per axis of a scan's points [N, 3] (N > 0) and its sensor origin, widened
    by ``margin_m``: a box holding its training points (the hits' centroids, and the free samples on the
    rays between the origin and them, and their centroids), known on the host before they are computed."""
    lo, hi = column_bounds(np.asarray(points, np.float32).reshape(-1, 3))
    origin = np.asarray(sensor_origin, np.float32).reshape(3)
    margin = np.float32(margin_m)
    return np.minimum(lo, origin) - margin, np.maximum(hi, origin) + margin


def _longest_ray(ray_length: wp.array, hit_count: wp.array, scratch: DeviceScratch) -> np.float32:
    """The longest of the counted rays, read back."""
    longest = scratch.zeros(1, wp.float32)
    wp.launch(free_space.longest_ray, dim=ray_length.shape[0], device=ray_length.device, inputs=[ray_length, hit_count, longest])
    return np.float32(longest.numpy()[0])


def _free_space_samples(hits: Rows, direction: wp.array, ray_length: wp.array, origin: np.ndarray, f: np.float32,
                        box: tuple[np.ndarray, np.ndarray], scratch: DeviceScratch) -> Rows:
    """``sbki_compat.free_space_samples`` of hits whose rays are computed (``kernels.free_space.ray_geometry``),
    within ``box`` (``training_box``): the steps go as far as its farthest corner from the origin, a bound
    of the longest ray known without reading it back (extra steps lie beyond every ray and are never
    taken); only where that bound would be refused is the longest ray itself read. The rows are the room
    reserved for them (``DeviceScratch.room``); their total goes to the scan's status, and a scan with
    more than ``sbki_compat.MAX_FREE_SAMPLES_PER_SCAN`` is refused on its redo, as the host path refuses it."""
    device = hits.array.device
    n = hits.capacity
    corners = np.stack(np.meshgrid(*zip(*box), indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float64)
    longest = np.float32(np.linalg.norm(corners - origin.astype(np.float64), axis=1).max() + float(f))  # + f: past any rounding
    try:
        sbki_compat.check_free_samples(0.0, float(longest), f, origin)  # the steps' bound, before they are listed
    except ValueError:
        longest = _longest_ray(ray_length, hits.count, scratch)
        sbki_compat.check_free_samples(0.0, float(longest), f, origin)
    redo = scratch.redo_status
    if redo is not None and int(redo[STATUS_FREE_ROWS]) > sbki_compat.MAX_FREE_SAMPLES_PER_SCAN:  # refused: the message names the longest ray
        sbki_compat.check_free_samples(float(redo[STATUS_FREE_ROWS]), float(_longest_ray(ray_length, hits.count, scratch)), f, origin)
    steps = scratch.upload(sbki_compat.ray_steps(f, longest), wp.float32)
    per_hit = scratch.empty(n, int)
    rows_per_hit = scratch.empty(n, int)
    total = scratch.zeros(1, wp.int64)  # the int prefix sum below wraps past 2^31 rows (far rays): the total is summed in int64 too
    wp.launch(free_space.samples_per_ray, dim=n, device=device, inputs=[ray_length, hits.count, steps, float(f), per_hit, rows_per_hit, total])
    first_row = scratch.empty(n, int)
    wp.utils.array_scan(rows_per_hit, first_row, inclusive=False)
    bound = min(n * (steps.shape[0] + 2), sbki_compat.MAX_FREE_SAMPLES_PER_SCAN)
    room = scratch.room(STATUS_FREE_ROWS, FREE_ROWS_GUESS_PER_HIT * n, bound)
    out = scratch.empty(room, wp.vec3)
    count = scratch.bounded(total, room, STATUS_FREE_ROWS)
    wp.launch(free_space.ray_samples, dim=n, device=device, inputs=[
        direction, ray_length, hits.count, wp.vec3(*origin.tolist()), float(f), steps, per_hit, first_row, out])
    return Rows(out, count)


def training_arrays(
    points: np.ndarray,
    labels: np.ndarray,
    sensor_origin: np.ndarray,
    *,
    ds_resolution_m: float,
    free_resolution_m: float,
    max_range_m: float | None,
    device: str,
    scratch: DeviceScratch | None = None,
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[Rows, wp.array, Rows]:
    """The training set of ``sbki_compat.training_data`` on ``device``, in its two parts: the downsampled
    hits within range (vec3), their labels (int64) and the downsampled free samples (vec3, label
    ``FREE_LABEL``), their counts on the device; ``sbki_compat.joined_training_set`` of their values is
    ``training_data``'s result. The points are at least one. ``scratch``: where the arrays are kept (None:
    new ones); ``box``: the scan's ``training_box`` with ds_resolution_m as its margin, when the caller has
    it already (None: computed here)."""
    scratch = scratch or DeviceScratch(device).begin()
    points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    labels = np.asarray(labels, dtype=np.int64)
    origin = np.asarray(sensor_origin, dtype=np.float32).reshape(3)
    if len(points) == 0:
        raise ValueError("training_arrays needs at least one point")
    if box is None:
        box = training_box(points, origin, ds_resolution_m)
    hits, hit_labels = voxel_grid_on_device(
        Rows(scratch.upload(points, wp.vec3), scratch.count(len(points))), scratch.upload(labels, wp.int64),
        (int(labels.min()), int(labels.max())), column_bounds(points), ds_resolution_m, scratch)
    n = hits.capacity
    direction = scratch.empty(n, wp.vec3)
    ray_length = scratch.empty(n, wp.float32)
    wp.launch(free_space.ray_geometry, dim=n, device=device, inputs=[hits.array, hits.count, wp.vec3(*origin.tolist()), direction, ray_length])
    if max_range_m is not None:
        keep = scratch.empty(n, int)
        wp.launch(free_space.within_range, dim=n, device=device, inputs=[ray_length, hits.count, float(np.float32(max_range_m)), keep])
        slot = inclusive_scan(keep, scratch)
        arrays = [scratch.empty(n, a.dtype) for a in (hits.array, hit_labels, direction, ray_length)]
        wp.launch(free_space.compact_rays, dim=n, device=device, inputs=[keep, slot, hits.array, hit_labels, direction, ray_length, *arrays])
        kept_hits, hit_labels, direction, ray_length = arrays
        hits = Rows(kept_hits, last_of(slot))
    frees = _free_space_samples(hits, direction, ray_length, origin, np.float32(free_resolution_m), box, scratch)
    # The box holds the free samples: their leaves, and the leaves' order (by z, y, x), are those of a grid
    # over their own bounds, unless PCL would refuse the box's grid but not theirs (then they are read).
    if sbki_compat.leaf_grid(*box, ds_resolution_m, warn=False) is None:
        box = float_bounds_on_device(frees, scratch)
    free_points, _ = voxel_grid_on_device(frees, None, None, box, ds_resolution_m, scratch)
    return hits, hit_labels, free_points


def training_set(hits: Rows, hit_labels: wp.array, free_points: Rows, scratch: DeviceScratch) -> tuple[Rows, wp.array]:
    """The training points and labels of ``training_arrays``' parts, hits first, on their device; their
    count also goes to the scan's status (``STATUS_KEPT_POINTS``)."""
    capacity = hits.capacity + free_points.capacity
    device = hits.array.device
    points = scratch.empty(capacity, wp.vec3)
    labels = scratch.empty(capacity, wp.int64)
    total = scratch.empty(1, int)
    wp.launch(free_space.join_training_set, dim=capacity, device=device, inputs=[
        hits.array, hit_labels, hits.count, free_points.array, free_points.count, sbki_compat.FREE_LABEL, points, labels, total])
    return Rows(points, scratch.bounded(total, capacity, STATUS_KEPT_POINTS)), labels


def block_memberships_on_device(points: Rows, block_size: np.float32, scratch: DeviceScratch | None = None) -> tuple[wp.array, Rows]:
    """``sbki_compat.block_memberships`` on the points' device: point ids (int64) and blocks [P, 3] (int64)
    of the (point, block) pairs, shift by shift, points ascending within a shift; P, their count, on the
    device, within the room reserved for them (``DeviceScratch.room``; their total goes to the scan's
    status). ``scratch``: where the arrays are kept (None: new ones)."""
    device = points.array.device
    scratch = scratch or DeviceScratch(device).begin()
    n = points.capacity
    nearest = scratch.empty((n, 3), wp.int64)
    masks = scratch.empty(n, int)
    pair_counts = counts_with_room(n, scratch)
    wp.launch(block_membership.membership_masks_parallel, dim=n, device=device, inputs=[
        points.array, points.count, float(np.float32(block_size)), nearest, masks, pair_counts])
    first_pair = scratch.empty(n + 1, int)
    wp.utils.array_scan(pair_counts, first_pair, inclusive=False)
    room = scratch.room(STATUS_PAIRS, int(PAIRS_GUESS_PER_POINT * n) + 16, 27 * n)
    count = scratch.bounded(last_of(first_pair), room, STATUS_PAIRS)
    bits = scratch.empty(2 * room, wp.int64)
    bits[:room].fill_(int(device_counts.PAST_COUNT_KEY))  # the rows past the count sort last
    point_ids = scratch.empty(2 * room, wp.int64)
    wp.launch(block_membership.membership_pairs_by_point, dim=n, device=device, inputs=[masks, points.count, first_pair, room, bits, point_ids])
    wp.utils.radix_sort_pairs(bits, point_ids, room, end_bit=5)
    blocks = scratch.empty((room, 3), wp.int64)
    wp.launch(block_membership.membership_blocks, dim=room, device=device, inputs=[bits, point_ids, count, nearest, blocks])
    return point_ids[:room], Rows(blocks, count)


@dataclass
class BlockGroups:
    """(point, block) pairs grouped by block on their device, as ``sbki_compat.group_by_block`` and
    ``sbki_compat.dense_block_grid`` group them on the host: the pair order (stable, by the blocks' packed
    keys; its first P entries), block b's pairs at order[starts[b]:starts[b + 1]], the ``count`` of
    distinct blocks (a [1] int array on the device) in ``blocks`` (vec3i, room for ``capacity``), and the
    dense grid of their indices (-1 elsewhere) over their bounding box widened by 3 from ``grid_corner``
    (block b at ``grid_blocks[b]`` in it)."""

    order: wp.array
    starts: wp.array
    count: wp.array
    capacity: int
    blocks: wp.array
    grid: wp.array
    grid_blocks: wp.array
    grid_corner: np.ndarray


def block_bounds_on_device(blocks: Rows, scratch: DeviceScratch) -> tuple[np.ndarray, np.ndarray]:
    """The per-axis (min, max) of the counted blocks [P, 3] (int64; the int64 extremes, max then min, for
    none), read back once."""
    bounds = scratch.empty((2, 3), wp.int64)
    bounds[0].fill_(np.iinfo(np.int64).max)
    bounds[1].fill_(np.iinfo(np.int64).min)
    wp.launch(block_gather.block_bounds, dim=blocks.capacity, device=blocks.array.device, inputs=[blocks.array, blocks.count, bounds[0], bounds[1]])
    lowest, highest = bounds.numpy()
    return lowest, highest


def sort_by_block(blocks: Rows, lo: np.ndarray, hi: np.ndarray, scratch: DeviceScratch) -> tuple[wp.array, wp.array, wp.array, wp.array]:
    """The counted rows of blocks [P, 3] (int64, within lo..hi) stably sorted by the blocks' packed-key
    order: the order (its first P entries), each sorted row's run number from 1 (an inclusive scan of run
    heads), the runs' starts and the run count R on the device (``runs_of_sorted``)."""
    device = blocks.array.device
    rows = blocks.capacity
    span = hi - lo + 1
    positions = scratch.empty(2 * rows, wp.int64)
    order = scratch.empty(2 * rows, wp.int64)
    wp.launch(block_gather.box_positions, dim=rows, device=device, inputs=[
        blocks.array, blocks.count, wp.vec3l(*[int(x) for x in lo]), int(span[1]), int(span[2]), positions, order])
    wp.utils.radix_sort_pairs(positions, order, rows, end_bit=max(1, int(sbki_compat.box_cells(span) - 1).bit_length()))
    run_rank, starts, runs = runs_of_sorted(positions, rows, blocks.count, scratch)
    return order, run_rank, starts, runs


def member_block_box(points_lo: np.ndarray, points_hi: np.ndarray, block_size: np.float32) -> tuple[np.ndarray, np.ndarray]:
    """A box (lowest, highest block per axis) holding every block a point within points_lo..points_hi
    (float, m) belongs to: its nearest block and the face neighbours its box tests reach, widened by one
    block for the rounding of points computed on the device (centroids, free samples) near the bounds."""
    size = float(np.float32(block_size))
    return (np.floor(np.asarray(points_lo, np.float64) / size).astype(np.int64) - 2,
            np.floor(np.asarray(points_hi, np.float64) / size).astype(np.int64) + 2)


def group_blocks_on_device(member_blocks: Rows, scratch: DeviceScratch, box: tuple[np.ndarray, np.ndarray] | None = None) -> BlockGroups | None:
    """``BlockGroups`` of pairs' blocks [P, 3] (int64) on their device; None where their dense grid would
    exceed ``sbki_compat.MAX_DENSE_LOOKUP_CELLS``, or no box holds them (no pairs): the caller takes the host
    path then. ``box``: (lowest, highest) blocks known to hold them all (``member_block_box``), the grid's box
    without reading their bounds back (they are read where its grid would be too large); the groups are
    the same for any box that holds them."""
    device = member_blocks.array.device

    def grid_shape(lo, hi):  # the grid is the box widened by 3 on every side
        return hi + 7 - lo

    if box is None or sbki_compat.box_cells(grid_shape(*box)) > sbki_compat.MAX_DENSE_LOOKUP_CELLS:  # none, or too wide: read theirs
        box = block_bounds_on_device(member_blocks, scratch)
        if np.any(box[0] > box[1]):
            return None
    lo, hi = box
    shape = grid_shape(lo, hi)
    if sbki_compat.box_cells(shape) > sbki_compat.MAX_DENSE_LOOKUP_CELLS:
        return None
    grid_corner = lo - 3
    order, _, starts, count = sort_by_block(member_blocks, lo, hi, scratch)
    capacity = member_blocks.capacity
    grid = scratch.full(tuple(int(x) for x in shape), -1, int)
    blocks = scratch.empty(capacity, wp.vec3i)
    grid_blocks = scratch.empty(capacity, wp.vec3i)
    wp.launch(block_gather.distinct_blocks, dim=capacity, device=device, inputs=[
        member_blocks.array, order, starts, count, wp.vec3l(*[int(x) for x in grid_corner]), blocks, grid_blocks, grid])
    return BlockGroups(order, starts, count, capacity, blocks, grid, grid_blocks, grid_corner)


def narrow_starts(groups: BlockGroups, scratch: DeviceScratch) -> wp.array:
    """The groups' starts as the gather kernels' int point starts [capacity + 1] (the first count + 1 set)."""
    point_start = scratch.empty(groups.capacity + 1, int)
    wp.launch(block_gather.narrow_starts, dim=groups.capacity + 1, device=groups.starts.device, inputs=[groups.starts, groups.count, point_start])
    return point_start


@dataclass
class DeviceBlocks:
    """A block gather's target blocks on the device: ``blocks`` (vec3i, room for ``capacity``), their
    ``count`` (a [1] int array on the device; 0 where the scan ran out of room), ``box``, (lowest, highest)
    blocks per axis known on the host to hold them all (None: not known), and the scan's ``status``
    (``device_scratch``), which the gather reads back with its counters. ``host()`` reads the blocks back,
    once, for what the box cannot settle (a box reaching past the key range, the shards' split)."""

    blocks: wp.array
    count: wp.array
    box: tuple[np.ndarray, np.ndarray] | None
    status: wp.array

    @property
    def capacity(self) -> int:
        """The blocks there is room for."""
        return self.blocks.shape[0]

    def host(self) -> np.ndarray:
        """The blocks [B, 3] (int64), read back on the first call."""
        if not hasattr(self, "_host"):
            self._host = Rows(self.blocks, self.count).numpy().reshape(-1, 3).astype(np.int64)
        return self._host


def gated_targets(blocks: wp.array, total: wp.array, box, scratch: DeviceScratch) -> DeviceBlocks:
    """``DeviceBlocks`` of the ``total`` blocks (a [1] view on the device), or of none where the scan ran
    out of room, so that such a scan changes no voxel."""
    count = scratch.empty(1, int)
    wp.launch(device_counts.gated_count, dim=1, device=blocks.device, inputs=[total, scratch.status, count])
    return DeviceBlocks(blocks, count, box, scratch.status)


@dataclass
class DeviceGatherTables:
    """One scan's inputs of the S-BKI gather kernel on the device (``block_gather.sbki_blocks``'s arrays):
    its test blocks (``DeviceBlocks``), their sources, the points' starts, the sorted points and labels, and
    for ``near_face_masks`` the points' count and the blocks holding them (``pair_count``, ``blocks`` and
    ``block_count``, the counts [1] arrays on the device)."""

    targets: DeviceBlocks
    sources: wp.array
    point_start: wp.array
    scaled_points: wp.array
    labels: wp.array
    pair_count: wp.array
    blocks: wp.array
    block_count: wp.array

    @property
    def tests(self) -> wp.array:
        """The test blocks (vec3i, room for the targets' capacity) on the device."""
        return self.targets.blocks

    @property
    def test_blocks(self) -> np.ndarray:
        """The test blocks [T, 3] (int64), read back."""
        return self.targets.host()


def gather_tables_on_device(points: Rows, labels: wp.array, block_size: np.float32, length_m: float,
                            scratch: DeviceScratch | None = None, box: tuple[np.ndarray, np.ndarray] | None = None) -> DeviceGatherTables | None:
    """``sbki_compat.block_memberships`` and ``sbki_compat.gather_tables`` of a training set on its device,
    and the points and labels sorted as the gather kernel reads them; None where the blocks are too spread
    for its dense grid (``group_blocks_on_device``). ``scratch``: where the arrays are kept (None: new ones);
    ``box``: a float box holding the points (``training_box``), which spares reading their blocks' bounds."""
    device = points.array.device
    scratch = scratch or DeviceScratch(device).begin()
    point_ids, member_blocks = block_memberships_on_device(points, block_size, scratch)
    member_box = None if box is None else member_block_box(*box, block_size)
    groups = group_blocks_on_device(member_blocks, scratch, member_box)
    if groups is None:
        return None
    offsets = scratch.upload(sbki_compat.EXTENDED_BLOCK_OFFSETS.astype(np.int32), wp.vec3i)
    marked = scratch.zeros(groups.grid.size, int)
    wp.launch(block_gather.mark_test_blocks, dim=(groups.capacity, offsets.shape[0]), device=device, inputs=[
        groups.grid_blocks, groups.count, offsets, groups.grid, marked])
    slot = inclusive_scan(marked, scratch)
    test_capacity = min(groups.grid.size, offsets.shape[0] * groups.capacity)
    tests = scratch.empty(test_capacity, wp.vec3i)
    sources = scratch.empty((test_capacity, offsets.shape[0]), int)
    wp.launch(block_gather.list_test_blocks, dim=groups.grid.size, device=device, inputs=[
        marked, slot, groups.grid, offsets, wp.vec3l(*[int(x) for x in groups.grid_corner]), tests, sources])
    pairs = member_blocks.capacity
    scaled_points = scratch.empty(pairs, wp.vec3)
    sorted_labels = scratch.empty(pairs, int)
    wp.launch(block_gather.sorted_block_points, dim=pairs, device=device, inputs=[
        points.array, labels, point_ids, groups.order, member_blocks.count, float(np.float32(length_m)), scaled_points, sorted_labels])
    test_box = None if member_box is None else (member_box[0] - 1, member_box[1] + 1)  # a test block is a face neighbour of a block
    return DeviceGatherTables(gated_targets(tests, last_of(slot), test_box, scratch), sources, narrow_starts(groups, scratch), scaled_points,
                              sorted_labels, member_blocks.count, groups.blocks, groups.count)


def near_face_masks(scaled_points: wp.array, pair_count: wp.array, point_start: wp.array, blocks: wp.array, block_count: wp.array, *,
                    cells_per_block: int, resolution_m: float, grid_offset_m: float, length_m: float,
                    scratch: DeviceScratch | None = None) -> wp.array:
    """The gather kernel's near-face masks [words, 6] (``block_gather.near_face_masks``) of the
    pair_count[0] sorted points (room for all of ``scaled_points``), block s (``blocks[s]``, vec3i) owning
    point_start[s]:point_start[s + 1] of block_count[0] blocks; ``scratch``: where the array is kept
    (None: a new one)."""
    device = scaled_points.device
    words = block_gather.near_face_words(scaled_points.shape[0])
    shape = (words, block_gather.FACE_COUNT)
    near = scratch.empty(shape, wp.int64) if scratch is not None else wp.empty(shape, dtype=wp.int64, device=device)
    wp.launch(block_gather.near_face_masks, dim=words, device=device, inputs=[
        scaled_points, pair_count, point_start, block_count, blocks, cells_per_block, float(np.float32(resolution_m)),
        float(np.float32(grid_offset_m)), float(np.float32(length_m)), near])
    return near

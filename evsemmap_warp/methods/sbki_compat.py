"""Per-scan preprocessing of the original S-BKI / S-CSM, reproduced in float32: numpy, and host
kernels for the per-point passes (``kernels.free_space`` rays, ``kernels.voxel_grid`` leaf indices,
``kernels.radix_sort`` the stable sorts).

What the C++ does before its kernel loops (docs/compatibility.md §1, BKISemanticMapping@66e3258):
PCL VoxelGrid downsampling of the hits (centroid, majority label, smallest label on ties), the
range filter, free samples along each ray plus the sensor origin once per hit, a second VoxelGrid
over the free samples, and block membership by inclusive float32 box tests (a point exactly on a
block face belongs to both blocks). The mapping itself then runs on the Warp gather (S-BKI) or
scatter (S-CSM) kernel.

This is the host path, one scan per worker thread, which a CPU map takes; for a GPU map the S-BKI
kernel's steps run as parallel kernels on the device (``methods.sbki_device``, the same results).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import block_gather, block_membership, free_space, radix_sort, voxel_grid
from ..voxel_keys import column_bounds, pack_voxel_keys, take_rows

FREE_LABEL = 0
# A block and its 6 face neighbours: S-BKI's "extended block" (the 27-block variant is compiled out).
EXTENDED_BLOCK_OFFSETS = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64)
_INT32_MAX = np.iinfo(np.int32).max
# More free samples than this in one scan means a far sensor origin or a missing range limit, not a map.
MAX_FREE_SAMPLES_PER_SCAN = 50_000_000


def block_size_m(resolution_m: float, block_depth: int) -> np.float32:
    """Block edge as the C++ computes it: (float) 2^(depth-1) * (float) resolution."""
    return np.float32(np.float32(2 ** (block_depth - 1)) * np.float32(resolution_m))


def box_cells(shape: np.ndarray) -> int:
    """The cells of a box of ``shape`` (per axis), exactly: numpy's int64 product wraps past 2^63, and a
    wrapped count of a huge box can look small."""
    cells = 1
    for length in shape:
        cells *= int(length)
    return cells


def leaf_grid(lo: np.ndarray, hi: np.ndarray, leaf_m: float, *, warn: bool = True) -> tuple[np.float32, np.ndarray, np.ndarray] | None:
    """PCL VoxelGrid's leaf grid over a cloud's float32 bounds: 1 / leaf in float32, the lowest leaf per
    axis and the leaves per axis; None (with a warning, unless not ``warn``) for a grid PCL refuses, which
    leaves the cloud unchanged."""
    inverse_leaf = np.float32(1.0) / np.float32(leaf_m)
    extent = ((hi - lo) * inverse_leaf).astype(np.int64) + 1
    if box_cells(extent) > _INT32_MAX:
        if not warn:
            return None
        # PCL refuses such grids and returns the cloud unchanged; so do we, loudly.
        warnings.warn(f"VoxelGrid leaf {leaf_m} m is too small for a {hi - lo} m cloud; returning it unchanged, as PCL does")
        return None
    # floor(p / leaf) is monotonic in p, so its extremes are those of the extreme coordinates.
    ijk_lo = np.floor(lo * inverse_leaf).astype(np.int64)
    return inverse_leaf, ijk_lo, np.floor(hi * inverse_leaf).astype(np.int64) - ijk_lo + 1


def voxel_grid_downsample(points: np.ndarray, labels: np.ndarray, leaf_m: float) -> tuple[np.ndarray, np.ndarray]:
    """pcl::VoxelGrid with downsample_all_data: one point per occupied leaf at the float32 centroid
    (``kernels.voxel_grid.leaf_centroids``: summed point by point from zero, as PCL's CentroidPoint),
    labelled by majority (smallest label on ties), in ascending leaf index order (x fastest)."""
    points = np.asarray(points, dtype=np.float32)
    labels = np.asarray(labels, dtype=np.int64)
    if len(points) == 0:
        return points.reshape(0, 3), labels
    grid = leaf_grid(*column_bounds(points), leaf_m)
    if grid is None:
        return points, labels
    inverse_leaf, ijk_lo, dims = grid
    # The leaf indices come from a kernel (``kernels.voxel_grid``; docs/performance.md, "Measurements behind the code's choices").
    n = len(points)
    points_wp = wp.array(np.ascontiguousarray(points), dtype=wp.vec3, device="cpu", copy=False)
    position_bits, key_bits = _packing_bits(n, box_cells(dims))
    one_label = labels.min() == labels.max()  # (the free samples): it is every leaf's majority
    if position_bits + key_bits <= 62:  # the leaf indices packed with their positions as the kernel computes them
        packed = wp.empty(n, dtype=wp.int64, device="cpu")
        wp.launch(voxel_grid.packed_leaf_indices, dim=n, device="cpu", inputs=[
            points_wp, float(inverse_leaf), wp.vec3l(*[int(x) for x in ijk_lo]), int(dims[0]), int(dims[1]), position_bits, packed])
        if one_label:  # no order or runs to list: the centroids straight from the sorted values
            centroids = wp.empty(n, dtype=wp.vec3, device="cpu")
            leaves = wp.zeros(1, dtype=int, device="cpu")
            wp.launch(voxel_grid.leaf_centroids_of_sorted, dim=1, device="cpu", inputs=[
                points_wp, wp.array(_sort_packed(packed.numpy(), position_bits, key_bits), dtype=wp.int64, device="cpu", copy=False), position_bits,
                centroids, leaves])
            leaf_count = int(leaves.numpy()[0])
            return centroids.numpy()[:leaf_count], np.full(leaf_count, labels[0], np.int64)
        order, starts = sorted_runs(packed.numpy(), position_bits, key_bits)
    else:
        leaf_index = wp.empty(n, dtype=wp.int64, device="cpu")
        wp.launch(voxel_grid.leaf_indices, dim=n, device="cpu", inputs=[
            points_wp, wp.array([n], dtype=int, device="cpu"), float(inverse_leaf), *[int(x) for x in ijk_lo], int(dims[0]), int(dims[1]), leaf_index])
        order, starts = stable_sorted_runs(leaf_index.numpy(), box_cells(dims))
    counts = np.diff(starts)
    starts = starts[:-1]
    centroids = wp.empty(len(starts), dtype=wp.vec3, device="cpu")
    wp.launch(voxel_grid.leaf_centroids, dim=1, device="cpu", inputs=[
        points_wp, wp.array(order, dtype=wp.int64, device="cpu", copy=False), wp.array(starts, dtype=wp.int64, device="cpu", copy=False),
        wp.array(counts, dtype=wp.int64, device="cpu", copy=False), centroids])
    centroids = centroids.numpy()
    if one_label:
        return centroids, np.full(len(starts), labels[0], np.int64)

    cell_of_point = np.repeat(np.arange(len(starts)), counts)
    return centroids, _majority_labels(cell_of_point, labels[order], len(starts))


# Label counts per leaf as one dense [leaves, labels] table up to this many entries (int64: 256 MB).
MAX_DENSE_LABEL_COUNTS = 1 << 25


def _majority_labels(cells: np.ndarray, labels: np.ndarray, n_cells: int) -> np.ndarray:
    """Per cell 0..n_cells-1 the most frequent of its labels, the smallest on ties."""
    label_min = int(labels.min())
    span = int(labels.max()) - label_min + 1
    if n_cells * span <= MAX_DENSE_LABEL_COUNTS:
        # argmax returns the first maximum: the smallest label.
        table = np.bincount(cells * span + (labels - label_min), minlength=n_cells * span).reshape(n_cells, span)
        return np.argmax(table, axis=1).astype(np.int64) + label_min
    pair_cell, pair_label, pair_count = _count_pairs(cells, labels)
    # Sort by cell, count descending, label ascending: each cell's first pair is its majority.
    best = np.lexsort((pair_label, -pair_count, pair_cell))
    first_of_cell = best[np.r_[True, pair_cell[best][1:] != pair_cell[best][:-1]]]
    return pair_label[first_of_cell]


# Digits of at most this many bits per radix pass, and below this many keys numpy's sort instead
# (docs/performance.md, "Measurements behind the code's choices").
MAX_RADIX_DIGIT_BITS = 13
MIN_RADIX_SORT_KEYS = 10_000


def _packing_bits(n: int, key_limit: int) -> tuple[int, int]:
    """The bits of a position among n values, and of a key below ``key_limit`` (``stable_sort``'s packing)."""
    return max(1, int(n - 1).bit_length()), int(max(key_limit, 1) - 1).bit_length()


# kernels.radix_sort on the host rather than Warp's wp.utils.radix_sort_pairs (docs/performance.md, "Measurements behind the code's choices"); the device
# paths (methods.sbki_device) sort with Warp's, as one thread would not do on a GPU.
def _sort_packed(packed: np.ndarray, position_bits: int, key_bits: int) -> np.ndarray:
    """Values packed as key << position_bits | position, sorted by the key bits (so stably): the radix sort
    for large inputs, numpy's for small ones."""
    if len(packed) < MIN_RADIX_SORT_KEYS or key_bits == 0:
        return np.sort(packed)
    return _radix_sort(packed, position_bits, key_bits)


def stable_sorted_runs(keys: np.ndarray, key_limit: int) -> tuple[np.ndarray, np.ndarray]:
    """``sorted_runs`` of keys too wide to pack with their positions (``stable_sort``): the stable order and
    the starts of its runs of equal keys [R + 1], the last the key count."""
    sorted_keys, order = stable_sort(keys, key_limit)
    return order, np.r_[np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]), len(order)]


def sorted_runs(packed: np.ndarray, position_bits: int, key_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """(the stable order, the starts of its runs of equal keys [R + 1], the last the value count) of values
    packed as key << position_bits | position (``_packing_bits``; keys below 2^key_bits)."""
    packed = _sort_packed(packed, position_bits, key_bits)
    order = wp.empty(len(packed), dtype=wp.int64, device="cpu")
    starts = wp.empty(len(packed) + 1, dtype=wp.int64, device="cpu")
    runs = wp.zeros(1, dtype=int, device="cpu")
    wp.launch(radix_sort.sorted_runs, dim=1, device="cpu", inputs=[wp.array(packed, dtype=wp.int64, device="cpu", copy=False), position_bits, order, starts,
                                                                   runs])
    return order.numpy(), starts.numpy()[:int(runs.numpy()[0]) + 1]


def stable_sort(keys: np.ndarray, key_limit: int) -> tuple[np.ndarray, np.ndarray]:
    """(sorted keys, the stable order) of non-negative int64 keys below ``key_limit``.

    Each key is packed with its position into one int64 (the packed values are unique, so any sort of them is
    stable) and the packed values are sorted by the key bits alone: by the LSD radix sort of
    ``kernels.radix_sort`` for large inputs (free_res 0.5 scans sort 0.5-0.8 M leaf indices of ~26 bits in 2
    passes), by numpy's sort for small ones (``_sort_packed``). Keys too wide to pack take numpy's stable
    argsort. The VoxelGrid and ``group_by_block`` pack their keys in the kernel that computes them and list
    the order with its runs (``sorted_runs``)."""
    keys = np.asarray(keys, dtype=np.int64)
    n = len(keys)
    position_bits, key_bits = _packing_bits(n, key_limit)
    if key_bits + position_bits > 62:
        order = np.argsort(keys, kind="stable")
        return keys[order], order
    packed = _sort_packed((keys << position_bits) | np.arange(n, dtype=np.int64), position_bits, key_bits)
    return packed >> position_bits, packed & ((1 << position_bits) - 1)


def _radix_sort(values: np.ndarray, lowest_bit: int, key_bits: int) -> np.ndarray:
    """The int64 values (overwritten) stably sorted by their bits lowest_bit .. lowest_bit + key_bits."""
    passes = -(-key_bits // MAX_RADIX_DIGIT_BITS)
    digit_bits = -(-key_bits // passes)
    n = len(values)
    source = wp.array(values, dtype=wp.int64, device="cpu", copy=False)
    counts = wp.zeros((passes, 1 << digit_bits), dtype=int, device="cpu")
    for first in range(0, passes, radix_sort.HISTOGRAM_PASSES):
        rows = [counts[min(p, passes - 1)] for p in range(first, first + radix_sort.HISTOGRAM_PASSES)]
        wp.launch(radix_sort.digit_histograms, dim=1, device="cpu", inputs=[
            source, lowest_bit + first * digit_bits, digit_bits, min(passes - first, radix_sort.HISTOGRAM_PASSES), *rows])
    target = wp.empty(n, dtype=wp.int64, device="cpu")  # the passes alternate between it and values
    for p, digit_counts in enumerate(counts.numpy()):
        if digit_counts.max() == n:  # one digit for every value: this pass would keep the order
            continue
        next_slot = wp.array(np.r_[0, np.cumsum(digit_counts[:-1])].astype(np.int32), dtype=int, device="cpu", copy=False)
        wp.launch(radix_sort.radix_scatter, dim=1, device="cpu", inputs=[source, lowest_bit + p * digit_bits, digit_bits, next_slot, target])
        source, target = target, source
    return source.numpy()


def _count_pairs(cells: np.ndarray, labels: np.ndarray):
    # One int64 per (cell, label) pair: a 1-D unique is several times faster than unique(axis=0).
    label_min = labels.min()
    span = int(labels.max() - label_min) + 1
    pairs, counts = np.unique(cells * span + (labels - label_min), return_counts=True)
    return pairs // span, pairs % span + label_min, counts


def check_free_samples(samples: float, longest: float, f: np.float32, origin: np.ndarray) -> None:
    """Refuse a scan whose free-space rays would place more than MAX_FREE_SAMPLES_PER_SCAN samples (about
    ``samples``), or whose longest ray (``longest`` m) takes 2^22 steps or more: there the float32
    distance d + f stops growing (f below half its spacing) and the step list would grow without end."""
    if samples > MAX_FREE_SAMPLES_PER_SCAN or longest / float(f) >= 2**22:
        limit = (f"at most {MAX_FREE_SAMPLES_PER_SCAN:,}" if samples > MAX_FREE_SAMPLES_PER_SCAN
                 else f"and a ray of {longest / float(f):,.0f} steps, at most {2**22:,} along one ray")
        raise ValueError(
            f"free-space rays would place about {samples:,.0f} samples in one scan (points up to {longest:,.0f} m from "
            f"the sensor origin {origin.tolist()}, one sample per free_resolution_m = {float(f)} m; {limit}): set "
            f"mapping.sbki.max_range_m, a larger mapping.sbki.free_resolution_m, or check the sensor origin")


def ray_steps(f: np.float32, longest: np.float32) -> np.ndarray:
    """The sample distances f, 2f, ... along a ray, accumulated in float32 as the C++ loop does, up to the
    first at or beyond ``longest``."""
    steps = [f]
    while steps[-1] < longest:
        steps.append(np.float32(steps[-1] + f))
    return np.array(steps, dtype=np.float32)


def free_space_samples(hits: np.ndarray, origin: np.ndarray, free_resolution_m: float) -> np.ndarray:
    """S-BKI's beam_sample for every hit, each preceded by the sensor origin itself.

    Samples sit at d = f, 2f, ... < l along the ray (d accumulated in float32, as in the C++ loop),
    plus one at l - f when l > f; every coordinate is computed in float32."""
    hits = np.asarray(hits, dtype=np.float32)
    origin = np.asarray(origin, dtype=np.float32).reshape(3)
    if len(hits) == 0:
        return np.zeros((0, 3), np.float32)
    f = np.float32(free_resolution_m)
    diff = hits - origin
    ray_length = np.sqrt(np.sum(diff * diff, axis=1, dtype=np.float32), dtype=np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = diff / ray_length[:, None]
    longest = ray_length.max()
    check_free_samples(float(np.sum(ray_length, dtype=np.float64) / float(f)) + 2 * len(hits), float(longest), f, origin)
    steps = ray_steps(f, longest)
    per_hit = np.searchsorted(steps, ray_length, side="left")  # how many d_k < l
    rows_per_hit = 1 + per_hit + (ray_length > f)  # origin + samples + the one at l - f
    first_row = np.r_[0, np.cumsum(rows_per_hit)[:-1]]
    # One thread per hit writes its rows (``kernels.free_space``; docs/performance.md, "Measurements behind the code's choices").
    out = wp.empty(int(rows_per_hit.sum()), dtype=wp.vec3, device="cpu")
    wp.launch(free_space.ray_samples, dim=len(hits), device="cpu", inputs=[
        wp.array(np.ascontiguousarray(direction), dtype=wp.vec3, device="cpu", copy=False),
        wp.array(ray_length, dtype=wp.float32, device="cpu", copy=False), wp.array([len(hits)], dtype=int, device="cpu"),
        wp.vec3(*origin.tolist()), float(f), wp.array(steps, dtype=wp.float32, device="cpu", copy=False),
        wp.array(per_hit.astype(np.int32), dtype=int, device="cpu", copy=False),
        wp.array(first_row.astype(np.int32), dtype=int, device="cpu", copy=False), out])
    return out.numpy()


def training_data(
    points: np.ndarray,
    labels: np.ndarray,
    sensor_origin: np.ndarray,
    *,
    ds_resolution_m: float,
    free_resolution_m: float,
    max_range_m: float | None,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """S-BKI's get_training_data: downsampled hits (those within ``max_range_m`` of the sensor; None: all),
    then downsampled free samples (label 0)."""
    origin = np.asarray(sensor_origin, dtype=np.float32).reshape(3)
    hits, hit_labels = voxel_grid_downsample(points, labels, ds_resolution_m)
    if max_range_m is not None and len(hits):
        d = hits - origin
        keep = np.sqrt(np.sum(d * d, axis=1, dtype=np.float32)) <= np.float32(max_range_m)
        hits, hit_labels = hits[keep], hit_labels[keep]
    frees = free_space_samples(hits, origin, free_resolution_m)
    free_points, _ = voxel_grid_downsample(frees, np.zeros(len(frees), np.int64), ds_resolution_m)
    return joined_training_set(hits, hit_labels, free_points)


def joined_training_set(hits: np.ndarray, hit_labels: np.ndarray, free_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The training set from its parts: the hits, then the free samples (label ``FREE_LABEL``), and the
    count of each."""
    train_points = np.concatenate([hits, free_points]).astype(np.float32, copy=False)
    train_labels = np.concatenate([hit_labels, np.full(len(free_points), FREE_LABEL, np.int64)])
    return train_points, train_labels, {"hits": len(hits), "free_samples": len(free_points)}


def block_memberships(points: np.ndarray, block_size: np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, block) pair with the point inside the block's closed float32 box.

    Block k spans [k B - B/2, k B + B/2] per axis (center k B, as S-BKI's hash_key_to_block); the
    R-tree query of the C++ is inclusive, so a point on a shared face belongs to both blocks.
    Returns point ids [M] and block indices [M, 3], block shift by block shift around each point's
    nearest block, points ascending within a shift (``kernels.block_membership`` tests the boxes and
    lists the pairs)."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    nearest = wp.empty((len(points), 3), dtype=wp.int64, device="cpu")
    masks = wp.empty(len(points), dtype=int, device="cpu")
    if len(points):
        wp.launch(block_membership.block_membership_masks, dim=1, device="cpu", inputs=[
            wp.array(points, dtype=wp.vec3, device="cpu", copy=False), float(np.float32(block_size)), nearest, masks])
    counts = wp.zeros(27, dtype=int, device="cpu")
    wp.launch(block_membership.membership_counts, dim=1, device="cpu", inputs=[masks, counts])
    counts = counts.numpy()
    point_ids = wp.empty(int(counts.sum()), dtype=wp.int64, device="cpu")
    blocks = wp.empty((int(counts.sum()), 3), dtype=wp.int64, device="cpu")
    wp.launch(block_membership.membership_pairs, dim=1, device="cpu", inputs=[
        masks, nearest, wp.array(np.r_[0, np.cumsum(counts[:-1])].astype(np.int32), dtype=int, device="cpu", copy=False), point_ids, blocks])
    return point_ids.numpy(), blocks.numpy()


def unique_rows(index: np.ndarray) -> np.ndarray:
    """np.unique(index, axis=0) for [M, 3] integer indices, via one packed int64 per row."""
    if len(index) == 0:
        return np.zeros((0, 3), np.int64)
    index = np.asarray(index, dtype=np.int64)
    lo, hi = column_bounds(index)
    span = hi - lo + 1
    packed = np.unique(((index[:, 0] - lo[0]) * span[1] + (index[:, 1] - lo[1])) * span[2] + (index[:, 2] - lo[2]))
    z = packed % span[2]
    y = (packed // span[2]) % span[1]
    x = packed // (span[1] * span[2])
    return np.stack([x, y, z], axis=1) + lo


def test_blocks(owner_blocks: np.ndarray) -> np.ndarray:
    """Blocks whose extended block (itself + 6 face neighbours) holds at least one point."""
    occupied = unique_rows(owner_blocks)
    return unique_rows((occupied[:, None, :] + EXTENDED_BLOCK_OFFSETS[None]).reshape(-1, 3))


@dataclass
class GatherTables:
    """One scan's blocks for the S-BKI gather kernel: the blocks holding points [B, 3] (key order), the
    (point, block) pairs sorted by block (``pair_order``; block s owns sorted pairs
    point_start[s]:point_start[s + 1]), the test blocks [T, 3] and, per test block and
    EXTENDED_BLOCK_OFFSETS entry f, the index of the block at test + f among the blocks (-1: none)."""

    blocks: np.ndarray
    pair_order: np.ndarray
    point_start: np.ndarray
    test_blocks: np.ndarray
    sources: np.ndarray


def gather_tables(owner_blocks: np.ndarray, check_blocks=None) -> GatherTables:
    """The ``GatherTables`` of one scan from each point's owner block [N, 3]: the blocks holding points, the
    points sorted by block, the test blocks and their sources (``kernels.block_gather.extended_block_tables``).
    ``check_blocks(count)``: called with the number of blocks holding points before the test blocks are
    listed (to refuse a scan the map has no room for, before that allocation)."""
    blocks, _, order, point_start = group_by_block(owner_blocks)
    if check_blocks is not None:
        check_blocks(len(blocks))
    tests, sources = _extended_block_tables(blocks)
    return GatherTables(blocks, order, point_start, tests, sources)


def _extended_block_tables(blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``kernels.block_gather.extended_block_tables`` on the host: test blocks [T, 3] (int64, key order) and
    their sources [T, 7] (int32) of distinct blocks [B, 3] in key order; the blocks are packed in their
    box widened by one, or, where that box does not pack in 62 bits, merged axis by axis
    (``extended_block_tables_wide``)."""
    f = len(EXTENDED_BLOCK_OFFSETS)
    most = len(blocks) * f
    if most == 0:
        return np.zeros((0, 3), np.int64), np.zeros((0, f), np.int32)
    blocks = np.ascontiguousarray(blocks, dtype=np.int64)
    lo, hi = column_bounds(blocks)
    lo = lo - 1
    span = hi + 2 - lo
    sources = wp.empty((most, f), dtype=int, device="cpu")
    count = wp.zeros(1, dtype=int, device="cpu")
    if box_cells(span) < 1 << 62:
        relative = blocks - lo
        keys = (relative[:, 0] * span[1] + relative[:, 1]) * span[2] + relative[:, 2]
        shifts = (EXTENDED_BLOCK_OFFSETS[:, 0] * span[1] + EXTENDED_BLOCK_OFFSETS[:, 1]) * span[2] + EXTENDED_BLOCK_OFFSETS[:, 2]
        widest = int(np.abs(shifts).max())
        last = int(keys[-1]) + widest
        tests = wp.empty(most, dtype=wp.int64, device="cpu")
        wp.launch(block_gather.extended_block_tables, dim=1, device="cpu", inputs=[
            wp.array(np.append(keys, last + 2 * widest + 1), dtype=wp.int64, device="cpu", copy=False),
            wp.array(shifts, dtype=wp.int64, device="cpu", copy=False), last, tests, sources, count])
        n = int(count.numpy()[0])
        packed = tests.numpy()[:n]
        z, yz = packed % span[2], packed // span[2]
        return np.stack([yz // span[1], yz % span[1], z], axis=1) + lo, sources.numpy()[:n]
    tests = wp.empty(most, dtype=wp.vec3l, device="cpu")
    wp.launch(block_gather.extended_block_tables_wide, dim=1, device="cpu", inputs=[
        wp.array(blocks, dtype=wp.vec3l, device="cpu", copy=False), wp.array(EXTENDED_BLOCK_OFFSETS, dtype=wp.vec3l, device="cpu", copy=False),
        wp.zeros(f, dtype=int, device="cpu"), tests, sources, count])
    n = int(count.numpy()[0])
    return tests.numpy()[:n].reshape(-1, 3), sources.numpy()[:n]


def group_by_block(member_blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The distinct blocks of (point, block) memberships [P, 3], in packed-key order, their keys, the
    pair order that groups the pairs by block (stable: input order within a block) and the CSR starts
    (block s owns sorted pairs point_start[s]:point_start[s + 1])."""
    member_blocks = np.ascontiguousarray(np.asarray(member_blocks, dtype=np.int64).reshape(-1, 3))
    if len(member_blocks) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64)
    # Row-major positions in the blocks' bounding box sort as the packed keys do (x, then y, then z).
    lo, hi = column_bounds(member_blocks)
    span = [int(x) for x in hi - lo + 1]
    cells = box_cells(span)
    n = len(member_blocks)
    position_bits, key_bits = _packing_bits(n, cells)
    if position_bits + key_bits <= 62:  # the positions packed with their rows as the kernel computes them
        packed = wp.empty(n, dtype=wp.int64, device="cpu")
        wp.launch(block_gather.packed_box_positions, dim=n, device="cpu", inputs=[
            wp.array(member_blocks, dtype=wp.int64, device="cpu", copy=False), wp.vec3l(*[int(x) for x in lo]), span[1], span[2], position_bits, packed])
        order, starts = sorted_runs(packed.numpy(), position_bits, key_bits)
    else:
        if cells < 1 << 62:
            relative = member_blocks - lo
            position = (relative[:, 0] * span[1] + relative[:, 1]) * span[2] + relative[:, 2]
        else:  # blocks spread over the whole key range: their packed keys (63 bits) sort alike
            position, cells = pack_voxel_keys(member_blocks), 1 << 63
        order, starts = stable_sorted_runs(position, cells)
    blocks = take_rows(member_blocks, order[starts[:-1]])
    return blocks, pack_voxel_keys(blocks), order, starts


# Above this many cells the release's block models look their blocks up by a binary search instead of a
# dense grid over the scan's blocks, and the device paths take the host path (the grid is int32: 64 MB at
# this size).
MAX_DENSE_LOOKUP_CELLS = 1 << 24


def dense_block_grid(blocks: np.ndarray):
    """A dense int32 map of the blocks' positions over their bounding box widened by 3 (-1: none),
    and its lowest corner; the grid is None when it would exceed MAX_DENSE_LOOKUP_CELLS."""
    if len(blocks) == 0:
        return None, None
    lo, hi = column_bounds(blocks)
    lo = lo - 3
    shape = hi + 4 - lo
    if box_cells(shape) > MAX_DENSE_LOOKUP_CELLS:
        return None, lo
    grid = np.full(tuple(shape), -1, np.int32)
    grid[tuple((blocks - lo).T)] = np.arange(len(blocks), dtype=np.int32)
    return grid, lo

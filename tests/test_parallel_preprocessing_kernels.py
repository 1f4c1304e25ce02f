"""Each kernel of the compatibility modes' parallel preprocessing (``methods.sbki_device``,
``methods.release_device``) against its numpy twin, on random inputs with the edge cases: one element,
values on cell and block faces, far coordinates, runs of equal keys (collisions). Each runs over more room
than its count (the rows past it garbage), as the device path runs them, and none counted."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from evsemmap_warp.kernels import block_gather, block_membership, free_space, release, voxel_grid
from evsemmap_warp.reference import block_gather as block_gather_twin
from evsemmap_warp.reference import block_membership as membership_twin
from evsemmap_warp.reference import free_space as free_space_twin
from evsemmap_warp.reference import release as release_twin
from evsemmap_warp.reference import voxel_grid as voxel_grid_twin


def _a(values, dtype, device):
    return wp.array(np.ascontiguousarray(values), dtype=dtype, device=device)


def _launch(kernel, dim, inputs, device):
    wp.launch(kernel, dim=dim, inputs=inputs, device=device)


def _count(n, device):
    return wp.array([n], dtype=int, device=device)


EXTRA = 5  # rows of room past each count


@pytest.mark.parametrize("n", [0, 1, 7, 3000])
def test_leaf_runs_starts_and_majority(device, n):
    rng = np.random.default_rng(n)
    room = n + EXTRA
    count = _count(n, device)
    sorted_leaf = np.r_[np.sort(rng.integers(0, max(2, n // 4), n)), rng.integers(0, 9, EXTRA)].astype(np.int64)
    heads = wp.empty(room, dtype=int, device=device)
    _launch(voxel_grid.leaf_runs, room, [_a(sorted_leaf, wp.int64, device), count, heads], device)
    np.testing.assert_array_equal(heads.numpy(), voxel_grid_twin.leaf_runs(sorted_leaf, n))
    rank = np.cumsum(heads.numpy()).astype(np.int32)
    leaves = int(rank[-1])
    starts = wp.empty(room + 1, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_starts, room, [_a(rank, wp.int32, device), count, starts], device)
    np.testing.assert_array_equal(starts.numpy()[:leaves + 1], voxel_grid_twin.leaf_starts(rank, n))
    labels = rng.integers(-2, 3, room).astype(np.int64)
    order = np.r_[rng.permutation(n), np.arange(n, room)].astype(np.int64)
    keys, positions = wp.empty(room, dtype=wp.int64, device=device), wp.empty(room, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_label_keys, room, [_a(order, wp.int64, device), _a(rank, wp.int32, device), _a(labels, wp.int64, device), count, -2, 5,
                                               keys, positions], device)
    want_keys, want_positions = voxel_grid_twin.leaf_label_keys(order, rank, labels, -2, 5, n)
    np.testing.assert_array_equal(keys.numpy(), want_keys)
    np.testing.assert_array_equal(positions.numpy(), want_positions)
    sorted_keys = np.sort(want_keys)
    majority = wp.empty(room, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_majority_labels, room, [_a(sorted_keys, wp.int64, device), starts, _count(leaves, device), -2, 5, majority], device)
    np.testing.assert_array_equal(majority.numpy()[:leaves], voxel_grid_twin.leaf_majority_labels(sorted_keys, starts.numpy(), leaves, -2, 5))
    points = (rng.normal(size=(room, 3)) * 50 + 40_000).astype(np.float32)
    centroids = wp.empty(room, dtype=wp.vec3, device=device)
    _launch(voxel_grid.leaf_centroids_parallel, room, [_a(points, wp.vec3, device), _a(order, wp.int64, device), starts, _count(leaves, device), centroids],
            device)
    np.testing.assert_array_equal(centroids.numpy()[:leaves], voxel_grid_twin.leaf_centroids_parallel(points, order, starts.numpy(), leaves))
    lowest, highest = wp.full(3, np.inf, dtype=wp.float32, device=device), wp.full(3, -np.inf, dtype=wp.float32, device=device)
    _launch(voxel_grid.point_bounds, room, [_a(points, wp.vec3, device), count, lowest, highest], device)
    want_low, want_high = voxel_grid_twin.point_bounds(points, n)
    np.testing.assert_array_equal(lowest.numpy(), want_low)
    np.testing.assert_array_equal(highest.numpy(), want_high)
    values = wp.empty(room, dtype=wp.int64, device=device)
    _launch(voxel_grid.positions, room, [values], device)
    np.testing.assert_array_equal(values.numpy(), voxel_grid_twin.positions(room))
    inverse_leaf, lowest_leaf, dims = 10.0, np.floor(points.min(axis=0) * 10).astype(np.int64), np.array([1000, 1000, 1000])
    leaf = wp.empty(room, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_indices, room, [_a(points, wp.vec3, device), count, inverse_leaf, *[int(x) for x in lowest_leaf], 1000, 1000, leaf], device)
    np.testing.assert_array_equal(leaf.numpy(), voxel_grid_twin.leaf_indices(points, inverse_leaf, lowest_leaf, dims[0], dims[1], n))


@pytest.mark.parametrize("n", [0, 1, 500])
def test_ray_kernels(device, n):
    rng = np.random.default_rng(n)
    room = n + EXTRA
    count = _count(n, device)
    origin = np.array([3.25, -1.5, 1.2], np.float32)
    hits = (origin + rng.normal(size=(room, 3)) * 8).astype(np.float32)
    hits[0] = origin + np.float32(0.5)  # on a step
    if n > 2:
        hits[1] = origin  # a zero ray
    direction, ray_length = wp.zeros(room, dtype=wp.vec3, device=device), wp.zeros(room, dtype=wp.float32, device=device)
    _launch(free_space.ray_geometry, room, [_a(hits, wp.vec3, device), count, wp.vec3(*origin.tolist()), direction, ray_length], device)
    want_direction, want_length = free_space_twin.ray_geometry(hits[:n], origin)
    np.testing.assert_array_equal(direction.numpy()[:n], want_direction)
    np.testing.assert_array_equal(ray_length.numpy()[:n], want_length)
    assert not ray_length.numpy()[n:].any()  # nothing past the count
    steps = np.cumsum(np.full(int(want_length.max(initial=0) / 0.5) + 2, np.float32(0.5)), dtype=np.float32)
    per_hit, rows, total_rows = wp.empty(room, dtype=int, device=device), wp.empty(room, dtype=int, device=device), wp.zeros(1, dtype=wp.int64, device=device)
    _launch(free_space.samples_per_ray, room, [ray_length, count, _a(steps, wp.float32, device), 0.5, per_hit, rows, total_rows], device)
    want_per_hit, want_rows, want_total = free_space_twin.samples_per_ray(ray_length.numpy(), steps, 0.5, n)
    np.testing.assert_array_equal(per_hit.numpy()[:n], want_per_hit)
    np.testing.assert_array_equal(rows.numpy(), want_rows)
    assert total_rows.numpy()[0] == want_total
    first_row = np.r_[0, np.cumsum(want_rows)].astype(np.int32)
    total = int(first_row[room])
    for capacity in (total, max(total - 3, 0), max(total - 1, 0)):  # room for every row, for all but 3, all but 1
        out = _a(np.full((capacity, 3), 1e30, np.float32), wp.vec3, device)  # every row below the room is written
        _launch(free_space.ray_samples, room, [direction, ray_length, count, wp.vec3(*origin.tolist()), 0.5, _a(steps, wp.float32, device), per_hit,
                                               _a(first_row, wp.int32, device), out], device)
        np.testing.assert_array_equal(out.numpy().reshape(-1, 3), free_space_twin.ray_samples(
            want_direction, want_length, origin, 0.5, steps, want_per_hit, first_row, capacity).reshape(-1, 3))
    keep = wp.empty(room, dtype=int, device=device)
    _launch(free_space.within_range, room, [ray_length, count, 8.0, keep], device)
    np.testing.assert_array_equal(keep.numpy(), free_space_twin.within_range(ray_length.numpy(), 8.0, n))
    slot = np.cumsum(keep.numpy()).astype(np.int32)
    labels = rng.integers(0, 5, room).astype(np.int64)
    kept = int(slot[-1])
    out = [wp.empty(kept, dtype=t, device=device) for t in (wp.vec3, wp.int64, wp.vec3, wp.float32)]
    _launch(free_space.compact_rays, room, [keep, _a(slot, wp.int32, device), _a(hits, wp.vec3, device), _a(labels, wp.int64, device), direction,
                                            ray_length, *out], device)
    for got, want in zip(out, free_space_twin.compact_rays(keep.numpy(), slot, hits, labels, direction.numpy(), ray_length.numpy())):
        np.testing.assert_array_equal(got.numpy(), want)
    longest = wp.zeros(1, dtype=wp.float32, device=device)
    _launch(free_space.longest_ray, room, [_a(np.r_[want_length, np.full(EXTRA, 1e9, np.float32)], wp.float32, device), count, longest], device)
    assert longest.numpy()[0] == free_space_twin.longest_ray(want_length)


@pytest.mark.parametrize("n", [0, 1, 2000])
def test_membership_kernels(device, n):
    rng = np.random.default_rng(n)
    room = n + EXTRA
    count = _count(n, device)
    size = np.float32(0.4)
    points = (rng.uniform(-3, 3, (room, 3))).astype(np.float32)
    points[: n // 4] = np.round(points[: n // 4] / size) * size + size / np.float32(2)  # on block faces, edges, corners
    if n > 10:
        points[n - 5:n] += np.float32(70_000)
    nearest, masks, counts = wp.empty((room, 3), dtype=wp.int64, device=device), wp.empty(room, dtype=int, device=device), wp.empty(room, dtype=int, device=device)
    _launch(block_membership.membership_masks_parallel, room, [_a(points, wp.vec3, device), count, float(size), nearest, masks, counts], device)
    want_nearest, want_masks, want_counts = membership_twin.membership_masks_parallel(points, size, n)
    np.testing.assert_array_equal(nearest.numpy()[:n], want_nearest)
    np.testing.assert_array_equal(masks.numpy()[:n], want_masks)
    np.testing.assert_array_equal(counts.numpy(), want_counts)
    first = np.r_[0, np.cumsum(want_counts)].astype(np.int32)
    pairs = int(want_counts.sum())
    for capacity in (pairs, max(pairs - 2, 0)):  # room for every pair, and for all but two
        bits, ids = wp.zeros(capacity, dtype=wp.int64, device=device), wp.zeros(capacity, dtype=wp.int64, device=device)
        _launch(block_membership.membership_pairs_by_point, room, [masks, count, _a(first, wp.int32, device), capacity, bits, ids], device)
        want_bits, want_ids = membership_twin.membership_pairs_by_point(want_masks, first, capacity)
        np.testing.assert_array_equal(bits.numpy(), want_bits)
        np.testing.assert_array_equal(ids.numpy(), want_ids)
    want_bits, want_ids = membership_twin.membership_pairs_by_point(want_masks, first)
    assert pairs > n or n <= 1  # face points belong to several blocks
    blocks = wp.zeros((pairs + EXTRA, 3), dtype=wp.int64, device=device)
    _launch(block_membership.membership_blocks, pairs + EXTRA, [_a(np.r_[want_bits, np.full(EXTRA, 31)], wp.int64, device),
                                                                _a(np.r_[want_ids, np.zeros(EXTRA, np.int64)], wp.int64, device), _count(pairs, device),
                                                                nearest, blocks], device)
    np.testing.assert_array_equal(blocks.numpy()[:pairs], membership_twin.membership_blocks(want_bits, want_ids, want_nearest))
    assert not blocks.numpy()[pairs:].any()


def test_block_table_kernels(device):
    rng = np.random.default_rng(9)
    member = rng.integers(-6, 6, (400, 3)).astype(np.int64)
    member[:50] = member[50]  # one block many times
    n = len(member)
    room = np.r_[member, rng.integers(-99, 99, (EXTRA, 3))]  # garbage past the count
    count = _count(n, device)
    lowest, highest = wp.full(3, np.iinfo(np.int64).max, dtype=wp.int64, device=device), wp.full(3, np.iinfo(np.int64).min, dtype=wp.int64, device=device)
    _launch(block_gather.block_bounds, len(room), [_a(room, wp.int64, device), count, lowest, highest], device)
    lo, hi = block_gather_twin.block_bounds(member)
    np.testing.assert_array_equal(lowest.numpy(), lo)
    np.testing.assert_array_equal(highest.numpy(), hi)
    span = hi - lo + 1
    positions, index = wp.empty(len(room), dtype=wp.int64, device=device), wp.empty(len(room), dtype=wp.int64, device=device)
    _launch(block_gather.box_positions, len(room), [_a(room, wp.int64, device), count, wp.vec3l(*lo.tolist()), int(span[1]), int(span[2]), positions, index],
            device)
    want_positions, want_index = block_gather_twin.box_positions(room, lo, int(span[1]), int(span[2]), n)
    np.testing.assert_array_equal(positions.numpy(), want_positions)
    np.testing.assert_array_equal(index.numpy(), want_index)
    order = np.argsort(want_positions, kind="stable")
    assert (order[n:] >= n).all()  # the rows past the count sort last
    sorted_positions = want_positions[order][:n]
    starts = np.r_[np.flatnonzero(np.r_[True, sorted_positions[1:] != sorted_positions[:-1]]), n]
    corner = lo - 3
    shape = tuple(int(x) for x in hi + 4 - corner)
    blocks_count = len(starts) - 1
    capacity = blocks_count + EXTRA
    blocks, grid_blocks, grid = wp.zeros(capacity, dtype=wp.vec3i, device=device), wp.zeros(capacity, dtype=wp.vec3i, device=device), wp.full(shape, -1, dtype=int, device=device)
    _launch(block_gather.distinct_blocks, capacity, [_a(room, wp.int64, device), _a(order, wp.int64, device), _a(np.r_[starts, np.zeros(EXTRA, np.int64)], wp.int64, device),
                                                     _count(blocks_count, device), wp.vec3l(*corner.tolist()), blocks, grid_blocks, grid], device)
    want_blocks, want_grid_blocks, want_grid = block_gather_twin.distinct_blocks(member, order[:n], starts, corner, shape)
    np.testing.assert_array_equal(blocks.numpy()[:blocks_count], want_blocks)
    np.testing.assert_array_equal(grid_blocks.numpy()[:blocks_count], want_grid_blocks)
    np.testing.assert_array_equal(grid.numpy(), want_grid)
    assert not blocks.numpy()[blocks_count:].any()
    offsets = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.int32)
    marked = wp.zeros(int(np.prod(shape)), dtype=int, device=device)
    garbage_grid_blocks = np.r_[grid_blocks.numpy()[:blocks_count], np.full((EXTRA, 3), 10**6, np.int32)]  # far outside the grid: never read
    _launch(block_gather.mark_test_blocks, (capacity, 7), [_a(garbage_grid_blocks, wp.vec3i, device), _count(blocks_count, device), _a(offsets, wp.vec3i, device),
                                                           grid, marked], device)
    want_marked = block_gather_twin.mark_test_blocks(want_grid_blocks, offsets, shape)
    np.testing.assert_array_equal(marked.numpy(), want_marked)
    slot = np.cumsum(want_marked).astype(np.int32)
    tests, sources = wp.empty(int(slot[-1]), dtype=wp.vec3i, device=device), wp.empty((int(slot[-1]), 7), dtype=int, device=device)
    _launch(block_gather.list_test_blocks, marked.shape[0], [marked, _a(slot, wp.int32, device), grid, _a(offsets, wp.vec3i, device), wp.vec3l(*corner.tolist()), tests, sources], device)
    want_tests, want_sources = block_gather_twin.list_test_blocks(want_marked, want_grid, offsets, corner)
    np.testing.assert_array_equal(tests.numpy(), want_tests)
    np.testing.assert_array_equal(sources.numpy(), want_sources)
    points = rng.normal(size=(100, 3)).astype(np.float32)
    labels = rng.integers(0, 9, 100).astype(np.int64)
    ids = rng.integers(0, 100, len(room)).astype(np.int64)
    scaled, sorted_labels = wp.zeros(len(room), dtype=wp.vec3, device=device), wp.zeros(len(room), dtype=int, device=device)
    _launch(block_gather.sorted_block_points, len(room), [_a(points, wp.vec3, device), _a(labels, wp.int64, device), _a(ids, wp.int64, device),
                                                          _a(order, wp.int64, device), count, 0.3, scaled, sorted_labels], device)
    want_scaled, want_labels = block_gather_twin.sorted_block_points(points, labels, ids, order[:n], 0.3)
    np.testing.assert_array_equal(scaled.numpy()[:n], want_scaled)
    np.testing.assert_array_equal(sorted_labels.numpy()[:n], want_labels)
    assert not sorted_labels.numpy()[n:].any()
    narrow = wp.zeros(capacity + 1, dtype=int, device=device)
    _launch(block_gather.narrow_starts, capacity + 1, [_a(np.r_[starts, np.full(EXTRA, 7)], wp.int64, device), _count(blocks_count, device), narrow], device)
    np.testing.assert_array_equal(narrow.numpy()[:blocks_count + 1], block_gather_twin.narrow_starts(starts))
    assert not narrow.numpy()[blocks_count + 1:].any()


def test_count_kernels(device):
    from evsemmap_warp.kernels import device_counts
    from evsemmap_warp.reference import device_counts as counts_twin

    for total, capacity, overflowed in ((0, 4, 0), (4, 4, 0), (5, 4, 0), (5, 4, 1), (3, 4, 1)):
        status = np.array([overflowed, 0, 0, 0], np.int32)
        for kernel, total_type in ((device_counts.bounded_count, wp.int32), (device_counts.bounded_wide_count, wp.int64)):
            status_on_device, count = _a(status, wp.int32, device), wp.zeros(1, dtype=int, device=device)
            _launch(kernel, 1, [wp.array([total], dtype=total_type, device=device), capacity, 2, status_on_device, count], device)
            want_status, want_count = counts_twin.bounded_count(total, capacity, 2, status)
            np.testing.assert_array_equal(status_on_device.numpy(), want_status)
            assert count.numpy()[0] == want_count
        gated = wp.zeros(1, dtype=int, device=device)
        _launch(device_counts.gated_count, 1, [_count(total, device), status_on_device, gated], device)
        assert gated.numpy()[0] == counts_twin.gated_count(total, want_status)
    assert counts_twin.gated_count(7, [1, 0]) == 0 and counts_twin.gated_count(7, [0, 0]) == 7
    # An int64 total past an int's range: the status holds the largest int, and the count the capacity.
    status_on_device, count = wp.zeros(4, dtype=int, device=device), wp.zeros(1, dtype=int, device=device)
    _launch(device_counts.bounded_wide_count, 1, [wp.array([5 << 31], dtype=wp.int64, device=device), 9, 3, status_on_device, count], device)
    want_status, want_count = counts_twin.bounded_wide_count(5 << 31, 9, 3, np.zeros(4, np.int32))
    np.testing.assert_array_equal(status_on_device.numpy(), want_status)
    assert count.numpy()[0] == want_count == 9


@pytest.mark.parametrize("dempster", [False, True])
def test_release_kernels(device, dempster):
    rng = np.random.default_rng(int(dempster))
    n = 1500
    points = rng.uniform(-4, 4, (n, 3)).astype(np.float32)
    points[:20] = np.round(points[:20] / np.float32(0.5)) * np.float32(0.5)  # on the ds lines
    lo, hi = points.min(axis=0), points.max(axis=0)
    keys = wp.empty((n, 3), dtype=wp.int64, device=device)
    _launch(release.snapped_block_keys, n, [_a(points, wp.vec3, device), wp.vec3(*lo.tolist()), wp.vec3(*hi.tolist()), 0.5, 0.4000000059604645, keys], device)
    want_keys = release_twin.snapped_block_keys(points, lo, hi, 0.5, np.float64(np.float32(0.4)))
    np.testing.assert_array_equal(keys.numpy(), want_keys)
    position = (want_keys - want_keys.min(axis=0)) @ np.array([10_000, 100, 1])
    order = np.argsort(position, kind="stable")
    sorted_position = position[order]
    heads = np.r_[True, sorted_position[1:] != sorted_position[:-1]]
    run_rank = np.cumsum(heads).astype(np.int32)
    starts = np.r_[np.flatnonzero(heads), n]
    keep = wp.empty(n, dtype=int, device=device)
    _launch(release.keep_first_sorted, n, [_a(order, wp.int64, device), _a(run_rank, wp.int32, device), _a(starts, wp.int64, device), 3, keep], device)
    want_keep = release_twin.keep_first_sorted(order, run_rank, starts, 3)
    np.testing.assert_array_equal(keep.numpy(), want_keep)
    assert 0 < want_keep.sum() < n
    slot = np.cumsum(want_keep).astype(np.int32)
    kept = wp.empty(int(slot[-1]), dtype=int, device=device)
    _launch(release.compact_indices, n, [keep, _a(slot, wp.int32, device), kept], device)
    np.testing.assert_array_equal(kept.numpy(), release_twin.compact_indices(want_keep))
    taken = wp.zeros(kept.shape[0] + EXTRA, dtype=wp.vec3, device=device)
    _launch(release.take_points, kept.shape[0] + EXTRA, [_a(points, wp.vec3, device), _a(np.r_[kept.numpy(), np.full(EXTRA, 10**9)], wp.int32, device),
                                                         _count(kept.shape[0], device), taken], device)
    np.testing.assert_array_equal(taken.numpy()[:kept.shape[0]], release_twin.take_points(points, kept.numpy()))
    probabilities = rng.dirichlet(np.ones(9), n)
    uncertainty = rng.uniform(0, 1, n)
    pair_ids = rng.integers(0, kept.shape[0], 3000).astype(np.int64)
    pair_order = np.r_[rng.permutation(3000), np.full(EXTRA, 10**9)].astype(np.int64)  # past the count: never read
    room = 3000 + EXTRA
    out = (wp.empty(room, dtype=wp.vec3, device=device), wp.empty(room, dtype=release.vector_type(9), device=device), wp.empty(room, dtype=wp.float64, device=device))
    _launch(release.sorted_rows_kernel(9, dempster), room, [_a(points, wp.vec3, device), _a(probabilities, wp.float64, device), _a(uncertainty, wp.float64, device),
                                                         kept, _a(pair_ids, wp.int64, device), _a(pair_order, wp.int64, device), _count(3000, device), *out], device)
    for got, want in zip(out, release_twin.sorted_rows(points, probabilities, uncertainty, kept.numpy(), pair_ids, pair_order[:3000], dempster=dempster)):
        np.testing.assert_array_equal(got.numpy()[:3000].reshape(want.shape), want)

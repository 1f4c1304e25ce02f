"""Each kernel of the compatibility modes' parallel preprocessing (``methods.sbki_device``,
``methods.release_device``) against its numpy twin, on random inputs with the edge cases: one element,
values on cell and block faces, far coordinates, runs of equal keys (collisions)."""

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


@pytest.mark.parametrize("n", [1, 7, 3000])
def test_leaf_runs_starts_and_majority(device, n):
    rng = np.random.default_rng(n)
    sorted_leaf = np.sort(rng.integers(0, max(2, n // 4), n)).astype(np.int64)
    heads = wp.empty(n, dtype=int, device=device)
    _launch(voxel_grid.leaf_runs, n, [_a(sorted_leaf, wp.int64, device), heads], device)
    np.testing.assert_array_equal(heads.numpy(), voxel_grid_twin.leaf_runs(sorted_leaf))
    rank = np.cumsum(heads.numpy()).astype(np.int32)
    leaves = int(rank[-1])
    starts = wp.empty(leaves + 1, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_starts, n, [_a(rank, wp.int32, device), starts], device)
    np.testing.assert_array_equal(starts.numpy(), voxel_grid_twin.leaf_starts(rank))
    labels = rng.integers(-2, 3, n).astype(np.int64)
    order = rng.permutation(n).astype(np.int64)
    keys, positions = wp.empty(n, dtype=wp.int64, device=device), wp.empty(n, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_label_keys, n, [_a(order, wp.int64, device), _a(rank, wp.int32, device), _a(labels, wp.int64, device), -2, 5, keys, positions], device)
    want_keys, want_positions = voxel_grid_twin.leaf_label_keys(order, rank, labels, -2, 5)
    np.testing.assert_array_equal(keys.numpy(), want_keys)
    np.testing.assert_array_equal(positions.numpy(), want_positions)
    sorted_keys = np.sort(want_keys)
    majority = wp.empty(leaves, dtype=wp.int64, device=device)
    _launch(voxel_grid.leaf_majority_labels, leaves, [_a(sorted_keys, wp.int64, device), starts, leaves, -2, 5, majority], device)
    np.testing.assert_array_equal(majority.numpy(), voxel_grid_twin.leaf_majority_labels(sorted_keys, starts.numpy(), leaves, -2, 5))
    points = (rng.normal(size=(n, 3)) * 50 + 40_000).astype(np.float32)
    centroids = wp.empty(leaves, dtype=wp.vec3, device=device)
    _launch(voxel_grid.leaf_centroids_parallel, leaves, [_a(points, wp.vec3, device), _a(order, wp.int64, device), starts, leaves, centroids], device)
    np.testing.assert_array_equal(centroids.numpy(), voxel_grid_twin.leaf_centroids_parallel(points, order, starts.numpy(), leaves))
    lowest, highest = wp.full(3, np.inf, dtype=wp.float32, device=device), wp.full(3, -np.inf, dtype=wp.float32, device=device)
    _launch(voxel_grid.point_bounds, n, [_a(points, wp.vec3, device), lowest, highest], device)
    want_low, want_high = voxel_grid_twin.point_bounds(points)
    np.testing.assert_array_equal(lowest.numpy(), want_low)
    np.testing.assert_array_equal(highest.numpy(), want_high)
    values = wp.empty(n, dtype=wp.int64, device=device)
    _launch(voxel_grid.positions, n, [values], device)
    np.testing.assert_array_equal(values.numpy(), voxel_grid_twin.positions(n))


@pytest.mark.parametrize("n", [1, 500])
def test_ray_kernels(device, n):
    rng = np.random.default_rng(n)
    origin = np.array([3.25, -1.5, 1.2], np.float32)
    hits = (origin + rng.normal(size=(n, 3)) * 8).astype(np.float32)
    hits[0] = origin + np.float32(0.5)  # on a step
    if n > 2:
        hits[1] = origin  # a zero ray
    direction, ray_length = wp.empty(n, dtype=wp.vec3, device=device), wp.empty(n, dtype=wp.float32, device=device)
    _launch(free_space.ray_geometry, n, [_a(hits, wp.vec3, device), wp.vec3(*origin.tolist()), direction, ray_length], device)
    want_direction, want_length = free_space_twin.ray_geometry(hits, origin)
    np.testing.assert_array_equal(direction.numpy(), want_direction)
    np.testing.assert_array_equal(ray_length.numpy(), want_length)
    steps = np.cumsum(np.full(int(want_length.max() / 0.5) + 2, np.float32(0.5)), dtype=np.float32)
    per_hit, rows = wp.empty(n, dtype=int, device=device), wp.empty(n, dtype=int, device=device)
    _launch(free_space.samples_per_ray, n, [ray_length, _a(steps, wp.float32, device), 0.5, per_hit, rows], device)
    want_per_hit, want_rows = free_space_twin.samples_per_ray(want_length, steps, 0.5)
    np.testing.assert_array_equal(per_hit.numpy(), want_per_hit)
    np.testing.assert_array_equal(rows.numpy(), want_rows)
    keep = wp.empty(n, dtype=int, device=device)
    _launch(free_space.within_range, n, [ray_length, 8.0, keep], device)
    np.testing.assert_array_equal(keep.numpy(), free_space_twin.within_range(want_length, 8.0))
    slot = np.cumsum(keep.numpy()).astype(np.int32)
    labels = rng.integers(0, 5, n).astype(np.int64)
    kept = int(slot[-1])
    out = [wp.empty(kept, dtype=t, device=device) for t in (wp.vec3, wp.int64, wp.vec3, wp.float32)]
    _launch(free_space.compact_rays, n, [keep, _a(slot, wp.int32, device), _a(hits, wp.vec3, device), _a(labels, wp.int64, device), direction, ray_length, *out], device)
    for got, want in zip(out, free_space_twin.compact_rays(keep.numpy(), slot, hits, labels, want_direction, want_length)):
        np.testing.assert_array_equal(got.numpy(), want)
    longest = wp.zeros(1, dtype=wp.float32, device=device)
    _launch(free_space.longest_ray, n, [ray_length, longest], device)
    assert longest.numpy()[0] == free_space_twin.longest_ray(want_length)


@pytest.mark.parametrize("n", [1, 2000])
def test_membership_kernels(device, n):
    rng = np.random.default_rng(n)
    size = np.float32(0.4)
    points = (rng.uniform(-3, 3, (n, 3))).astype(np.float32)
    points[: n // 4] = np.round(points[: n // 4] / size) * size + size / np.float32(2)  # on block faces, edges, corners
    if n > 10:
        points[-5:] += np.float32(70_000)
    nearest, masks, counts = wp.empty((n, 3), dtype=wp.int64, device=device), wp.empty(n, dtype=int, device=device), wp.empty(n, dtype=int, device=device)
    _launch(block_membership.membership_masks_parallel, n, [_a(points, wp.vec3, device), float(size), nearest, masks, counts], device)
    want_nearest, want_masks, want_counts = membership_twin.membership_masks_parallel(points, size)
    np.testing.assert_array_equal(nearest.numpy(), want_nearest)
    np.testing.assert_array_equal(masks.numpy(), want_masks)
    np.testing.assert_array_equal(counts.numpy(), want_counts)
    first = np.r_[0, np.cumsum(want_counts)[:-1]].astype(np.int32)
    pairs = int(want_counts.sum())
    bits, ids = wp.empty(pairs, dtype=wp.int64, device=device), wp.empty(pairs, dtype=wp.int64, device=device)
    _launch(block_membership.membership_pairs_by_point, n, [masks, _a(first, wp.int32, device), bits, ids], device)
    want_bits, want_ids = membership_twin.membership_pairs_by_point(want_masks, first)
    np.testing.assert_array_equal(bits.numpy(), want_bits)
    np.testing.assert_array_equal(ids.numpy(), want_ids)
    assert pairs > n or n == 1  # face points belong to several blocks
    blocks = wp.empty((pairs, 3), dtype=wp.int64, device=device)
    _launch(block_membership.membership_blocks, pairs, [bits, ids, nearest, blocks], device)
    np.testing.assert_array_equal(blocks.numpy(), membership_twin.membership_blocks(want_bits, want_ids, want_nearest))


def test_block_table_kernels(device):
    rng = np.random.default_rng(9)
    member = rng.integers(-6, 6, (400, 3)).astype(np.int64)
    member[:50] = member[50]  # one block many times
    lowest, highest = wp.full(3, np.iinfo(np.int64).max, dtype=wp.int64, device=device), wp.full(3, np.iinfo(np.int64).min, dtype=wp.int64, device=device)
    _launch(block_gather.block_bounds, len(member), [_a(member, wp.int64, device), lowest, highest], device)
    lo, hi = block_gather_twin.block_bounds(member)
    np.testing.assert_array_equal(lowest.numpy(), lo)
    np.testing.assert_array_equal(highest.numpy(), hi)
    span = hi - lo + 1
    positions, index = wp.empty(len(member), dtype=wp.int64, device=device), wp.empty(len(member), dtype=wp.int64, device=device)
    _launch(block_gather.box_positions, len(member), [_a(member, wp.int64, device), wp.vec3l(*lo.tolist()), int(span[1]), int(span[2]), positions, index], device)
    want_positions, want_index = block_gather_twin.box_positions(member, lo, int(span[1]), int(span[2]))
    np.testing.assert_array_equal(positions.numpy(), want_positions)
    np.testing.assert_array_equal(index.numpy(), want_index)
    order = np.argsort(want_positions, kind="stable")
    sorted_positions = want_positions[order]
    starts = np.r_[np.flatnonzero(np.r_[True, sorted_positions[1:] != sorted_positions[:-1]]), len(order)]
    corner = lo - 3
    shape = tuple(int(x) for x in hi + 4 - corner)
    count = len(starts) - 1
    blocks, grid_blocks, grid = wp.empty(count, dtype=wp.vec3i, device=device), wp.empty(count, dtype=wp.vec3i, device=device), wp.full(shape, -1, dtype=int, device=device)
    _launch(block_gather.distinct_blocks, count, [_a(member, wp.int64, device), _a(order, wp.int64, device), _a(starts, wp.int64, device),
                                                  wp.vec3l(*corner.tolist()), blocks, grid_blocks, grid], device)
    want_blocks, want_grid_blocks, want_grid = block_gather_twin.distinct_blocks(member, order, starts, corner, shape)
    np.testing.assert_array_equal(blocks.numpy(), want_blocks)
    np.testing.assert_array_equal(grid_blocks.numpy(), want_grid_blocks)
    np.testing.assert_array_equal(grid.numpy(), want_grid)
    offsets = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.int32)
    marked = wp.zeros(int(np.prod(shape)), dtype=int, device=device)
    _launch(block_gather.mark_test_blocks, (count, 7), [grid_blocks, _a(offsets, wp.vec3i, device), grid, marked], device)
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
    ids = rng.integers(0, 100, len(member)).astype(np.int64)
    scaled, sorted_labels = wp.empty(len(member), dtype=wp.vec3, device=device), wp.empty(len(member), dtype=int, device=device)
    _launch(block_gather.sorted_block_points, len(member), [_a(points, wp.vec3, device), _a(labels, wp.int64, device), _a(ids, wp.int64, device),
                                                            _a(order, wp.int64, device), 0.3, scaled, sorted_labels], device)
    want_scaled, want_labels = block_gather_twin.sorted_block_points(points, labels, ids, order, 0.3)
    np.testing.assert_array_equal(scaled.numpy(), want_scaled)
    np.testing.assert_array_equal(sorted_labels.numpy(), want_labels)
    narrow = wp.empty(len(starts), dtype=int, device=device)
    _launch(block_gather.narrow_starts, len(starts), [_a(starts, wp.int64, device), narrow], device)
    np.testing.assert_array_equal(narrow.numpy(), block_gather_twin.narrow_starts(starts))


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
    taken = wp.empty(kept.shape[0], dtype=wp.vec3, device=device)
    _launch(release.take_points, kept.shape[0], [_a(points, wp.vec3, device), kept, taken], device)
    np.testing.assert_array_equal(taken.numpy(), release_twin.take_points(points, kept.numpy()))
    probabilities = rng.dirichlet(np.ones(9), n)
    uncertainty = rng.uniform(0, 1, n)
    pair_ids = rng.integers(0, kept.shape[0], 3000).astype(np.int64)
    pair_order = rng.permutation(3000).astype(np.int64)
    out = (wp.empty(3000, dtype=wp.vec3, device=device), wp.empty(3000, dtype=release.vector_type(9), device=device), wp.empty(3000, dtype=wp.float64, device=device))
    _launch(release.sorted_rows_kernel(9, dempster), 3000, [_a(points, wp.vec3, device), _a(probabilities, wp.float64, device), _a(uncertainty, wp.float64, device),
                                                         kept, _a(pair_ids, wp.int64, device), _a(pair_order, wp.int64, device), *out], device)
    for got, want in zip(out, release_twin.sorted_rows(points, probabilities, uncertainty, kept.numpy(), pair_ids, pair_order, dempster=dempster)):
        np.testing.assert_array_equal(got.numpy().reshape(want.shape), want)

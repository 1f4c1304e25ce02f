"""The scatter kernel against its numpy twin, on random inputs and edge cases.

Tagged boundary band (style recommendation 3): in radius mode, a (point, voxel) pair with
|d - l| < 1e-5 l can fall either side of the strict d < l test in float32 vs float64; only voxels
reached exclusively by such pairs may be missing from one side, with a kernel weight ~0.
"""

import dataclasses

import numpy as np
import pytest
import warp as wp

from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.reference import scatter as ref
from evsemmap_warp.core.integrators.convbki import scatter_stencil
from evsemmap_warp.core.integrators.sbki import insert_blocks
from evsemmap_warp.core.integrators.scatter import scatter
from evsemmap_warp.core.voxel_map import VoxelMap

MODES = {"radius": sc.MODE_RADIUS, "own_voxel": sc.MODE_OWN_VOXEL}


def _run(points, lengths, unc, *, mode, k, device, labels=None, weights=None, res=0.2, sigma0=1.0, capacity=1 << 12, offset=0.0):
    vm = VoxelMap(k, res, device=device, initial_capacity=capacity, grid_offset_m=offset)
    updates = scatter(vm, points, lengths, unc, mode=mode, sigma0=sigma0, reach=float(np.max(lengths, initial=0.0)), labels=labels, class_weights=weights)
    return vm, updates


def _compare(vm, updates, expected: ref.ScatterResult, atol=2e-5):
    got = vm.arrays()
    assert vm.voxel_count == len(got.index)
    np.testing.assert_array_equal(got.index, expected.voxel_index)
    np.testing.assert_allclose(got.evidence, expected.alpha_increment, rtol=2e-5, atol=atol)
    np.testing.assert_allclose(got.weight_sum, expected.weight_sum, rtol=2e-5, atol=atol)
    np.testing.assert_allclose(got.weighted_uncertainty_sum, expected.weighted_uncertainty_sum, rtol=2e-5, atol=atol)
    np.testing.assert_array_equal(got.hits, expected.hits)
    np.testing.assert_allclose(got.weighted_height_sum, expected.weighted_height_sum, rtol=2e-5, atol=atol)
    assert got.touched.all()
    assert updates == expected.update_count


def _random_scan(rng, n, k, spread=3.0):
    pts = rng.uniform(-spread, spread, (n, 3)).astype(np.float32).astype(np.float64)
    weights = rng.dirichlet(np.ones(k), n)
    labels = rng.integers(0, k, n)
    lengths = rng.uniform(0.05, 0.5, n).astype(np.float32).astype(np.float64)
    unc = rng.uniform(0, 1, n)
    return pts, weights, labels, lengths, unc


def _away_from_boundaries(pts, lengths, res):
    """Drop points with any voxel center within 1e-4 of their kernel length (the tagged band)."""
    keep = np.ones(len(pts), bool)
    for i, (p, l) in enumerate(zip(pts, lengths)):
        lo = np.floor((p - l) / res).astype(int)
        hi = np.floor((p + l) / res).astype(int)
        grid = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
        d = np.linalg.norm((grid + 0.5) * res - p, axis=1)
        keep[i] = np.abs(d - l).min() > 1e-4
    return keep


@pytest.mark.parametrize("k", [2, 9, 20])
@pytest.mark.parametrize("media", ["labels", "weights"])
def test_radius_mode_matches_reference(device, k, media):
    rng = np.random.default_rng(k + len(media))
    pts, weights, labels, lengths, unc = _random_scan(rng, 1500, k)
    keep = _away_from_boundaries(pts, lengths, 0.2)
    pts, weights, labels, lengths, unc = pts[keep], weights[keep], labels[keep], lengths[keep], unc[keep]
    kw = {"labels": labels} if media == "labels" else {"weights": weights}
    vm, updates = _run(pts, lengths, unc, mode=sc.MODE_RADIUS, k=k, device=device, **kw)
    expected = ref.scatter_points(pts, kw.get("labels"), kw.get("weights"), lengths, unc, None, sc.MODE_RADIUS, 0.2, 0.0, 1.0, 1, k)
    _compare(vm, updates, expected)


def test_own_voxel_mode_matches_reference(device):
    rng = np.random.default_rng(5)
    pts, weights, labels, lengths, unc = _random_scan(rng, 3000, 4)
    vm, updates = _run(pts, lengths, unc, mode=sc.MODE_OWN_VOXEL, k=4, device=device, labels=labels)
    _compare(vm, updates, ref.scatter_points(pts, labels, None, lengths, unc, None, sc.MODE_OWN_VOXEL, 0.2, 0.0, 1.0, 1, 4))


def test_boundary_band_is_the_only_disagreement():
    rng = np.random.default_rng(11)
    pts, weights, labels, lengths, unc = _random_scan(rng, 3000, 3)
    vm, _ = _run(pts, lengths, unc, mode=sc.MODE_RADIUS, k=3, device="cpu", weights=weights)
    expected = ref.scatter_points(pts, None, weights, lengths, unc, None, sc.MODE_RADIUS, 0.2, 0.0, 1.0, 1, 3)
    got = vm.arrays()
    got_set = {tuple(v) for v in got.index}
    ref_set = {tuple(v) for v in expected.voxel_index}
    only = got_set ^ ref_set
    assert len(only) <= 3, f"{len(only)} voxels differ; only the tagged d ~ l band may"
    for v in only:  # each such voxel is within the band of some point and carries ~0 weight
        d = np.linalg.norm((np.array(v) + 0.5) * 0.2 - pts, axis=1)
        assert np.abs(d - lengths).min() < 1e-5 * lengths.max()
    common = [i for i, v in enumerate(map(tuple, got.index)) if v in ref_set]
    ref_rows = {v: i for i, v in enumerate(map(tuple, expected.voxel_index))}
    rows = [ref_rows[tuple(got.index[i])] for i in common]
    np.testing.assert_allclose(got.evidence[common], expected.alpha_increment[rows], rtol=2e-5, atol=2e-5)


def test_empty_and_single_point(device):
    vm, updates = _run(np.zeros((0, 3)), np.zeros(0), np.zeros(0), mode=sc.MODE_RADIUS, k=3, device=device, labels=np.zeros(0, int))
    assert updates == 0 and vm.voxel_count == 0
    # One point at a voxel center with l = 0.15 < r: exactly its own voxel, weight sigma0.
    p = np.array([[0.1, 0.1, 0.1]])
    vm, updates = _run(p, np.array([0.15]), np.array([0.25]), mode=sc.MODE_RADIUS, k=3, device=device, labels=np.array([2]), sigma0=2.0)
    a = vm.arrays()
    np.testing.assert_array_equal(a.index, [[0, 0, 0]])
    np.testing.assert_allclose(a.evidence, [[0, 0, 2.0]], atol=1e-6)
    np.testing.assert_allclose(a.weighted_uncertainty_sum, [0.5], atol=1e-6)
    assert updates == 1


def test_points_exactly_on_voxel_faces(device):
    # x = 0.2 lies on the face between voxels 0 and 1; floor puts it in voxel 1 (half-open cells).
    pts = np.array([[0.2, 0.0, 0.0], [0.0, 0.4, 0.2], [-0.2, -0.2, -0.2]])
    labels = np.array([1, 2, 0])
    vm, _ = _run(pts, np.full(3, 0.2), np.zeros(3), mode=sc.MODE_OWN_VOXEL, k=3, device=device, labels=labels)
    np.testing.assert_array_equal(vm.arrays().index, [[-1, -1, -1], [0, 2, 1], [1, 0, 0]])
    # Radius mode: a point on the x-face between voxels (0,0,0) and (1,0,0), level with their
    # centers, is 0.1 m from both and farther from every other center: both get the same weight.
    p = np.array([[0.2, 0.1, 0.1]])
    vm, _ = _run(p, np.array([0.1001]), np.zeros(1), mode=sc.MODE_RADIUS, k=3, device=device, labels=np.array([1]))
    got = vm.arrays()
    np.testing.assert_array_equal(got.index, [[0, 0, 0], [1, 0, 0]])
    w = ref.sparse_kernel(np.array([0.1]), np.array([0.1001]), 1.0)[0]
    # The two centers differ in float32 (0.1 vs 0.3), so t = 1 - d/l differs by ~1e-7 / 1e-3.
    np.testing.assert_allclose(got.evidence[:, 1], [w, w], rtol=2e-3)


def test_growth_during_one_launch_loses_nothing(device):
    rng = np.random.default_rng(2)
    pts, weights, labels, lengths, unc = _random_scan(rng, 2000, 5, spread=6.0)
    keep = _away_from_boundaries(pts, lengths, 0.2)
    pts, weights, lengths, unc = pts[keep], weights[keep], lengths[keep], unc[keep]
    vm, updates = _run(pts, lengths, unc, mode=sc.MODE_RADIUS, k=5, device=device, weights=weights, capacity=16)
    assert vm.grow_count >= 5, "a 16-slot table must grow repeatedly inside the launch"
    _compare(vm, updates, ref.scatter_points(pts, None, weights, lengths, unc, None, sc.MODE_RADIUS, 0.2, 0.0, 1.0, 1, 5))


@wp.func
def _insert_pass_first(scan: sc.ScanPoints, params: sc.ScatterParams, out: sc.MapTarget, t: int, i: int, span: sc.Span) -> int:
    out.failed[t] = 0  # a relaunched point had added nothing
    return -1


def _two_pass_scatter(mode, fusion, use_labels):
    """The clean scatter as it was: every point runs its insert pass before it adds."""
    reach, rule, _ = sc.SCATTER_MODES[mode]
    visit = sc.scatter_visit(rule, sc._evidence_rule(mode, fusion, use_labels), inserts=True, heights=True)
    return sc.walk_kernel(reach, dataclasses.replace(visit, plan=_insert_pass_first), module="unique")


@pytest.mark.parametrize("capacity", [16, 1 << 17])
@pytest.mark.parametrize("mode", [sc.MODE_RADIUS, sc.MODE_STENCIL])
def test_one_pass_points_map_as_two_passes_bit_for_bit(monkeypatch, capacity, mode):
    """A CPU launch runs its threads in order, so a point that found room for its span cannot fail:
    the map (rows, sums, their order) is the two-pass scatter's, with growth (16 slots) or without."""
    rng = np.random.default_rng(5)
    pts, weights, labels, lengths, unc = _random_scan(rng, 1500, 5)
    stencil = rng.uniform(0.0, 1.0, (27, 5)) if mode == sc.MODE_STENCIL else None

    def run():
        vm = VoxelMap(5, 0.2, device="cpu", initial_capacity=capacity)
        if mode == sc.MODE_STENCIL:
            return vm, scatter_stencil(vm, pts, lengths, unc, weights, stencil)
        updates = scatter(vm, pts, lengths, unc, mode=mode, sigma0=1.0, reach=float(np.max(lengths)), class_weights=weights)
        return vm, updates

    one_pass, one_pass_updates = run()
    monkeypatch.setattr(sc, "scatter_kernel", _two_pass_scatter)
    two_pass, two_pass_updates = run()
    assert one_pass_updates == two_pass_updates and one_pass.grow_count == two_pass.grow_count
    assert (one_pass.grow_count > 0) == (capacity == 16)
    np.testing.assert_array_equal(one_pass.keys.numpy(), two_pass.keys.numpy())
    np.testing.assert_array_equal(one_pass.data.numpy()[:one_pass.voxel_count], two_pass.data.numpy()[:two_pass.voxel_count])


def test_points_stopped_in_their_adding_pass_resume_where_they_stopped(device, overfill_next_launch):
    """On a GPU other points may take the room a point saw before it inserts; it then stops part way
    through its adding pass and its relaunch resumes after the voxels it had added. Forced here
    (``overfill_next_launch``) on a second scan, wider than the first so that its points reach voxels
    held and new ones: the relaunch must land every (point, voxel) exactly once."""
    rng = np.random.default_rng(6)
    scans = [_random_scan(rng, n, 4, spread=spread) for n, spread in ((300, 2.0), (1500, 4.0))]
    pts, weights, _, lengths, unc = (np.concatenate(arrays) for arrays in zip(*scans))
    keep = _away_from_boundaries(pts, lengths, 0.2)
    pts, weights, lengths, unc = pts[keep], weights[keep], lengths[keep], unc[keep]
    first, second = slice(0, int(keep[:300].sum())), slice(int(keep[:300].sum()), None)
    vm = VoxelMap(4, 0.2, device=device, initial_capacity=16)
    updates = scatter(vm, pts[first], lengths[first], unc[first], mode=sc.MODE_RADIUS, sigma0=1.0, reach=float(lengths.max()),
                      class_weights=weights[first])
    resumed_after, launches = overfill_next_launch()
    updates += scatter(vm, pts[second], lengths[second], unc[second], mode=sc.MODE_RADIUS, sigma0=1.0, reach=float(lengths.max()),
                       class_weights=weights[second])
    assert len(launches) >= 2 and np.count_nonzero(np.array(resumed_after) > 0) >= 20, "points must stop part way and be relaunched"
    _compare(vm, updates, ref.scatter_points(pts, None, weights, lengths, unc, None, sc.MODE_RADIUS, 0.2, 0.0, 1.0, 1, 4))


def test_cpu_results_are_bit_identical_run_to_run():
    rng = np.random.default_rng(4)
    pts, weights, labels, lengths, unc = _random_scan(rng, 3000, 6)
    runs = [_run(pts, lengths, unc, mode=sc.MODE_RADIUS, k=6, device="cpu", weights=weights, capacity=64)[0].arrays() for _ in range(2)]
    for field in ("index", "evidence", "weight_sum", "weighted_uncertainty_sum", "hits", "touched"):
        np.testing.assert_array_equal(getattr(runs[0], field), getattr(runs[1], field))


def test_total_evidence_equals_total_kernel_weight(device):
    rng = np.random.default_rng(9)
    pts, weights, labels, lengths, unc = _random_scan(rng, 1000, 7)
    vm, _ = _run(pts, lengths, unc, mode=sc.MODE_RADIUS, k=7, device=device, weights=weights)
    a = vm.arrays()
    np.testing.assert_allclose(a.evidence.sum(), a.weight_sum.sum(), rtol=1e-5)


def test_permuting_points_leaves_the_map_unchanged(device):
    rng = np.random.default_rng(10)
    pts, weights, labels, lengths, unc = _random_scan(rng, 2000, 4)
    a = _run(pts, lengths, unc, mode=sc.MODE_RADIUS, k=4, device=device, weights=weights)[0].arrays()
    perm = rng.permutation(len(pts))
    b = _run(pts[perm], lengths[perm], unc[perm], mode=sc.MODE_RADIUS, k=4, device=device, weights=weights[perm])[0].arrays()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-5, atol=1e-6)


def test_sbki_modes_match_reference_on_random_owners(device):
    rng = np.random.default_rng(12)
    n = 800
    pts = rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32).astype(np.float64)
    labels = rng.integers(0, 4, n)
    # Owner block by rounding (block 0.4 m = 4 cells of 0.1 m), as block_memberships assigns it.
    owners = np.floor(pts / 0.4 + 0.5).astype(np.int64)
    vm = VoxelMap(4, 0.1, device=device, initial_capacity=64)
    ext = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    blocks = np.unique((np.unique(owners, axis=0)[:, None] + ext[None]).reshape(-1, 3), axis=0)
    insert_blocks(vm, blocks, 4, mark_touched=True)
    updates = scatter(vm, pts, np.full(n, 0.3), np.zeros(n), mode=sc.MODE_SBKI_BLOCKS, sigma0=10.0, reach=0.3 * sc.SBKI_REACH_FACTOR, labels=labels,
                      owner_blocks=owners, cells_per_block=4)
    expected = ref.scatter_points(pts, labels, None, np.full(n, 0.3), np.zeros(n), owners, sc.MODE_SBKI_BLOCKS, 0.1, 0.0, 10.0, 4, 4)
    got = vm.arrays()
    assert len(got.index) == len(blocks) * 64
    rows = {tuple(v): i for i, v in enumerate(got.index)}
    idx = [rows[tuple(v)] for v in expected.voxel_index]
    np.testing.assert_allclose(got.evidence[idx], expected.alpha_increment, rtol=1e-4, atol=1e-5)
    # Tagged band: at d ~ ell the C++-style float32 kernel is rounding noise (< 1e-6 sigma0), and
    # Warp's and numpy's float32 sin/cos round differently there; only such cells may disagree.
    untouched = np.ones(len(got.index), bool)
    untouched[idx] = False
    noise = got.evidence[untouched].sum(axis=1)
    assert noise.max() < 1e-6 * 10.0 and (noise > 0).sum() <= 0.001 * len(expected.voxel_index)
    assert got.touched.all()
    assert abs(updates - expected.update_count) <= 0.001 * expected.update_count


def test_sincos_float32_is_the_correctly_rounded_sine_and_cosine(device):
    import warp as wp

    @wp.kernel(enable_backward=False)
    def evaluate(a: wp.array(dtype=float), out: wp.array(dtype=wp.vec2)):
        t = wp.tid()
        out[t] = sc.sincos_float32(a[t])

    rng = np.random.default_rng(5)
    # The S-BKI range (2 pi d for d up to the 1.05 reach), wider arguments, negatives, and the
    # float32 neighbours of multiples of pi / 2 (where the reduction cancels most).
    multiples = np.float32(np.arange(-8, 200) * np.pi / 2)
    a = np.concatenate([rng.uniform(0, 7, 400_000), rng.uniform(-300, 300, 100_000), [0.0, -0.0, 1e-30, 1e-7],
                        multiples, np.nextafter(multiples, np.float32(np.inf)), np.nextafter(multiples, np.float32(-np.inf))]).astype(np.float32)
    out = wp.empty(len(a), dtype=wp.vec2, device=device)
    wp.launch(evaluate, dim=len(a), inputs=[wp.array(a, dtype=float, device=device), out], device=device)
    got = out.numpy()
    want_sin, want_cos = ref.sincos_float32(a)
    exact = np.stack([np.sin(a.astype(np.float64)), np.cos(a.astype(np.float64))], 1)
    error_ulps = np.abs(got - exact) / np.spacing(np.abs(exact).astype(np.float32))
    assert error_ulps.max() < 0.5 + 1e-3  # at worst a near-halfway case rounded the other way
    assert (got[:, 0] == want_sin).mean() > 0.99999 and (got[:, 1] == want_cos).mean() > 0.99999
    np.testing.assert_array_equal(got[500_000:500_004], np.float32([[0, 1], [-0.0, 1], [1e-30, 1], [1e-7, 1]]))


def test_sparse_kernel_is_accurate_near_the_support_edge():
    # Evaluate the Warp kernel through a one-point scatter at controlled distances and compare it
    # with float64 (where the closed form is accurate to ~1e-16): no float32 cancellation noise.
    length = 0.3
    for t in (0.3, 0.2, 0.05, 1e-2, 1e-3):
        d = length * (1 - t)
        p = np.array([[0.05 + d, 0.05, 0.05]])  # voxel (0,0,0) center is (0.05, 0.05, 0.05) at r = 0.1
        vm, _ = _run(p, np.array([length]), np.zeros(1), mode=sc.MODE_RADIUS, k=2, device="cpu", labels=np.array([1]), res=0.1)
        a = vm.arrays()
        row = np.flatnonzero((a.index == [0, 0, 0]).all(axis=1))[0]
        dist = np.linalg.norm(np.float32(0.05) - p.astype(np.float32))
        expected = ref.sparse_kernel(np.array([dist], dtype=np.float64), np.array([np.float32(length)], dtype=np.float64), 1.0)[0]
        # float32 t = 1 - d/l carries ~6e-8 absolute error, i.e. ~5 * 6e-8 / t relative in k'.
        np.testing.assert_allclose(a.evidence[row, 1], expected, rtol=max(1e-5, 5e-7 / t))


@pytest.mark.parametrize("cells_per_block", [1, 2, 4])
@pytest.mark.parametrize("mark_touched", [False, True])
def test_insert_block_cells_matches_reference(device, cells_per_block, mark_touched):
    rng = np.random.default_rng(cells_per_block)
    blocks = np.unique(rng.integers(-20, 20, (300, 3)), axis=0)
    vm = VoxelMap(3, 0.1, device=device, initial_capacity=16)  # grows during the insertion
    insert_blocks(vm, blocks, cells_per_block, mark_touched=mark_touched)
    insert_blocks(vm, blocks[:10], cells_per_block, mark_touched=mark_touched)  # idempotent
    expected = ref.insert_block_cells(blocks, cells_per_block)
    got = vm.arrays()
    np.testing.assert_array_equal(got.index, np.unique(expected, axis=0))
    assert len(got.index) == len(blocks) * cells_per_block**3 and vm.grow_count > 0
    assert (got.touched == mark_touched).all() and (got.evidence == 0).all() and (got.hits == 0).all()
    assert insert_blocks(vm, np.zeros((0, 3), int), 2, mark_touched=True) is None and vm.voxel_count == len(got.index)

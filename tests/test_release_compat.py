"""The release mode (mapping.compat: release, docs/compatibility.md §4): the released EvSemMap C++."""

import numpy as np
import pytest
from conftest import REPO, shared_path

from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core.integrators import ReleaseCompatIntegrator
from evsemmap_warp.core.mapper import Mapper, prepare_payload
from evsemmap_warp.methods import release_compat as er
from evsemmap_warp.reference.release import release_insert
from evsemmap_warp.voxel_keys import pack_voxel_keys, unpack_voxel_keys

PRESET = REPO / "configs/presets/release.yaml"


def _config(method: str, **overrides):
    return load_config([PRESET], method=method).mapping.replace(**overrides)


@pytest.mark.parametrize("offset", [0.0, 2.5e4])
def test_snapping_kernel_follows_the_cpp_loop_ties_and_the_last_line(offset):
    # Against the literal loop (the kernel's twin): random points, exact half-way ties, the box
    # minimum and maximum on every axis, far from zero; one point, and none.
    from evsemmap_warp.reference.release import snap_to_lines

    rng = np.random.default_rng(0)
    p = (rng.uniform(-3, 5, (2000, 3)) + offset).astype(np.float32)
    lo, hi, ds = p.min(axis=0), p.max(axis=0), np.float32(0.01)
    p[:20] = (lo + np.arange(20, dtype=np.float32)[:, None] * np.float32(0.005)).astype(np.float32)  # half-way ties
    p[20], p[21] = lo, hi
    for cloud in (p, p[21:22], p[:0]):
        np.testing.assert_array_equal(er.snapped_points(cloud, lo, hi, ds), snap_to_lines(cloud, lo, hi, ds))
    # Past the last line the loop ends without a stop and gives the maximum: a box whose extent ends
    # 0.75 ds past a line (the kernel's fallback after its three branch-free tests), and points above it.
    lo, hi = np.float32([offset] * 3), np.float32([offset + 0.0075, offset + 0.0475, offset + 0.0275])
    cloud = np.vstack([hi, hi - np.float32(0.001), hi + np.float32(0.02), lo]).astype(np.float32)
    want = snap_to_lines(cloud, lo, hi, ds)
    assert (want[:3] == hi).any(axis=1).all()
    np.testing.assert_array_equal(er.snapped_points(cloud, lo, hi, ds), want)


def test_block_cap_keeps_the_first_points_in_input_order():
    keys = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(er.first_per_block(keys, 2), [True, True, True, False, True, False])
    np.testing.assert_array_equal(er.first_per_block(keys[:0], 2), np.zeros(0, bool))


@pytest.mark.parametrize("spread", [3, 40, 1 << 18])
def test_block_cap_kernel_matches_its_twin(spread, monkeypatch):
    # Many points per block (dense counts), one point, none, and keys spread too wide for the dense
    # grid (counted over the distinct keys); the cap of the release's EBS and Dempster configs, and 1.
    from evsemmap_warp.reference.release import keep_first_per_block

    rng = np.random.default_rng(spread)
    keys = rng.integers(-spread, spread, (20000, 3)) + np.array([5, -7, 1 << 19])
    for cap in (1, 6, 11):
        for part in (keys, keys[:1], keys[:0]):
            np.testing.assert_array_equal(er.first_per_block(part, cap), keep_first_per_block(pack_voxel_keys(part), cap))
    if spread == 3:
        assert not er.first_per_block(keys, 11).all()  # the cap drops points


def test_uncertainty_cut_keeps_ties_at_the_float32_threshold():
    u = np.array([0.5, 0.1, 0.3, 0.3, 0.3, 0.9, 0.2, 0.4, 0.6, 0.7])
    keep, threshold = er.uncertainty_cut(u, 0.3)  # index int(10 * 0.3) = 3 of the ascending u: 0.3
    assert threshold == float(np.float32(0.3))
    # double 0.3 > float32(0.3)? float32(0.3) = 0.30000001192..., so the ties are kept
    np.testing.assert_array_equal(keep, u <= float(np.float32(0.3)))
    assert keep.sum() == 5
    assert er.uncertainty_cut(np.zeros(0), 0.9)[0].shape == (0,)


def _scan(rng, n, spread=1.6):
    pts = rng.uniform(0, spread, (n, 3)).astype(np.float32)
    pts[:6, 0] = np.float32(0.2)  # on the face between blocks 0 and 1 (block centers at 0.4 k)
    pts[6:10, 1] = np.float32(0.6)
    pts[10:12] = np.float32(0.2)  # on an edge and a corner
    alpha = np.ones((n, 5))
    alpha[np.arange(n), rng.integers(1, 5, n)] += rng.uniform(0, 30, n)
    alpha[np.arange(n), rng.integers(1, 5, n)] += rng.uniform(0, 5, n)
    return pts, alpha


@pytest.mark.parametrize("method", ["ebs", "dempster"])
@pytest.mark.parametrize("n", [1, 2, 150])
def test_gather_kernel_matches_the_literal_block_models(device, method, n):
    rng = np.random.default_rng(n)
    pts, alpha = _scan(rng, max(n, 12))
    pts, alpha = pts[:n] if n < 12 else pts, alpha[:n] if n < 12 else alpha
    cfg = _config(method, sbki={"ds_resolution_m": 0.01})
    mapper = Mapper(cfg, 5, device=device, origin=np.zeros(3))
    mapper.integrate(pts, alpha, payload_type="alpha")
    # the twin on the same training points (cut and cap from the integrator's own rule)
    payload = prepare_payload(pts, alpha, "alpha", 5)
    keep, _ = ReleaseCompatIntegrator(cfg).training_points(payload, np.zeros(3))
    weights = payload.probabilities[keep]
    if method == "dempster":
        weights = np.clip(weights - payload.uncertainty[keep, None] / 5, 0, 1)
    expected = release_insert(pts[keep], weights, payload.uncertainty[keep], resolution_m=0.2, block_depth=2,
                              length=er.kernel_length(0.3), sf2=1.0, dempster=method == "dempster")
    arrays, summary = mapper.voxels()
    assert {tuple(v) for v in arrays.index} == set(expected)
    want = np.array([expected[tuple(v)] for v in arrays.index])
    np.testing.assert_allclose(arrays.evidence, want[:, :5], rtol=2e-6, atol=1e-6)
    np.testing.assert_allclose(arrays.weight_sum, want[:, 5], rtol=2e-6, atol=1e-6)
    # Contributions are counted where the kernel is > 0: the C++'s float32 trig is noise around d = l, the
    # engine's polynomial exactly positive below it; the weights above agree, so the extra ones weigh ~0.
    assert (arrays.hits >= want[:, 7]).all() and (arrays.hits - want[:, 7]).sum() <= 0.05 * want[:, 7].sum()
    assert (summary.state == 2).all()  # no free-space samples: every cell is OCCUPIED


def test_blocks_out_of_the_brick_cache_are_found_cell_by_cell(device):
    # As in the S-BKI mode (tests/test_sbki_compat.py): blocks whose cells were inserted before, out of
    # cell order, are never cached; two scans give twice the twin's sums.
    rng = np.random.default_rng(8)
    pts, alpha = _scan(rng, 2000, spread=3.2)
    cfg = _config("ebs", sbki={"ds_resolution_m": 0.01})
    mapper = Mapper(cfg, 5, device=device, origin=np.zeros(3), workers=1)
    payload = prepare_payload(pts, alpha, "alpha", 5)
    keep, _ = ReleaseCompatIntegrator(cfg).training_points(payload, np.zeros(3))
    expected = release_insert(pts[keep], payload.probabilities[keep], payload.uncertainty[keep], resolution_m=0.2, block_depth=2,
                              length=er.kernel_length(0.3), sf2=1.0, dempster=False)
    cells = np.array(sorted(expected))
    first_cells = np.unique(cells - (cells % 2 == 0), axis=0)  # block b holds cells 2b - 1 and 2b per axis
    cell_offsets = np.array([[j // 4, (j // 2) % 2, j % 2] for j in range(8)])
    scrambled = first_cells[::5]
    for first in scrambled:
        mapper.shards[0].insert_voxels(first + cell_offsets[::-1])
    for _ in range(2):
        mapper.integrate(pts, alpha, payload_type="alpha")
    arrays, _ = mapper.voxels()
    assert {tuple(v) for v in arrays.index} == set(expected)
    want = np.array([expected[tuple(v)] for v in arrays.index])
    np.testing.assert_allclose(arrays.evidence, 2 * want[:, :5], rtol=2e-6, atol=1e-6)
    cached = mapper.shards[0].brick_keys.numpy()
    cached_first = {tuple(c) for c in unpack_voxel_keys(cached[cached != -1])}
    assert cached_first and not cached_first & {tuple(c) for c in scrambled}
    if device == "cpu":
        assert len(cached_first) == len(first_cells) - len(scrambled)


def test_a_point_weighs_7x_in_its_own_block_2x_in_face_and_edge_neighbours_0x_in_corners():
    faces = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    occupied = np.array([[0, 0, 0], *faces, [1, 1, 0], [1, 1, 1], [2, 0, 0]])
    models = er.release_blocks(occupied)
    offsets = {tuple(o): j for j, o in enumerate(er.TARGET_BLOCK_OFFSETS)}

    def mult(source, target):
        b = next(i for i, blk in enumerate(models.blocks) if tuple(blk) == tuple(target))
        o = offsets.get(tuple(np.subtract(source, target)))
        return 0 if o is None or models.source_blocks[b, o] < 0 else int(models.source_mult[b, o])

    assert mult([0, 0, 0], [0, 0, 0]) == 7  # its own model and the 6 face neighbours' models
    assert mult([0, 0, 0], [1, 0, 0]) == 2  # face neighbour: its model and the source's
    assert mult([0, 0, 0], [1, 1, 0]) == 2  # edge neighbour: through (1, 0, 0) and (0, 1, 0)
    assert mult([0, 0, 0], [1, 1, 1]) == 0  # corner neighbour: no model holds both
    assert mult([0, 0, 0], [2, 0, 0]) == 1  # two blocks along an axis: through (1, 0, 0) only
    assert mult([1, 1, 1], [1, 1, 0]) == 2  # a corner block's point still reaches its own face neighbours
    # the literal twin agrees: a point at the center block's center, alone vs with the others
    alone = release_insert(np.zeros((1, 3), np.float32), np.eye(3)[[1]], np.zeros(1), resolution_m=0.2, block_depth=2,
                           length=er.kernel_length(0.3), sf2=1.0, dempster=False)
    points = np.concatenate([[[0.0, 0.0, 0.0]], 0.4 * occupied[1:] + 0.15]).astype(np.float32)
    weights = np.eye(3)[[1] + [2] * (len(points) - 1)]
    together = release_insert(points, weights, np.zeros(len(points)), resolution_m=0.2, block_depth=2,
                              length=er.kernel_length(0.3), sf2=1.0, dempster=False)
    np.testing.assert_allclose(together[(0, 0, 0)][1], 7 * alone[(0, 0, 0)][1], rtol=1e-12)


@pytest.mark.parametrize("method", ["ebs", "dempster"])
def test_the_gather_kernel_without_prefetch_gives_the_same_map(method):
    import functools

    from evsemmap_warp.kernels import release

    rng = np.random.default_rng(6)
    pts, alpha = _scan(rng, 30000, spread=10.0)
    maps = []
    for prefetch in (True, False):
        mapper = Mapper(_config(method), 5, workers=1)
        mapper.integrator.gather_kernel = functools.partial(release.gather_release_kernel, prefetch=prefetch)
        mapper.integrate(pts, alpha, payload_type="alpha")
        maps.append(mapper.voxels()[0])
    assert maps[0].hits.sum() > 0
    np.testing.assert_array_equal(maps[0].index, maps[1].index)
    np.testing.assert_array_equal(maps[0].rows(), maps[1].rows())


def test_two_workers_give_the_one_worker_map_bit_for_bit():
    rng = np.random.default_rng(5)
    pts, alpha = _scan(rng, 40000, spread=12.0)
    maps = []
    for workers in (1, 2):
        mapper = Mapper(_config("ebs"), 5, workers=workers)
        mapper.integrate(pts, alpha, payload_type="alpha")
        mapper.integrate(pts[::-1] + np.float32(0.05), alpha[::-1], payload_type="alpha")
        maps.append(mapper)
    assert min(shard.voxel_count for shard in maps[1].shards) > 0
    (a, _), (b, _) = maps[0].voxels(), maps[1].voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_array_equal(a.rows(), b.rows())
    assert not a.weighted_height_sum.any()  # the release's rows: no heights kept


def test_refusals_name_the_key():
    with pytest.raises(ConfigError, match="mapping.media"):
        _config("s-bki")
    with pytest.raises(ConfigError, match="beta 1, gamma 0"):
        _config("ebs", gamma=10.0)
    with pytest.raises(ConfigError, match=r"mapping.release.ds_multiplier = -1: must be >= 0"):
        _config("ebs", release={"ds_multiplier": -1})
    mapper = Mapper(_config("ebs"), 3)
    with pytest.raises(ValueError, match="evidential alpha"):
        mapper.integrate(np.full((4, 3), 5000.0), np.ones(4, int), payload_type="label")
    assert mapper.origin_index is None and mapper.scans_integrated == 0  # the refused scan left no trace
    ranged = Mapper(_config("ebs", sbki={"max_range_m": 30.0}), 3)
    with pytest.raises(ValueError, match="range filter"):
        ranged.integrate(np.zeros((4, 3)), np.full((4, 3), 2.0), payload_type="alpha")


def test_block_cap_follows_the_fusion_unless_set():
    assert _config("ebs").release_block_cap == 11
    assert _config("dempster").release_block_cap == 6
    assert _config("ebs", release={"ds_multiplier": 0}).release_block_cap == 1


@pytest.mark.parametrize("method, after_ds, cells", [("ebs", 845_312, 225_872), ("dempster", 638_662, 225_672)])
def test_bench_workload_gives_the_release_counts_exactly(method, after_ds, cells):
    # ../shared/data/bench/rellis_like_30scans.json: the release's own counts on this workload
    shared_path("data", "bench", "rellis_like_30scans.npz")
    from evsemmap_warp.data.datasets import open_dataset

    run = load_config([PRESET, REPO / "configs/datasets/bench_rellis_like.yaml"], method=method)
    mapper = Mapper(run.mapping, 9)
    after_cut = kept = 0
    for scan in open_dataset(run.dataset):
        payload = prepare_payload(scan.points - mapper.origin, scan.payload, "alpha", 9)
        after_cut += ReleaseCompatIntegrator(run.mapping).training_points(payload, np.zeros(3))[1]["after_cut"]
        kept += mapper.integrate(scan.points, scan.payload, payload_type="alpha").kept_points
    assert (after_cut, kept, mapper.voxel_count) == (1_618_253, after_ds, cells)
    assert mapper.state_counts()["OCCUPIED"] == cells


def test_block_tables_are_the_same_from_the_dense_grid_and_the_binary_search(monkeypatch):
    rng = np.random.default_rng(9)
    members = np.concatenate([rng.integers(-6, 6, (400, 3)), [[500_000, -400_000, 3]]])  # one far block: a huge box
    far = er.release_blocks(members)
    near = er.release_blocks(members[:-1])
    from evsemmap_warp.methods import sbki_compat

    sbki_tables = sbki_compat.gather_tables(members[:-1])
    monkeypatch.setattr(sbki_compat, "MAX_DENSE_LOOKUP_CELLS", 0)
    for got, want in ((er.release_blocks(members), far), (er.release_blocks(members[:-1]), near)):
        for field in ("blocks", "pair_order", "point_start", "source_blocks", "source_mult"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
    searched = sbki_compat.gather_tables(members[:-1])  # the S-BKI tables use the same lookup
    np.testing.assert_array_equal(searched.sources, sbki_tables.sources)
    np.testing.assert_array_equal(searched.test_blocks, sbki_tables.test_blocks)
    assert far.source_blocks[-1].max() == len(far.blocks) - 1 and (far.source_blocks[-1] >= 0).sum() == 1  # alone: only itself
    from evsemmap_warp.reference.release import block_models

    literal = block_models(far.blocks, er.TARGET_BLOCK_OFFSETS)  # the kernel's binary search against the literal twin
    np.testing.assert_array_equal(far.source_blocks, literal[0])
    np.testing.assert_array_equal(far.source_mult, literal[1])


def test_block_models_kernel_matches_its_numpy_twin(device):
    from evsemmap_warp.reference.release import block_models

    rng = np.random.default_rng(10)
    members = rng.integers(-5, 5, (300, 3))
    got = er.release_blocks(members, device=device)
    literal = block_models(got.blocks, er.TARGET_BLOCK_OFFSETS)
    np.testing.assert_array_equal(got.source_blocks, literal[0])
    np.testing.assert_array_equal(got.source_mult, literal[1])
    one = er.release_blocks(members[:1], device=device)
    assert one.source_mult[0].tolist() == [1 if tuple(o) == (0, 0, 0) else 0 for o in er.TARGET_BLOCK_OFFSETS]


def test_dempster_products_fold_before_they_overflow():
    # 300 confident points in one block: each multiplies ratios of up to 1e6 into its cells; unfolded the
    # products would pass float64's 1.8e308 after ~52 points.
    rng = np.random.default_rng(12)
    pts = (np.float32(0.1) + rng.uniform(-0.05, 0.05, (300, 3))).astype(np.float32)
    alpha = np.ones((300, 3))
    alpha[:, 1] = 1e7
    cfg = _config("dempster", uncertainty_drop_fraction=0.0, release={"ds_multiplier": 1000})
    mapper = Mapper(cfg, 3, origin=np.zeros(3))
    mapper.integrate(pts, alpha, payload_type="alpha")
    arrays, summary = mapper.voxels()
    payload = prepare_payload(pts, alpha, "alpha", 3)
    weights = np.clip(payload.probabilities - payload.uncertainty[:, None] / 3, 0, 1)
    expected = release_insert(pts, weights, payload.uncertainty, resolution_m=0.2, block_depth=2,
                              length=er.kernel_length(0.3), sf2=1.0, dempster=True)
    want = np.array([expected[tuple(v)] for v in arrays.index])
    assert np.isfinite(arrays.evidence).all() and arrays.evidence.max() > 1000  # far beyond one product's range
    np.testing.assert_allclose(arrays.evidence, want[:, :3], rtol=2e-6)  # the kernel values: polynomial vs float32 trig
    assert (summary.label == 1).all()

"""The Mapper end to end against numpy: thresholds, adaptive lengths, post-pass, queries, merging,
and the errors a user gets for bad input."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings, load_config
from evsemmap_warp.core.integrators import uncertainty_quantile_mask
from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.core.mapper import UNKNOWN_LABEL, Mapper, VoxelState, summarize_dirichlet
from evsemmap_warp.reference import scatter as ref

K = 5
REPO = Path(__file__).resolve().parents[1]


def _config(method: str, **overrides) -> MappingConfig:
    cfg = load_config([REPO / "configs/presets/offroad.yaml"], method=method).mapping
    return dataclasses.replace(cfg, **overrides)


def _alpha_scan(rng, n, spread=4.0):
    pts = rng.uniform(-spread, spread, (n, 3))
    evidence = rng.gamma(0.7, 6.0, (n, K))
    return pts, evidence + 1.0


def _expected_evidence(cfg: MappingConfig, pts, alpha):
    """docs/algorithm.md §3 in numpy: quantile threshold, adaptive length, scatter of p or one-hot."""
    s = alpha.sum(1)
    u, p = K / s, alpha / s[:, None]
    keep = np.ones(len(pts), bool)
    if cfg.uncertainty_threshold:
        order = np.sort(u)
        t = order[min(int(np.floor(len(u) * cfg.keep_quantile)), len(u) - 1)]
        keep = u <= t
    lengths = cfg.length_m * cfg.beta * np.exp(1 - cfg.gamma * u) if cfg.adaptive_length else np.full(len(u), cfg.length_m)
    labels = np.argmax(alpha, 1) if cfg.media is Media.ONEHOT else None
    weights = None if cfg.media is Media.ONEHOT else p
    mode = sc.MODE_OWN_VOXEL if cfg.kernel is Kernel.COUNT else sc.MODE_RADIUS
    sel = lambda a: None if a is None else a[keep]  # noqa: E731
    return ref.scatter_points(pts[keep], sel(labels), sel(weights), lengths[keep], u[keep], None, mode, cfg.resolution_m, 0.0, cfg.sigma0, 1, K)


@pytest.mark.parametrize("method", ["s-csm", "s-bki", "ebs", "prob", "prob-adap", "prob-thr", "prob-adap-thr"])
def test_every_method_matches_the_numpy_pipeline(device, method):
    rng = np.random.default_rng(len(method))
    cfg = _config(method)
    mapper = Mapper(cfg, K, device=device)
    pts, alpha = _alpha_scan(rng, 1500)
    pts = pts.astype(np.float32).astype(np.float64)
    mapper.integrate(pts, alpha, payload_type="alpha")
    expected = _expected_evidence(cfg, pts, alpha)
    arrays, summary = mapper.voxels()
    got = {tuple(v): i for i, v in enumerate(arrays.index)}
    want = {tuple(v): i for i, v in enumerate(expected.voxel_index)}
    band = set(got) ^ set(want)  # the d ~ l band of test_scatter; weights there are ~0
    assert len(band) <= 0.002 * len(want)
    common = sorted(set(got) & set(want))
    np.testing.assert_allclose(arrays.evidence[[got[v] for v in common]], expected.alpha_increment[[want[v] for v in common]], rtol=1e-4, atol=1e-5)


def test_uncertainty_quantile_rule():
    u = np.arange(1, 11) / 10.0
    keep, t = uncertainty_quantile_mask(u, 0.7)  # floor(10 * 0.7) = 7 -> the 8th smallest
    assert t == 0.8 and keep.sum() == 8
    keep, t = uncertainty_quantile_mask(np.array([0.1, 0.5, 0.5, 0.5, 0.9]), 0.4)  # ties at t are kept
    assert t == 0.5 and keep.sum() == 4
    keep, t = uncertainty_quantile_mask(np.array([0.3, 0.2]), 1.0)  # index clamped to N - 1
    assert keep.all()
    keep, _ = uncertainty_quantile_mask(np.array([0.42]), 0.9)  # one point
    assert keep.all()


def test_dirichlet_post_pass_rules():
    alpha = np.array([[1, 1, 1], [1, 3, 3], [5, 1, 1], [1, 1, 2], [2, 2, 2]], dtype=np.float32)
    touched = np.array([True, True, True, True, False])
    s = summarize_dirichlet(alpha, touched)
    np.testing.assert_array_equal(s.label, [0, 1, 0, 2, 0])  # ties -> lowest index
    np.testing.assert_array_equal(s.state, [VoxelState.FREE, VoxelState.OCCUPIED, VoxelState.FREE, VoxelState.OCCUPIED, VoxelState.UNKNOWN])
    p = 3 / 7
    np.testing.assert_allclose(s.variance[1], p * (1 - p) / 8, rtol=1e-6)
    np.testing.assert_allclose(s.probabilities.sum(1), 1, rtol=1e-6)


def test_query_returns_map_values_and_unknown_outside(device):
    cfg = _config("s-bki", resolution_m=0.5, length_m=0.4, prior=1.0, sigma0=1.0)
    mapper = Mapper(cfg, 3, device=device)
    pts = np.array([[0.25, 0.25, 0.25], [0.3, 0.2, 0.25]])
    mapper.integrate(pts, np.array([2, 2]), payload_type="label")
    res = mapper.query(np.array([[0.1, 0.1, 0.1], [10.0, 10.0, 10.0]]))
    assert res.label.tolist() == [2, UNKNOWN_LABEL]
    assert res.state.tolist() == [VoxelState.OCCUPIED, VoxelState.UNKNOWN]
    np.testing.assert_allclose(res.probabilities[1], [1 / 3] * 3, rtol=1e-6)
    arrays, summary = mapper.voxels()
    row = np.flatnonzero((arrays.index == 0).all(1))[0]
    np.testing.assert_allclose(res.variance[0], summary.variance[row])
    assert mapper.query(np.zeros((0, 3))).label.shape == (0,)


def test_streaming_halves_equals_one_insertion_without_threshold(device):
    rng = np.random.default_rng(3)
    pts, alpha = _alpha_scan(rng, 2000)
    cfg = _config("prob-adap")
    once = Mapper(cfg, K, device=device)
    once.integrate(pts, alpha, payload_type="alpha")
    halves = Mapper(cfg, K, device=device)
    halves.integrate(pts[:1000], alpha[:1000], payload_type="alpha")
    halves.integrate(pts[1000:], alpha[1000:], payload_type="alpha")
    a, _ = once.voxels()
    b, _ = halves.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-5, atol=1e-6)


def test_merge_of_disjoint_scan_sets_equals_one_map(device):
    rng = np.random.default_rng(4)
    scans = [_alpha_scan(rng, 800) for _ in range(4)]
    cfg = _config("ebs")
    full, first, second = (Mapper(cfg, K, device=device) for _ in range(3))
    for i, (pts, alpha) in enumerate(scans):
        full.integrate(pts, alpha, payload_type="alpha")
        (first if i % 2 == 0 else second).integrate(pts, alpha, payload_type="alpha")
    merged = first.merge(second)
    a, sa = full.voxels()
    b, sb = merged.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a.weight_sum, b.weight_sum, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a.weighted_height_sum, b.weighted_height_sum, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(a.hits, b.hits)
    np.testing.assert_array_equal(a.touched, b.touched)
    assert (sa.label != sb.label).sum() <= 2  # only near-ties may flip with the summation order
    assert merged.scans_integrated == 4
    with pytest.raises(ValueError, match="different methods"):
        first.merge(Mapper(_config("s-bki"), K, device=device))


def test_cpu_maps_are_bit_identical_run_to_run():
    rng = np.random.default_rng(5)
    scans = [_alpha_scan(rng, 1000) for _ in range(3)]
    outs = []
    for _ in range(2):
        m = Mapper(_config("ebs"), K, device="cpu", initial_capacity=16)
        for pts, alpha in scans:
            m.integrate(pts, alpha, payload_type="alpha")
        outs.append(m.voxels()[0])
    for field in dataclasses.fields(outs[0]):
        np.testing.assert_array_equal(getattr(outs[0], field.name), getattr(outs[1], field.name))


# ---------------------------------------------------------------------- bad input
@pytest.fixture
def mapper():
    return Mapper(_config("ebs"), K)


def test_empty_scan_is_a_no_op(mapper):
    stats = mapper.integrate(np.zeros((0, 3)), np.zeros((0, K)), payload_type="alpha")
    assert stats.input_points == 0 and mapper.voxel_count == 0 and mapper.scans_integrated == 0


@pytest.mark.parametrize(
    "points, payload, kind, message",
    [
        (np.array([[0, 0, np.nan]]), np.ones((1, K)), "alpha", "NaN/inf coordinates"),
        (np.array([[0, np.inf, 0]]), np.ones((1, K)), "alpha", "NaN/inf coordinates"),
        (np.zeros((2, 2)), np.ones((2, K)), "alpha", r"expected shape \[N, 3\]"),
        (np.zeros((2, 3)), np.ones((2, K + 1)), "alpha", "6 class columns, but the map has 5 classes"),
        (np.zeros((2, 3)), np.ones((3, K)), "alpha", r"must have shape \[2, 5\]"),
        (np.zeros((1, 3)), np.full((1, K), 0.5), "alpha", "negative evidence"),
        (np.zeros((1, 3)), np.array([[1, 1, np.nan, 1, 1]]), "alpha", "NaN/inf values"),
        (np.zeros((1, 3)), np.full((1, K), 0.3), "prob", "sum to 1"),
        (np.zeros((1, 3)), np.array([[1.2, -0.2, 0, 0, 0]]), "prob", ">= 0"),
        (np.zeros((2, 3)), np.array([0, 5]), "label", r"must lie in \[0, 4\]"),
        (np.zeros((2, 3)), np.array([0.5, 1]), "label", "must be integers"),
        (np.zeros((2, 3)), np.array([0]), "label", r"shape \[2\]"),
        (np.array([[0.0, 0, 0], [1e9, 0, 0]]), np.ones((2, K)) * 2, "alpha", "outside the key range"),
    ],
)
def test_bad_input_gets_a_clear_error(mapper, points, payload, kind, message):
    with pytest.raises(ValueError, match=message):
        mapper.integrate(points, payload, payload_type=kind)
    assert mapper.voxel_count == 0  # nothing half-written


def test_unknown_payload_type_is_refused(mapper):
    with pytest.raises(ValueError, match="'logits' is not a valid PayloadType"):
        mapper.integrate(np.zeros((1, 3)), np.ones((1, K)), payload_type="logits")


def test_sbki_mode_needs_the_sensor_origin():
    cfg = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False, compat=Compat.SBKI)
    with pytest.raises(ValueError, match="sensor_origin"):
        Mapper(cfg, 3).integrate(np.zeros((1, 3)), np.array([1]), payload_type="label")


@pytest.mark.parametrize("method", ["ebs", "s-csm"])
def test_two_workers_give_the_single_worker_map(method):
    rng = np.random.default_rng(6)
    scans = [_alpha_scan(rng, 12000, spread=6.0) for _ in range(2)]  # big enough to be split
    maps = []
    for workers in (1, 2):
        m = Mapper(_config(method), K, workers=workers)
        for pts, alpha in scans:
            m.integrate(pts, alpha, payload_type="alpha")
        maps.append(m)
    assert len(maps[1].shards) == 2 and maps[1].shards[1].voxel_count > 0
    (a, sa), (b, sb) = maps[0].voxels(), maps[1].voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(a.hits, b.hits)
    assert (sa.label != sb.label).sum() <= 2
    q = rng.uniform(-6, 6, (3000, 3))
    qa, qb = maps[0].query(q), maps[1].query(q)
    np.testing.assert_array_equal(qa.state, qb.state)
    np.testing.assert_allclose(qa.probabilities, qb.probabilities, rtol=1e-5, atol=1e-6)
    assert maps[1].voxel_count == maps[0].voxel_count


@pytest.mark.parametrize("origin,pattern", [([1.0, 2.0], "expected 3 coordinates"), ([np.nan, 0, 0], "NaN/inf"), ("abc", "expected 3 coordinates")])
def test_a_bad_map_origin_is_named(origin, pattern):
    with pytest.raises(ValueError, match=f"origin: .*{pattern}"):
        Mapper(_config("ebs"), K, origin=origin)


def _scan_items(scans, payload_type="alpha", origin=(0.0, 0.0, 0.5)):
    from types import SimpleNamespace

    return [SimpleNamespace(name=f"scan{i}", points=pts, payload=payload, payload_type=payload_type, sensor_origin=np.array(origin))
            for i, (pts, payload) in enumerate(scans)]


@pytest.mark.parametrize("mode", ["clean ebs", "sbki", "release ebs", "release dempster"])
def test_integrate_many_equals_integrate_scan_by_scan(mode):
    # The pipelined form (next scan's host work on its own thread) must give the same map bit for bit.
    rng = np.random.default_rng(17)
    scans = [_alpha_scan(rng, n, spread=5.0) for n in (9000, 0, 7000, 1, 8000)]
    if mode == "sbki":
        cfg = MappingConfig(method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
                            compat=Compat.SBKI, sbki=SbkiSettings(free_resolution_m=2.0))
        scans, payload_type = [(p, np.argmax(a, 1)) for p, a in scans], "label"
    elif mode.startswith("release"):
        cfg = load_config([REPO / "configs/presets/release.yaml"], method=mode.split()[1]).mapping
        payload_type = "alpha"
    else:
        cfg, payload_type = _config("ebs"), "alpha"
    one_by_one = Mapper(cfg, K, workers=2)
    expected = [one_by_one.integrate(p, a, payload_type=payload_type, sensor_origin=np.array([0.0, 0.0, 0.5])) for p, a in scans]
    seen = []
    many = Mapper(cfg, K, workers=2)
    got = many.integrate_many(_scan_items(scans, payload_type), progress=lambda scan, stats: seen.append((scan.name, stats.voxel_updates)))
    assert [s.voxel_updates for s in got] == [s.voxel_updates for s in expected]
    assert [s.kept_points for s in got] == [s.kept_points for s in expected]
    assert seen == [(f"scan{i}", s.voxel_updates) for i, s in enumerate(expected)]
    (a, _), (b, _) = one_by_one.voxels(), many.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_array_equal(a.rows(), b.rows())
    assert many.scans_integrated == one_by_one.scans_integrated == 4
    np.testing.assert_array_equal(many.origin_index, one_by_one.origin_index)


@pytest.mark.parametrize("workers", [1, 2])
def test_integrate_many_names_the_bad_scan_and_keeps_what_came_before(workers):
    rng = np.random.default_rng(18)
    scans = [_alpha_scan(rng, 500), _alpha_scan(rng, 500), _alpha_scan(rng, 500)]
    scans[1][1][3, 2] = np.nan
    mapper = Mapper(_config("ebs"), K, workers=workers)
    with pytest.raises(ValueError, match=r"^scan1: .*NaN"):
        mapper.integrate_many(_scan_items(scans))
    reference = Mapper(_config("ebs"), K, workers=1)
    reference.integrate(*scans[0], payload_type="alpha")
    assert mapper.scans_integrated == 1
    np.testing.assert_array_equal(mapper.voxels()[0].index, reference.voxels()[0].index)


def test_integrate_many_names_a_scan_its_shards_refuse_and_stops_before_returning():
    # A scan whose kernels reach past the key range fails inside a shard's job, while the other shard
    # may already be on the next scan: the error still names it, the scans before it are in the map,
    # and no shard job changes the map after integrate_many has raised.
    import time

    from evsemmap_warp.kernels import hash_table as ht

    rng = np.random.default_rng(21)
    scans = [_alpha_scan(rng, 9000) for _ in range(4)]
    scans[1][0][-1] = [2.5 * ht.INDEX_LIMIT * 0.2, 0.0, 0.0]  # in the second shard's part
    mapper = Mapper(_config("ebs"), K, workers=2)
    with pytest.raises(ValueError, match=r"^scan1: .*key range"):
        mapper.integrate_many(_scan_items(scans))
    before = [shard.arrays().rows() for shard in mapper.shards]
    time.sleep(0.2)
    for shard, rows in zip(mapper.shards, before):
        np.testing.assert_array_equal(shard.arrays().rows(), rows)
    reference = Mapper(_config("ebs"), K, workers=1)
    reference.integrate(*scans[0], payload_type="alpha")
    assert set(map(tuple, reference.voxels()[0].index)) <= set(map(tuple, mapper.voxels()[0].index))


def test_integrate_many_passes_reading_errors_through():
    def scans():
        yield from _scan_items([_alpha_scan(np.random.default_rng(19), 300)])
        raise ValueError("frame 000001.bin: truncated")

    mapper = Mapper(_config("ebs"), K, workers=2)
    with pytest.raises(ValueError, match="truncated"):
        mapper.integrate_many(scans())
    assert mapper.scans_integrated == 1


def test_integrate_many_reads_in_order_and_sets_the_origin_from_the_first_non_empty_scan():
    # Reading takes varying time and the first scans are empty: the scans still map in order, and
    # the origin is the one integrate gives (scan by scan), not whichever scan a thread reached first.
    import time

    rng = np.random.default_rng(20)
    scans = [_alpha_scan(rng, 0), _alpha_scan(rng, 0)] + [(_alpha_scan(rng, 3000)[0] + 5000.0 * i, _alpha_scan(rng, 3000)[1]) for i in range(1, 7)]
    delays = rng.uniform(0, 0.02, len(scans))

    def slowly():
        for item, delay in zip(_scan_items(scans), delays):
            time.sleep(delay)
            yield item

    seen = []
    many = Mapper(_config("ebs"), K, workers=2)
    many.integrate_many(slowly(), progress=lambda scan, _: seen.append(scan.name))
    one_by_one = Mapper(_config("ebs"), K, workers=2)
    for pts, alpha in scans:
        one_by_one.integrate(pts, alpha, payload_type="alpha")
    assert seen == [f"scan{i}" for i in range(len(scans))]
    np.testing.assert_array_equal(many.origin_index, one_by_one.origin_index)
    np.testing.assert_array_equal(many.voxels()[0].rows(), one_by_one.voxels()[0].rows())


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("k", [1, 2, 7, 8, 9, 15, 16, 17, 24, 129])
def test_row_sums_are_numpys_row_sums_bit_for_bit(k, dtype):
    # row_sums reproduces numpy's pairwise order column by column; a different order changes the last bits
    # of S, and with them the uncertainty cut of the release mode and every map built from alpha.
    from evsemmap_warp.core.mapper import row_sums

    rng = np.random.default_rng(k)
    values = (rng.gamma(0.3, 1e3, (4000, k)) * rng.choice([1e-8, 1.0, 1e8], (4000, k)) + 1.0).astype(dtype)
    values[0] = -0.0  # a row of negative zeros sums to +0.0 in numpy
    want = np.asarray(values, np.float64).sum(axis=1)
    got = row_sums(values)
    assert got.dtype == np.float64 and np.array_equal(got.view(np.int64), want.view(np.int64))
    assert row_sums(values[:0]).shape == (0,)


@pytest.mark.parametrize("payload_type", ["alpha", "prob", "label"])
def test_probabilities_derived_on_demand_are_those_of_the_whole_payload(payload_type):
    # The probabilities are derived for the rows an integrator asks for; they must be those rows of the
    # whole payload's probabilities, in any order, from a float32 payload as from its float64 copy.
    from evsemmap_warp.core.mapper import prepare_payload

    rng = np.random.default_rng(3)
    n = 500
    points = rng.uniform(-5, 5, (n, 3))
    alpha = (rng.gamma(0.7, 6.0, (n, K)) + 1.0).astype(np.float32)
    payload = {"alpha": alpha, "prob": alpha / alpha.sum(axis=1, keepdims=True), "label": rng.integers(0, K, n)}[payload_type]
    scan = prepare_payload(points, payload, payload_type, K)
    whole = np.asarray(payload, np.float64)
    want = np.eye(K)[payload] if payload_type == "label" else whole / whole.sum(axis=1)[:, None]
    rows = rng.permutation(n)[:200]
    np.testing.assert_array_equal(scan.probability_rows(rows), want[rows])
    np.testing.assert_array_equal(scan.probability_rows(want[:, 0] > 0.2), want[want[:, 0] > 0.2])
    np.testing.assert_array_equal(scan.probabilities, want)
    np.testing.assert_array_equal(scan.probability_rows(rows), want[rows])  # from the cached whole
    if payload_type == "alpha":
        np.testing.assert_array_equal(scan.uncertainty, K / whole.sum(axis=1))
    elif payload_type == "prob":
        np.testing.assert_array_equal(scan.uncertainty, 1.0 - want.max(axis=1))
    assert scan.num_classes == K

"""Correct at any scale: far coordinates, the key range, long accumulations, exact merges, and two
worker threads growing their tables on a cold kernel cache."""

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from evsemmap_warp.config import Compat, load_config
from evsemmap_warp.core.mapper import ORIGIN_STEP_VOXELS, UNKNOWN_LABEL, Mapper
from evsemmap_warp.core.voxel_map import VoxelMap
from evsemmap_warp.kernels import hash_table as ht

K = 5
REPO = Path(__file__).resolve().parents[1]
# UTM-like coordinates: a scan at (500 km, 4,000 km, 100 m).
FAR = np.array([500_000.0, 4_000_000.0, 100.0])
CLEAN_METHODS = ["s-csm", "s-bki", "ebs", "prob-adap-thr", "convbki", "see-csom", "dempster"]
ALL_METHODS = CLEAN_METHODS + ["s-bki@sbki", "s-csm@sbki"]


def _config(name: str):
    method, _, compat = name.partition("@")
    cfg = load_config([REPO / "configs/presets/offroad.yaml"], method=method).mapping
    if compat:
        cfg = dataclasses.replace(cfg, compat=Compat(compat))
    return cfg


def _scan(rng, n=3000, spread=6.0, center=(0.0, 0.0, 0.0)):
    pts = rng.uniform(-spread, spread, (n, 3)) + np.asarray(center)
    return pts, rng.gamma(0.7, 6.0, (n, K)) + 1.0


def _integrate(mapper, scans):
    for pts, alpha in scans:
        mapper.integrate(pts, alpha, payload_type="alpha", sensor_origin=pts.mean(axis=0) + [0, 0, 2])
    return mapper


@pytest.mark.parametrize("method", ALL_METHODS)
def test_a_far_scan_maps_as_the_same_scan_near_the_origin(method):
    rng = np.random.default_rng(11)
    scans = [_scan(rng) for _ in range(2)]
    cfg = _config(method)
    # a whole number of voxels near FAR, so the two maps hold the same voxels, shifted
    shift = np.round(FAR / cfg.resolution_m) * cfg.resolution_m
    float32_preprocessing = cfg.compat is Compat.SBKI or method == "see-csom"
    if float32_preprocessing:
        # S-BKI, S-CSM and SEE-CSOM preprocess scans in float32 as their C++ does (VoxelGrid, rays),
        # relative to the map origin: their maps agree when the shift is a whole number of origin
        # steps, up to float32 rounding of the weights.
        step = ORIGIN_STEP_VOXELS * cfg.resolution_m
        shift = np.round(FAR / step) * step
    near = _integrate(Mapper(cfg, K), scans)
    far = _integrate(Mapper(cfg, K), [(pts + shift, alpha) for pts, alpha in scans])
    assert far.origin_index.any() and not near.origin_index.any()
    (a, sa), (b, sb) = near.voxels(), far.voxels()
    offset = np.round(shift / cfg.resolution_m).astype(np.int64)
    assert len(a.index) > 100
    np.testing.assert_array_equal(a.index + offset, b.index)
    np.testing.assert_array_equal(sa.label, sb.label)
    np.testing.assert_array_equal(sa.state, sb.state)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-5 if float32_preprocessing else 1e-7,
                               atol=1e-4 if float32_preprocessing else 1e-9)
    if float32_preprocessing:  # float32 kernel values at the support edge round to 0 or not
        assert (a.hits != b.hits).mean() < 1e-3
    else:
        np.testing.assert_array_equal(a.hits, b.hits)
    # Queries at the far coordinates find the same voxels.
    q = scans[0][0][:200]
    near_hits, far_hits = near.query(q), far.query(q + shift)
    np.testing.assert_array_equal(near_hits.label, far_hits.label)
    np.testing.assert_array_equal(near_hits.voxel_index + offset, far_hits.voxel_index)


def test_float32_positions_would_have_lost_the_far_map():
    """The failure the float64 origin fixes, shown on the numbers: at 4,000 km float32 positions are
    0.25 m apart, more than a voxel."""
    assert np.spacing(np.float32(4_000_000.0)) == 0.25
    assert np.spacing(4_000_000.0 - 3_998_720.0) < 1e-12


def test_queries_outside_the_key_range_find_nothing_and_never_wrap(device):
    mapper = Mapper(_config("s-csm"), K, device=device)
    rng = np.random.default_rng(3)
    pts, alpha = _scan(rng, 500, spread=2.0)
    mapper.integrate(pts, alpha, payload_type="alpha")
    r = mapper.config.resolution_m
    wrap = (1 << ht.KEY_BITS) * r  # one full key period away: the old packing landed on the same voxel
    limit = ht.INDEX_LIMIT * r
    queries = np.array([pts[0], pts[0] + [wrap, 0, 0], pts[0] + [0, -wrap, 0], [limit + 1.0, 0, 0], [-limit - 1.0, 0, 0], [0, 0, 1e300]])
    result = mapper.query(queries)
    assert result.label[0] != UNKNOWN_LABEL
    assert (result.label[1:] == UNKNOWN_LABEL).all()
    assert (result.state[1:] == 0).all()


def test_the_empty_sentinel_is_never_found_or_inserted(device):
    vm = VoxelMap(K, 0.2, device=device, initial_capacity=64)
    vm.insert_voxels(np.array([[0, 0, 0]]))
    import warp as wp

    keys = wp.array(np.array([ht.EMPTY_KEY, ht.EMPTY_KEY], np.int64), dtype=wp.int64, device=device)
    found = wp.empty(2, dtype=int, device=device)
    wp.launch(ht.lookup_keys, dim=2, inputs=[keys, vm.table(), found], device=device)
    assert (found.numpy() == -1).all()
    wp.launch(ht.insert_keys, dim=2, inputs=[keys, ht.hash_table(vm.keys, vm.slot_rows, vm.key_count, 1 << 20), found], device=device)
    assert (found.numpy() == -1).all() and vm.voxel_count == 1


@pytest.mark.parametrize("method", ["convbki", "ebs", "s-bki@sbki", "see-csom"])
def test_a_scan_wider_than_the_key_range_is_refused_not_wrapped(method):
    mapper = Mapper(_config(method), K)
    span = 2.5 * ht.INDEX_LIMIT * mapper.config.resolution_m
    pts = np.array([[0.0, 0.0, 0.0], [span, 0.0, 0.0]])
    with pytest.raises(ValueError, match="key range"):
        mapper.integrate(pts, np.full((2, K), 2.0), payload_type="alpha", sensor_origin=[0, 0, 0])
    assert mapper.voxel_count == 0


def test_twenty_million_unit_contributions_sum_exactly():
    mapper = Mapper(_config("s-csm"), 2)
    batch = np.full((2_000_000, 3), 0.05)
    labels = np.ones(len(batch), dtype=np.int64)
    for _ in range(10):
        mapper.integrate(batch, labels, payload_type="label")
    arrays, summary = mapper.voxels()
    assert len(arrays.index) == 1
    assert arrays.hits[0] == 20_000_000
    assert abs(arrays.evidence[0, 1] - 2e7) <= 2e7 * 1e-9
    assert abs(arrays.weight_sum[0] - 2e7) <= 2e7 * 1e-9
    # float32 would have stopped at 2^24 = 16,777,216
    assert arrays.evidence[0, 1] > 2**24 + 1
    np.testing.assert_allclose(summary.probabilities[0], [1 / (2e7 + 2), (2e7 + 1) / (2e7 + 2)], rtol=1e-12)


@pytest.mark.parametrize("method", ALL_METHODS)
def test_merge_of_disjoint_scan_sets_is_exact_for_every_method(method):
    rng = np.random.default_rng(5)
    scans = [_scan(rng, 1500, spread=4.0, center=(i * 1.5, 0, 0)) for i in range(4)]
    cfg = _config(method)
    full = _integrate(Mapper(cfg, K), scans)
    first = _integrate(Mapper(cfg, K), scans[::2])
    second = _integrate(Mapper(cfg, K), scans[1::2])
    merged = first.merge(second)
    (a, sa), (b, sb) = full.voxels(), merged.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.weight_sum, b.weight_sum, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(a.hits, b.hits)
    np.testing.assert_array_equal(a.touched, b.touched)
    np.testing.assert_array_equal(sa.label, sb.label)
    np.testing.assert_array_equal(sa.state, sb.state)


def test_merge_reindexes_maps_with_other_origins():
    rng = np.random.default_rng(6)
    cfg = _config("ebs")
    scans = [_scan(rng, 1500, center=FAR + [i * 900.0, 0, 0]) for i in range(2)]  # 900 m apart: different origins
    full = _integrate(Mapper(cfg, K, origin=FAR), scans)
    first = _integrate(Mapper(cfg, K), scans[:1])
    second = _integrate(Mapper(cfg, K), scans[1:])
    assert (first.origin_index != second.origin_index).any()
    merged = first.merge(second)
    (a, sa), (b, sb) = full.voxels(), merged.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    # the maps' local frames differ by whole origin steps: float64 rounding of positions near 4,000 km
    np.testing.assert_allclose(a.evidence, b.evidence, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(sa.label, sb.label)


def test_merge_refuses_incompatible_maps_with_the_reason():
    base = Mapper(_config("ebs"), K, class_names=list("abcde"))
    with pytest.raises(ValueError, match="different classes"):
        base.merge(Mapper(_config("ebs"), K, class_names=list("abcdx")))
    with pytest.raises(ValueError, match="different resolutions"):
        base.merge(Mapper(dataclasses.replace(_config("ebs"), resolution_m=0.5), K, class_names=list("abcde")))
    with pytest.raises(ValueError, match="different methods"):
        base.merge(Mapper(_config("s-bki"), K, class_names=list("abcde")))
    with pytest.raises(ValueError, match="length_m"):
        base.merge(Mapper(dataclasses.replace(_config("ebs"), length_m=0.5), K, class_names=list("abcde")))
    rng = np.random.default_rng(1)
    near = _integrate(Mapper(_config("ebs"), K, class_names=list("abcde")), [_scan(rng, 200)])
    far = _integrate(Mapper(_config("ebs"), K, class_names=list("abcde")), [_scan(rng, 200, center=(FAR[0], 0, 0))])
    with pytest.raises(ValueError, match="too far apart"):
        near.merge(far)


_COLD_CACHE_SCRIPT = """
import numpy as np
from evsemmap_warp import Mapper, load_config
cfg = load_config([], method="ebs").mapping
m = Mapper(cfg, 3, workers=2, initial_capacity=16)
rng = np.random.default_rng(0)
pts = rng.uniform(-20, 20, (40000, 3))
m.integrate(pts, rng.gamma(1, 3, (40000, 3)) + 1, payload_type="alpha")
assert all(s.grow_count > 0 and s.voxel_count > 0 for s in m.shards), [s.grow_count for s in m.shards]
print("ok", m.voxel_count)
"""


def test_two_workers_growing_their_tables_on_a_cold_kernel_cache(tmp_path):
    """Every kernel is built before the workers start: a cold cache, two shards whose tables both
    grow in the first launch, no lazy instantiation inside a worker thread."""
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "cold"))
    done = subprocess.run([sys.executable, "-c", _COLD_CACHE_SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.startswith("ok")


def test_no_kernel_is_generic():
    """A generic kernel is instantiated on first use, which may be inside a worker thread while the
    other thread runs the module (the KeyError once seen): every kernel has concrete types."""
    import importlib
    import pkgutil

    import warp as wp

    import evsemmap_warp.kernels as kernels_pkg

    for info in pkgutil.iter_modules(kernels_pkg.__path__):
        module = importlib.import_module(f"evsemmap_warp.kernels.{info.name}")
        for name, obj in vars(module).items():
            if isinstance(obj, wp.Kernel):
                assert not obj.is_generic, f"kernels/{info.name}.py: {name} is generic"


def test_a_far_map_file_round_trips_and_the_viewer_finds_its_voxels(tmp_path):
    from evsemmap_warp.apps.viewer import MapLayer

    rng = np.random.default_rng(8)
    mapper = _integrate(Mapper(_config("ebs"), K), [_scan(rng, 2000, center=FAR)])
    path = mapper.save(tmp_path / "far.npz")
    loaded = Mapper.load(path)
    np.testing.assert_array_equal(loaded.origin, mapper.origin)
    (a, _), (b, _) = mapper.voxels(), loaded.voxels()
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_array_equal(a.evidence, b.evidence)
    layer = MapLayer.from_file(path)
    rows = layer.voxel_at(layer.centers[:50])
    np.testing.assert_array_equal(rows, np.arange(50))
    assert (layer.voxel_at(np.array([[0.0, 0.0, 0.0]])) == -1).all()

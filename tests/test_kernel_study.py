"""The performance study runs and its strategies agree; the sort-then-reduce and microbenchmark kernels
against their numpy twins."""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO

from evsemmap_warp.config import CleanSettings, ConfigError, ScatterStrategy, load_config
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.core.warp_runtime import init_warp
from evsemmap_warp.kernels import microbench as mb
from evsemmap_warp.reference import microbench as mb_ref
from evsemmap_warp.reference import sorted_scatter as ss_ref
from evsemmap_warp.reference.hash_table import pack_key

wp = init_warp()


def _cloud(rng, n):
    pts = rng.uniform(-1.0, 1.0, (n, 3))
    pts[: n // 4, 0] = np.round(pts[: n // 4, 0] / 0.2) * 0.2  # on voxel faces
    pts[: n // 8, 1] = 1.6  # on block faces (8 voxels of 0.2 m)
    alpha = np.ones((n, 5))
    alpha[np.arange(n), rng.integers(0, 5, n)] += rng.uniform(0, 20, n)
    return pts, alpha


@pytest.mark.parametrize("n", [0, 1, 2, 500])
@pytest.mark.parametrize("method", ["s-bki", "prob", "ebs"])
def test_sorted_and_gather_strategies_give_the_atomic_map(device, method, n):
    rng = np.random.default_rng(n)
    pts, alpha = _cloud(rng, max(n, 1))
    pts, alpha = pts[:n], alpha[:n]
    base = load_config([REPO / "configs/presets/rellis3d.yaml"], method=method).mapping
    maps = []
    for strategy in ("atomic", "sorted", "gather"):
        mapper = Mapper(base.replace(clean={"scatter_strategy": ScatterStrategy(strategy)}), 5, device=device, origin=np.zeros(3), initial_capacity=16)
        mapper.integrate(pts, alpha, payload_type="alpha")
        mapper.integrate(pts + 0.05, alpha, payload_type="alpha")  # accumulation and table growth
        maps.append(mapper.voxels()[0])
    for other in maps[1:]:
        np.testing.assert_array_equal(maps[0].index, other.index)
        np.testing.assert_allclose(maps[0].rows(), other.rows(), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("strategy", ["sorted", "gather"])
def test_deterministic_strategies_far_from_the_origin_map_as_near_it(strategy):
    rng = np.random.default_rng(3)
    pts, alpha = _cloud(rng, 300)
    cfg = load_config([REPO / "configs/presets/rellis3d.yaml"], method="s-bki").mapping.replace(clean=CleanSettings(ScatterStrategy(strategy)))
    shift = np.array([500_000.0, 4_000_000.0, 100.0])
    near, far = Mapper(cfg, 5), Mapper(cfg, 5)
    near.integrate(pts, alpha, payload_type="alpha")
    far.integrate(pts + shift, alpha, payload_type="alpha")
    (a, _), (b, _) = near.voxels(), far.voxels()
    np.testing.assert_array_equal(a.index + np.round(shift / 0.2).astype(np.int64), b.index)
    np.testing.assert_allclose(a.rows(), b.rows(), rtol=1e-7, atol=1e-9)


def test_sorted_stages_match_their_twins():
    rng = np.random.default_rng(4)
    pts, _ = _cloud(rng, 200)
    lengths = rng.uniform(0.05, 0.5, 200)
    from evsemmap_warp.kernels import sorted_scatter as ss

    from evsemmap_warp.kernels import scatter as sc

    scan = sc.scan_points(points=wp.array(pts, dtype=wp.vec3d, device="cpu"), lengths=wp.array(lengths, dtype=wp.float64, device="cpu"))
    params = sc.scatter_params(resolution=0.2, grid_offset=0.0, sigma0=1.0)
    counts = wp.empty(200, dtype=int, device="cpu")
    wp.launch(ss.count_pairs, dim=200, inputs=[scan, params, ss.pair_counts(counts)], device="cpu")
    np.testing.assert_array_equal(counts.numpy(), ss_ref.count_pairs(pts, lengths, 0.2, 0.0))
    offsets = np.r_[0, np.cumsum(counts.numpy())[:-1]].astype(np.int32)
    total = int(counts.numpy().sum())
    keys, ids = wp.empty(2 * total, dtype=wp.int64, device="cpu"), wp.empty(2 * total, dtype=int, device="cpu")
    point, weight = wp.empty(total, dtype=int, device="cpu"), wp.empty(total, dtype=wp.float64, device="cpu")
    wp.launch(ss.expand_pairs, dim=200, inputs=[scan, params, ss.pair_list(offsets=wp.array(offsets, dtype=int, device="cpu"), keys=keys, ids=ids,
                                                                            point=point, weight=weight)], device="cpu")
    want_keys, want_point, want_weight = ss_ref.expand_pairs(pts, lengths, 0.2, 0.0, 1.0)
    got = sorted(zip(point.numpy(), keys.numpy()[:total], weight.numpy()))
    want = sorted(zip(want_point, want_keys, want_weight))
    assert [g[:2] for g in got] == [w[:2] for w in want]
    np.testing.assert_allclose([g[2] for g in got], [w[2] for w in want], rtol=1e-12, atol=1e-15)
    heads = ss_ref.mark_heads(np.sort(want_keys))
    assert heads.sum() == len(np.unique(want_keys))
    assert pack_key(np.zeros((1, 3), np.int64))[0] >= 0


def test_row_adds_and_stream_copy_match_their_twins():
    rng = np.random.default_rng(5)
    rows = rng.integers(0, 10, 400).astype(np.int32)
    w = rng.random(400)
    for kernel, twin, dtype in ((mb.add_rows64, mb_ref.add_rows64, wp.float64), (mb.add_rows32, mb_ref.add_rows32, wp.float32)):
        data = wp.zeros((10, 3), dtype=dtype, device="cpu")
        wp.launch(kernel, dim=400, inputs=[wp.array(rows, dtype=int, device="cpu"), wp.array(w.astype(wp.dtype_to_numpy(dtype)), dtype=dtype, device="cpu"), data], device="cpu")
        np.testing.assert_allclose(data.numpy(), twin(rows, w, np.zeros((10, 3))), rtol=1e-5)
    src = wp.array(w, dtype=wp.float64, device="cpu")
    dst = wp.empty(400, dtype=wp.float64, device="cpu")
    wp.launch(mb.stream_copy, dim=400, inputs=[src, dst], device="cpu")
    np.testing.assert_array_equal(dst.numpy(), mb_ref.stream_copy(w))


def test_every_index_form_of_the_radix_scatter_matches_its_twin_and_the_study_times_them():
    rng = np.random.default_rng(8)
    values = (rng.integers(0, 1 << 9, 3000).astype(np.int64) << 12) | np.arange(3000)
    digits = (values >> 12) & 63
    want = mb_ref.radix_scatter_form(values, 12, 6)
    assert (np.diff((want >> 12) & 63) >= 0).all() and not (want == values).all()
    for while_loop in (True, False):
        for masked in (True, False):
            slots = wp.array(np.r_[0, np.cumsum(np.bincount(digits, minlength=64))[:-1]].astype(np.int32), dtype=int, device="cpu")
            out = wp.empty(len(values), dtype=wp.int64, device="cpu")
            wp.launch(mb.radix_scatter_form(while_loop, masked), dim=1, device="cpu",
                      inputs=[wp.array(values, dtype=wp.int64, device="cpu"), 12, 6, slots, out])
            np.testing.assert_array_equal(out.numpy(), want)
    result = subprocess.run([sys.executable, str(REPO / "tools/kernel_study.py"), "--index-forms", "5000"], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.count(" ns per value") == 4 and "while loop, masked" in result.stdout


def test_sorted_strategy_refuses_what_it_does_not_integrate():
    with pytest.raises(ConfigError, match="mapping.clean.scatter_strategy"):
        dataclasses.replace(load_config([REPO / "configs/presets/rellis3d.yaml"], method="dempster").mapping,
                            clean=CleanSettings(ScatterStrategy.SORTED))
    with pytest.raises(ConfigError, match="mapping.clean.scatter_strategy = 'fast': must be atomic, sorted or gather"):
        dataclasses.replace(load_config([REPO / "configs/presets/rellis3d.yaml"], method="ebs").mapping, clean=CleanSettings("fast"))


def test_quick_study_runs_and_its_strategies_agree(tmp_path):
    result = subprocess.run([sys.executable, str(REPO / "tools/kernel_study.py"), "--quick", "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    report = (tmp_path / "kernel_study.md").read_text()
    assert "every strategy gave the atomic scatter's voxels" in report
    assert report.count("| S-BKI gather") == 5 and report.count("| release gather") == 2  # every form, the same map
    for png in ("strategies.png", "hash_load.png", "scaling.png"):
        assert (tmp_path / "kernel_study" / png).stat().st_size > 1000
    # its record beside it, named by the page, holding every speed figure the page prints
    sys.path.insert(0, str(REPO / "tools"))
    import perf_records

    records = list((tmp_path / "bench").glob("kernel_study-*.json"))
    assert len(records) == 1 and f"<!-- page-record: {records[0]} -->" in report
    checked = perf_records.check([tmp_path / "kernel_study.md"])
    assert not checked.problems and not checked.unrecorded


def test_hashgrid_stages_match_their_twins():
    from evsemmap_warp.kernels import hashgrid_gather as hg
    from evsemmap_warp.reference import hashgrid_gather as hg_ref

    rng = np.random.default_rng(6)
    pts, _ = _cloud(rng, 150)
    lengths = rng.uniform(0.05, 0.5, 150)
    from evsemmap_warp.kernels import hash_table as ht
    from evsemmap_warp.kernels import scatter as sc

    scan = sc.scan_points(points=wp.array(pts, dtype=wp.vec3d, device="cpu"), lengths=wp.array(lengths, dtype=wp.float64, device="cpu"))
    params = sc.scatter_params(resolution=0.2, grid_offset=0.0)
    keys = wp.full(4096, -1, dtype=wp.int64, device="cpu")
    count, failed = wp.zeros(1, dtype=int, device="cpu"), wp.zeros(1, dtype=int, device="cpu")
    wp.launch(hg.mark_reached, dim=150, inputs=[scan, params, hg.reached_keys(ht.hash_table(keys, wp.zeros(4096, dtype=int, device="cpu"), count, 4096),
                                                                                failed)], device="cpu")
    got = np.sort(keys.numpy()[keys.numpy() != -1])
    np.testing.assert_array_equal(got, hg_ref.mark_reached(pts, lengths, 0.2, 0.0))
    assert int(count.numpy()[0]) == len(got) and not failed.numpy()[0]
    tiny = wp.full(8, -1, dtype=wp.int64, device="cpu")  # a full key set reports instead of dropping
    wp.launch(hg.mark_reached, dim=150, inputs=[scan, params, hg.reached_keys(ht.hash_table(tiny, wp.zeros(8, dtype=int, device="cpu"),
                                                                                             wp.zeros(1, dtype=int, device="cpu"), 4), failed)], device="cpu")
    assert failed.numpy()[0] == 1


def test_the_integration_bench_releases_each_repeats_map_before_the_next(monkeypatch):
    # Keeping every repeat's map alive made each repeat after the first run on memory the process had
    # not touched before, which faults in ~1.5x slower on this project's VMs: the median was biased.
    import gc
    import weakref
    from types import SimpleNamespace

    sys.path.insert(0, str(REPO / "tools"))
    import bench_integrate

    alive_at_start = []
    made = []

    class Tracked(Mapper):
        def __init__(self, *args, **kwargs):
            gc.collect()
            alive_at_start.append(sum(ref() is not None for ref in made))
            super().__init__(*args, **kwargs)
            made.append(weakref.ref(self))

    monkeypatch.setattr(bench_integrate, "Mapper", Tracked)
    rng = np.random.default_rng(3)
    scans = [SimpleNamespace(points=rng.uniform(-3, 3, (400, 3)), sensor_origin=np.zeros(3)) for _ in range(2)]
    payloads = [rng.gamma(0.7, 6.0, (400, 9)) + 1.0 for _ in scans]
    timed = bench_integrate.MapperRow(load_config([REPO / "configs/presets/rellis3d.yaml"], method="ebs").mapping, scans, payloads, "alpha", "cpu")
    row = bench_integrate.time_rows({"ebs": timed}, 3, SimpleNamespace(update=lambda n: None))["ebs"]
    assert len(row["all_seconds"]) == 3 and row["voxels"] > 0
    # no map, the warm-up's included, is alive when the next one is made
    assert alive_at_start == [0, 0, 0, 0]


def test_the_integration_bench_runs_its_rows_in_rounds():
    # A slower stretch of a shared VM then falls on one repeat of every row, not on all of one row's.
    sys.path.insert(0, str(REPO / "tools"))
    import bench_integrate

    calls = []

    class Row:
        def __init__(self, name):
            self.name, self.runs = name, []

        def warm_up(self):
            calls.append(("warm", self.name))

        def run(self, progress):
            calls.append(("run", self.name))
            self.runs.append(float(len(calls)))

        def result(self):
            return {"seconds": self.runs[len(self.runs) // 2]}

    got = bench_integrate.time_rows({"a": Row("a"), "b": Row("b")}, 3, None)
    assert calls == [("warm", "a"), ("warm", "b")] + [("run", "a"), ("run", "b")] * 3
    assert got == {"a": {"seconds": 5.0}, "b": {"seconds": 6.0}}


def _cpp_figures(totals=(2.0, 1.0, 3.0)):
    row = {"totals": list(totals), "cells": 10, "free": 4, "occupied": 6, "after_unc": 5, "after_ds": 3}
    return {"measured": {"summary": "timed here"},
            "sbki_original": {"results": {f"{k}_t{t}": dict(row) for k in ("fr0.5", "fr4.0", "fr100") for t in (1, 2)}},
            "evsemmap": {"results": {f"{m}_t{t}": dict(row) for m in ("ebs", "dempster") for t in (1, 2)}}}


def test_the_integration_bench_reads_the_cpp_figures_it_is_given(tmp_path):
    import json

    sys.path.insert(0, str(REPO / "tools"))
    import bench_integrate

    path = tmp_path / "side_by_side.json"
    path.write_text(json.dumps(_cpp_figures()))
    sbki, evsemmap, source = bench_integrate.read_cpp_figures(path)
    assert source == "timed here" and sbki["fr4.0_t2"]["totals"] == [2.0, 1.0, 3.0] and evsemmap["dempster_t1"]["cells"] == 10
    # a missing row, a release row without its counts, a zero time, a file that is no JSON: one message naming the file
    broken = _cpp_figures()
    del broken["evsemmap"]["results"]["ebs_t2"]
    uncounted = _cpp_figures()
    del uncounted["evsemmap"]["results"]["dempster_t1"]["after_ds"]
    zero = _cpp_figures(totals=(0.0, 1.0))
    for name, text in (("missing.json", json.dumps(broken)), ("uncounted.json", json.dumps(uncounted)), ("zero.json", json.dumps(zero)),
                       ("text.json", "not json")):
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match=name):
            bench_integrate.read_cpp_figures(tmp_path / name)
    with pytest.raises(ValueError, match="absent.json"):
        bench_integrate.read_cpp_figures(tmp_path / "absent.json")


def test_the_integration_bench_feeds_sbki_the_workloads_labels():
    # The C++ S-BKI runs read the workload's label array; the argmax of its alphas differs for ~2 % of
    # the points (there the second class carries more evidence), which would change the map.
    sys.path.insert(0, str(REPO / "tools"))
    import bench_integrate

    label = np.array([3, 1, 4, 1, 5, 9, 2], np.uint8)
    dataset = type("Workload", (), {"offsets": np.array([0, 4, 7]), "data": {"label": label}, "__len__": lambda self: 2})()
    got = bench_integrate.sbki_labels(dataset)
    assert [g.tolist() for g in got] == [[3, 1, 4, 1], [5, 9, 2]] and got[0].dtype == np.int64


@pytest.mark.parametrize("n", [0, 1, 300])
def test_the_reduce_and_gather_twins_sum_what_the_scatter_twin_sums(n):
    # the twins of the sorted and gather kernels, heights included, against the scatter's twin (test_scatter
    # holds the kernels to it): points on voxel faces in z, at a far height and in one voxel together
    from evsemmap_warp.reference import hashgrid_gather as hg_ref
    from evsemmap_warp.reference import scatter as sc_ref

    rng = np.random.default_rng(9)
    pts, _ = _cloud(rng, max(n, 1))
    pts = pts[:n]
    pts[: n // 5, 2] = np.round(pts[: n // 5, 2] / 0.2) * 0.2  # on a face between two voxel layers
    pts[n // 5: n // 4, 2] += 1000.0  # far up: the height sums are offsets from the centers, as near the origin
    pts[n // 4: n // 3] = pts[n // 4: n // 4 + 1]  # many points of one voxel
    weights = rng.random((n, 5))
    lengths, unc = rng.uniform(0.05, 0.5, n), rng.random(n)
    want = sc_ref.scatter_points(pts, None, weights, lengths, unc, None, sc_ref.MODE_RADIUS, 0.2, 0.0, 1.0, 4, 5)
    want_rows = np.column_stack([want.alpha_increment, want.weight_sum, want.weighted_uncertainty_sum, want.hits, want.weighted_height_sum])
    want_keys = pack_key(want.voxel_index)
    order = np.argsort(want_keys)
    keys, point, weight = ss_ref.expand_pairs(pts, lengths, 0.2, 0.0, 1.0)
    by_key = np.argsort(keys, kind="stable")
    for got_keys, got_rows in (ss_ref.reduce_voxels(keys[by_key], point[by_key], weight[by_key], weights, unc, pts, 0.2, 0.0),
                               hg_ref.gather_voxels(pts, lengths, weights, unc, 0.2, 0.0, 1.0)):
        np.testing.assert_array_equal(got_keys, want_keys[order])
        np.testing.assert_allclose(got_rows, want_rows[order], rtol=1e-12, atol=1e-12)
    if n:
        assert (want.weighted_height_sum < 0).any() and (want.weighted_height_sum > 0).any()
        mean = want.weighted_height_sum / want.weight_sum
        assert np.abs(mean).max() < 0.5  # a point reaches the voxels whose centers lie within its length (< 0.5 m)

"""Issue 29: the robustness protocol (seeds, subsets, --quick) and the uncertainty diagnostics."""

import dataclasses
import json

import numpy as np
import pytest

from evsemmap_warp.apps import uncertainty_study as us
from evsemmap_warp.apps.cli import main
from evsemmap_warp.apps.experiment import NetworkSpec, _subset, load_experiment, seed_group
from evsemmap_warp.config import ConfigError, load_config, preset_path
from evsemmap_warp.core.integrators import uncertainty_quantile_mask
from evsemmap_warp.core.mapper import VoxelState, load_map
from evsemmap_warp.segmentation.metrics import SegmentationMetrics

SCORED = np.arange(1, 9)


def _mapping(method="ebs"):
    return load_config([preset_path("offroad")], method=method).mapping


# --- the protocol ------------------------------------------------------------------------------------------------
def test_seeds_train_every_network_once_per_seed_and_pools_follow():
    config, _ = load_experiment("paper-unseen")
    assert len(config.networks) == 6 * 3 and len(config.conditions) == 12 * 3 and len(config.pools) == 6 * 3
    assert config.networks["summer-25pct@s2"].seed == 2 and config.networks["summer-25pct@s2"].fraction == 0.25
    assert config.conditions["other-domain-b@s3"].network == "autumn@s3"
    assert config.pools["in-domain@s1"] == ["in-domain-a@s1", "in-domain-b@s1"]
    assert seed_group("subset-10pct@s3") == "subset-10pct" and seed_group("in-domain") == "in-domain"


def test_quick_scales_the_study_down_and_keeps_its_shape():
    config, _ = load_experiment("paper-unseen", quick=True)
    assert {s.world for s in config.sequences.values()} == {"tiny"}
    assert {n.epochs for n in config.networks.values()} == {1}
    assert len(config.conditions) == 12 * 2  # its two seeds
    with pytest.raises(ConfigError, match="quick section"):
        load_experiment("demo", quick=True)


def test_a_drawn_subset_depends_on_the_seed_and_the_first_one_does_not():
    random = [_subset(150, NetworkSpec(fraction=0.25, subset="random", seed=s)) for s in (1, 2, 1)]
    assert len(random[0]) == 38 and random[0] == random[2] and random[0] != random[1]
    assert random[0] == sorted(set(random[0])) and max(random[0]) < 150 and max(random[0]) > 37  # spread over the drive
    first = [_subset(150, NetworkSpec(fraction=0.25, seed=s)) for s in (1, 2)]
    assert first[0] == first[1] == list(range(38))
    assert _subset(3, NetworkSpec(fraction=0.01, subset="random")) and _subset(10, NetworkSpec()) == list(range(10))


@pytest.mark.parametrize("bad, message", [("subset: sometimes", "subset must be first or random"),
                                          ("seeds: [1, 1]", "seeds must be distinct")])
def test_protocol_config_errors_name_the_key(tmp_path, bad, message):
    text = (load_experiment.__globals__["experiments_dir"]() / "paper-unseen.yaml").read_text()
    if bad.startswith("subset"):
        text = text.replace("subset: random, epochs: 36}", f"{bad}, epochs: 36}}", 1)
    else:
        text = text.replace("seeds: [1, 2, 3]", bad)
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_experiment(path)


def test_too_few_training_frames_is_one_clear_line(tmp_path, capsys):
    text = (load_experiment.__globals__["experiments_dir"]() / "paper-unseen.yaml").read_text()
    path = tmp_path / "few.yaml"
    path.write_text(text.replace("sequences: {world: tiny, frames: 30, spacing_m: 0.5}", "sequences: {world: tiny, frames: 10, spacing_m: 0.5}"))
    assert main(["experiment", str(path), "--quick", "--quiet", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "networks.summer-25pct@s1: fraction 0.25 of train-summer is 2 frames: 2 images are too few" in err and "Traceback" not in err


def test_the_quick_study_runs_with_its_spread_and_diagnostics(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["experiment", "paper-unseen", "--quick", "--quiet", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "[study] 1 of 24 conditions" in err and "(and the training still to come, not yet timed)" not in err.split("[study] 1 of")[1]
    assert "[study] 24 of 24 conditions" in err and "about 0 min left" in err
    text = (out / "results.md").read_text()
    assert "over 2 training seeds (1, 2): mean ± sd" in text and "## Uncertainty diagnostics" in text
    assert "| two-other-domains / ebs |" in text and "| subset-10pct |" in text
    spread = json.loads((out / "spread.json").read_text())
    assert set(spread) == {"in-domain", "subset-50pct", "subset-25pct", "subset-10pct", "other-domain", "two-other-domains"}
    assert spread["in-domain"]["ebs"]["seeds"] == 2 and len(spread["in-domain"]["ebs"]["mIoU"]) == 2
    # ebs-learned is mapped with the lengths learned for convbki on each network's training drive
    assert spread["subset-10pct"]["ebs-learned"]["seeds"] == 2
    learned = load_map(out / "maps/subset-10pct-a@s1/ebs-learned.npz").config.convbki.lengths_file
    assert learned == load_map(out / "maps/subset-10pct-a@s1/convbki.npz").config.convbki.lengths_file
    assert learned.startswith(str(out / "cache" / "convbki"))
    summary = json.loads((out / "diagnostics.json").read_text())
    ebs = summary["in-domain"]["methods"]["ebs"]
    assert 0.2 < ebs["dropped_share"] <= 0.3 + 1e-9  # offroad drops 30 % per insertion (ties are kept)
    assert summary["in-domain"]["methods"]["s-csm"]["dropped_share"] == 0
    for group in spread:
        assert (out / f"diagnostics_{group}.png").stat().st_size > 10_000
    # a rerun reads every diagnostic from its cache and writes the same tables
    before = (out / "diagnostics.json").read_text()
    assert main(["experiment", "paper-unseen", "--quick", "--quiet", "--out", str(out)]) == 0
    assert (out / "diagnostics.json").read_text() == before


# --- the diagnostics against plain counting -------------------------------------------------------------------------
def test_merged_metrics_equal_the_metrics_of_all_inputs():
    rng = np.random.default_rng(0)
    parts = []
    for n in (0, 1, 500):
        p = rng.dirichlet(np.ones(9), n)
        parts.append((p, rng.uniform(0, 1, n), rng.integers(0, 9, n)))
    merged = SegmentationMetrics(9)
    for p, u, t in parts:
        one = SegmentationMetrics(9)
        if len(t):
            one.update(p, u, t)
        merged = merged.merged(one)
    whole = SegmentationMetrics(9)
    whole.update(*(np.concatenate(x) for x in zip(*parts)))
    assert merged.ece == pytest.approx(whole.ece, rel=1e-12) and merged.uncertainty_auroc == whole.uncertainty_auroc
    np.testing.assert_array_equal(merged.confusion, whole.confusion)
    with pytest.raises(ValueError, match="cannot merge"):
        merged.merged(SegmentationMetrics(5))


def _insertion(rng, n, resolution):
    points = rng.uniform(-50, 50, (n, 3))
    u = rng.uniform(0, 1, n)
    truth = rng.integers(0, 9, n)
    right = rng.random(n) < 0.7
    predicted = np.where(right, truth, (truth + 1) % 9)
    return points, u, right, truth, predicted


def test_method_diagnostics_count_what_the_mapper_would_do():
    rng = np.random.default_rng(1)
    mapping = _mapping("ebs")
    res = mapping.resolution_m
    insertions = [_insertion(rng, n, res) for n in (0, 1, 2000)]
    d = us.method_diagnostics(mapping, 9, insertions, SCORED)
    dropped = dropped_right = short = nothing = points = 0
    for pts, u, right, truth, _ in insertions:
        keep = uncertainty_quantile_mask(u, mapping.keep_quantile)[0] if len(u) else np.ones(0, bool)
        scored = np.isin(truth, SCORED)
        points += scored.sum()
        dropped += (~keep & scored).sum()
        dropped_right += (~keep & scored & right).sum()
        kept = keep & scored
        lengths = mapping.length_m * mapping.beta * np.exp(1 - mapping.gamma * u[kept])
        short += (lengths < res / 2).sum()
        centers = (np.floor(pts[kept] / res) + 0.5) * res
        nothing += (np.linalg.norm(pts[kept] - centers, axis=1) >= lengths).sum()
    assert (d.points, d.dropped, d.dropped_right, d.kept_short, d.kept_reaching_nothing) == (points, dropped, dropped_right, short, nothing)
    assert d.length_hist.sum() == points - dropped and d.adaptive_length
    truth = np.concatenate([i[3] for i in insertions])
    np.testing.assert_array_equal(d.class_points, np.bincount(truth[np.isin(truth, SCORED)], minlength=9))
    assert d.class_dropped.sum() == dropped
    csm = us.method_diagnostics(_mapping("s-csm"), 9, insertions, SCORED)
    assert csm.dropped == 0 and csm.kept_reaching_nothing == 0 and not csm.adaptive_length  # 0.3 m reaches any own center


def test_a_point_on_a_voxel_face_far_away_reaches_nothing_with_a_short_kernel():
    mapping = dataclasses.replace(_mapping("ebs"), uncertainty_threshold=False)
    res = mapping.resolution_m
    far = res * 13_333_333  # a voxel face 4,000 km out: float64 keeps it where it is
    on_center = np.array([[far + 0.5 * res, 0.5 * res, 0.5 * res]])
    on_face = np.array([[far, 0.5 * res, 0.5 * res]])  # half a voxel from its center
    for pts, u, expect in ((on_center, 0.99, 0), (on_face, 0.99, 1), (on_face, 0.0, 0)):
        d = us.method_diagnostics(mapping, 9, [(pts, np.array([u]), np.array([True]), np.array([1]), np.array([1]))], SCORED)
        assert d.kept_reaching_nothing == expect, (pts, u)


class _Query:
    def __init__(self, label, variance):
        self.result = type("R", (), {"label": label, "variance": variance, "state": np.full(len(label), VoxelState.OCCUPIED, np.int8)})

    def query(self, points):
        return self.result


def test_error_rate_by_variance_decile_ranks_ties_and_counts_every_query():
    n = 1000
    variance = np.repeat(np.arange(5, dtype=float), 200)  # ties across decile edges
    truth = np.ones(n, np.int64)
    label = np.where(variance >= 3, 2, 1)  # the two most variant fifths are wrong
    d = us.method_diagnostics(_mapping("s-csm"), 9, [], SCORED, mapper=_Query(label, variance), gt=(np.zeros((n, 3)), truth))
    assert d.decile_queries.sum() == n
    np.testing.assert_array_equal(d.decile_errors / d.decile_queries, [0] * 6 + [1] * 4)


def test_condition_diagnostics_survive_their_cache_and_merge():
    rng = np.random.default_rng(2)
    metrics = SegmentationMetrics(9)
    metrics.update(rng.dirichlet(np.ones(9), 50), rng.uniform(0, 1, 50), rng.integers(0, 9, 50))
    method = us.method_diagnostics(_mapping("ebs"), 9, [_insertion(rng, 300, 0.3)], SCORED, brier=(1.0, 2.0, 3.0))
    d = us.ConditionDiagnostics(metrics, metrics, {"ebs": method})
    back = us.ConditionDiagnostics.from_arrays(json.loads(json.dumps(d.arrays())))
    assert back.summary() == d.summary()
    both = back.merge(d)
    assert both.methods["ebs"].points == 2 * method.points and both.points.bin_count.sum() == 100
    assert both.summary()["methods"]["ebs"]["brier_analytic"] == 2.0


# --- the remedy: the threshold per predicted class ------------------------------------------------------------------
def test_per_class_threshold_keeps_each_classes_surest_share():
    from evsemmap_warp.core.integrators import per_class_quantile_mask

    rng = np.random.default_rng(3)
    u = np.round(rng.uniform(0, 1, 3000), 2)  # ties
    predicted = rng.choice(9, 3000, p=[0.02] + [0.0] + [0.7] + [0.28 / 6] * 6)  # one class absent, one large
    keep = per_class_quantile_mask(u, predicted, 0.7)
    for c in range(9):
        rows = predicted == c
        if rows.any():
            k = min(int(np.floor(rows.sum() * 0.7)), rows.sum() - 1)
            np.testing.assert_array_equal(keep[rows], u[rows] <= np.sort(u[rows])[k])
    one = per_class_quantile_mask(np.array([0.9]), np.array([4]), 0.7)
    assert one.tolist() == [True] and per_class_quantile_mask(np.zeros(0), np.zeros(0, int), 0.7).shape == (0,)


def test_a_map_with_the_threshold_per_class_is_ebs_on_the_points_it_keeps():
    from evsemmap_warp.core.integrators import per_class_quantile_mask
    from evsemmap_warp.core.mapper import Mapper

    rng = np.random.default_rng(4)
    mapping = _mapping("ebs-per-class")
    assert mapping.threshold_scope.value == "predicted-class"
    points = rng.uniform(0, 6, (4000, 3))
    alpha = 1 + rng.gamma(0.5, 4, (4000, 9))
    alpha[:, 7] += np.where(points[:, 0] < 3, 30, 0)  # one confident half, one unsure half
    u = 9 / alpha.sum(axis=1)
    keep = per_class_quantile_mask(u, alpha.argmax(axis=1), mapping.keep_quantile)
    maps = {}
    for name, config, rows in (("per class", mapping, slice(None)), ("ebs on the kept points", dataclasses.replace(mapping, uncertainty_threshold=False), keep),
                               ("ebs", dataclasses.replace(mapping, threshold_scope=type(mapping.threshold_scope)("insertion")), slice(None))):
        mapper = Mapper(config, num_classes=9, origin=(0.0, 0.0, 0.0))
        mapper.integrate(points[rows], alpha[rows], payload_type="alpha")
        maps[name] = mapper.voxels().arrays
    np.testing.assert_array_equal(maps["per class"].index, maps["ebs on the kept points"].index)
    np.testing.assert_array_equal(maps["per class"].evidence, maps["ebs on the kept points"].evidence)
    assert len(maps["ebs"].index) != len(maps["per class"].index) or not np.array_equal(maps["ebs"].evidence, maps["per class"].evidence)

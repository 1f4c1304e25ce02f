"""The cost model from evidence and the cost file's layering (evsemmap_warp/terrain/config.py, layers.py;
docs/terrain.md): a cell costs what the table says for the class its evidence shows, however little there is,
and how little is a band of its own; a partial cost file changes exactly the keys it names."""

import dataclasses
from dataclasses import replace

import numpy as np
import pytest
import yaml

from evsemmap_warp.apps.cli import main
from evsemmap_warp.classes import class_set
from evsemmap_warp.config import ConfigError, load_config
from evsemmap_warp.core.mapper import Mapper
from evsemmap_warp.core.voxel_map import VoxelArrays
from evsemmap_warp.terrain import CostSettings, LayerSettings, compute_layers, default_costs_path, load_terrain_config
from evsemmap_warp.terrain.layers import class_cost, subjective_opinion

CLASSES = class_set().names
C = {name: i for i, name in enumerate(CLASSES)}


def _alpha(prior=1.0, **evidence):
    alpha = np.full((1, len(CLASSES)), prior)
    for name, amount in evidence.items():
        alpha[0, C[name]] += amount
    return alpha


def test_the_dataclass_defaults_are_the_default_files():
    table = yaml.safe_load(default_costs_path().read_text())
    layers = LayerSettings()
    for key, value in table["layers"].items():
        assert getattr(layers, key) == (tuple(value) if isinstance(value, list) else value), key
    costs = CostSettings()
    for key, value in table["costs"].items():
        if key not in ("classes", "lethal_classes"):
            assert getattr(costs, key) == value, key


def test_a_voxel_costs_its_evidences_class_mix_however_much_there_is():
    config = load_terrain_config()
    table = config.costs.classes
    # the uncommitted mass (the prior's share) costs nothing: a thin and a thick road both cost the road's
    for name in ("paved", "unpaved", "grass"):
        for amount in (0.3, 9.0, 5000.0):
            mean, _, lethal = class_cost(_alpha(**{name: amount}), config, CLASSES)
            assert mean[0] == pytest.approx(table[name]) and lethal[0] == 0.0
    mean, _, _ = class_cost(_alpha(paved=3.0, grass=1.0), config, CLASSES)
    assert mean[0] == pytest.approx(0.75 * table["paved"] + 0.25 * table["grass"])
    _, _, lethal = class_cost(_alpha(object=2.0, grass=2.0), config, CLASSES)
    assert lethal[0] == pytest.approx(0.5)  # the lethal classes' share of the evidence, not of the prior's too (4/13)
    mean, _, lethal = class_cost(_alpha(), config, CLASSES)  # no evidence at all (min_evidence 0): the unknown's cost
    assert mean[0] == config.costs.unknown_cost and lethal[0] == 0.0
    # the expected rule pulls the unobserved voxel to the table's mean and a thin road towards it
    expected = replace(config, costs=replace(config.costs, rule="expected"))
    assert class_cost(_alpha(), expected, CLASSES)[0][0] == pytest.approx(np.mean(list(table.values())))
    assert class_cost(_alpha(paved=9.0), expected, CLASSES)[0][0] == pytest.approx((table["paved"] + np.mean(list(table.values()))) / 2)


def test_a_cell_below_the_evidence_threshold_is_unknown_not_costed():
    voxels = {(i, j, 0): ("paved" if i < 10 else "grass", 400.0) for i in range(20) for j in range(20)}
    voxels[(15, 15, 0)] = ("grass", 0.1)  # a kernel tail: below the default min_evidence 0.2
    layers = compute_layers(_map(voxels))
    assert np.isnan(layers.bands["traversability_cost"][::-1].T[15, 15]) and layers.bands["known"][::-1].T[15, 15] == 0


@pytest.mark.parametrize("prior", [1.0, 0.001, 3.0])
def test_belief_and_uncommitted_mass_add_up_to_one(prior):
    rng = np.random.default_rng(7)
    alpha = prior + rng.exponential(3.0, (50, len(CLASSES)))
    alpha[0] = prior  # nothing observed
    belief, uncommitted = subjective_opinion(alpha, prior)
    np.testing.assert_allclose(belief.sum(axis=1) + uncommitted, 1.0)
    assert uncommitted[0] == pytest.approx(1.0) and (belief >= 0).all()
    np.testing.assert_allclose(uncommitted, len(CLASSES) * prior / alpha.sum(axis=1))


def _map(voxels) -> Mapper:
    """A map of ``voxels``: {(i, j, k): (class name, evidence) or {class name: evidence, ...}}."""
    keys = sorted(voxels)
    evidence = np.zeros((len(keys), len(CLASSES)))
    for row, key in enumerate(keys):
        value = voxels[key]
        for name, amount in (value.items() if isinstance(value, dict) else [value]):
            evidence[row, C[name]] = amount
    n = len(keys)
    mapper = Mapper(load_config([], method="ebs").mapping, len(CLASSES), class_names=CLASSES, workers=1)
    mapper.load_voxels(VoxelArrays(index=np.array(keys, np.int64), evidence=evidence, weight_sum=np.full(n, 2.0),
                                   weighted_uncertainty_sum=np.full(n, 0.2), hits=np.full(n, 3, np.int64), touched=np.ones(n, bool),
                                   weighted_height_sum=np.zeros(n)))
    return mapper


def test_a_road_beside_grass_costs_the_table_and_a_thin_cell_is_marked_uncommitted():
    voxels = {(i, j, 0): ("paved" if i < 10 else "grass", 400.0) for i in range(20) for j in range(20)}
    voxels[(3, 3, 0)] = ("paved", 0.3)  # seen once, from afar
    voxels[(12, 5, 0)] = {"grass": 300.0, "paved": 100.0}  # where the labels meet
    layers = compute_layers(_map(voxels))
    cost = layers.bands["traversability_cost"][::-1].T  # [i, j]
    table = load_terrain_config().costs.classes
    assert np.median(cost[:10]) == pytest.approx(table["paved"], abs=1e-6)
    assert np.median(cost[10:]) == pytest.approx(table["grass"], abs=1e-6)
    assert cost[3, 3] == pytest.approx(table["paved"])  # the road's cost, not an average ...
    uncommitted = layers.bands["surface_uncommitted"][::-1].T
    assert uncommitted[3, 3] == pytest.approx(9 / 9.3) and uncommitted[5, 5] == pytest.approx(9 / 409)  # ... marked as barely seen
    assert cost[12, 5] == pytest.approx(0.75 * table["grass"] + 0.25 * table["paved"])
    # the conflict, 1 - e_label / sum e: how much of what was seen disagrees with the label, whatever its amount
    conflict = layers.bands["surface_conflict"][::-1].T
    assert conflict[12, 5] == pytest.approx(0.25) and conflict[3, 3] == 0.0 and conflict[5, 5] == 0.0


def _write(tmp_path, text):
    path = tmp_path / "my_costs.yaml"
    path.write_text(text)
    return path


def test_a_partial_file_overrides_exactly_the_keys_it_names(tmp_path):
    default = load_terrain_config()
    mine = load_terrain_config(_write(tmp_path, "costs:\n  classes: {grass: 0.6}\n  unknown_cost: 0.8\n"))
    assert mine.layers == default.layers  # min_evidence 0.2 and the 9 x 9 plane, not the dataclass's old 0.0 and 5 x 5
    assert mine.costs.classes == default.costs.classes | {"grass": 0.6}
    assert mine.costs == replace(default.costs, classes=mine.costs.classes, unknown_cost=0.8)
    assert mine.named == {"costs.classes", "costs.classes.grass", "costs.unknown_cost"}
    layers_only = load_terrain_config(_write(tmp_path, "layers:\n  min_evidence: 0.5\n"))
    assert layers_only.costs == default.costs and layers_only.layers == replace(default.layers, min_evidence=0.5)


def test_a_file_for_another_class_set_is_checked_against_its_map_only(tmp_path):
    names = ["free", "ground", "wall", "obstacle"]
    path = _write(tmp_path, "layers:\n  surface_classes: [ground]\ncosts:\n  classes: {free: 0.0, ground: 0.1, wall: 1.0, obstacle: 1.0}\n"
                            "  lethal_classes: [wall, obstacle]\n")
    load_terrain_config(path).check_classes(names)  # the default table's nine names are not this file's words
    no_surface = _write(tmp_path, "costs:\n  classes: {free: 0.0, ground: 0.1, wall: 1.0, obstacle: 1.0}\n")
    with pytest.raises(ConfigError, match=r"layers.surface_classes .* holds none of the map's classes"):
        load_terrain_config(no_surface).check_classes(names)
    missing = _write(tmp_path, "layers:\n  surface_classes: [ground]\ncosts:\n  classes: {free: 0.0, ground: 0.1}\n")
    with pytest.raises(ConfigError, match=r"costs.classes gives no cost for the map's classes \['wall', 'obstacle'\]"):
        load_terrain_config(missing).check_classes(names)
    with pytest.raises(ConfigError, match=r"costs.rule = 'cheapest' is not a cost rule"):
        load_terrain_config(_write(tmp_path, "costs:\n  rule: cheapest\n"))
    with pytest.raises(ConfigError, match=r"costs.classes must be a mapping of class name to cost, got NoneType"):
        load_terrain_config(_write(tmp_path, "costs:\n  classes:\n"))


def test_dump_config_shows_the_resolved_terrain_settings(tmp_path, capsys):
    path = _write(tmp_path, "costs:\n  classes: {grass: 0.6}\n")
    assert main(["dump-config", "rellis3d", "--costs", str(path)]) == 0
    terrain = yaml.safe_load(capsys.readouterr().out)["terrain"]
    default = load_terrain_config()
    assert terrain["source"] == str(path)
    assert terrain["layers"] == {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(default.layers).items()}
    assert terrain["costs"]["classes"]["grass"] == 0.6 and terrain["costs"]["rule"] == "evidential"

"""The cost model from evidence and the cost file's layering (evsemmap_warp/terrain/config.py, layers.py;
docs/terrain.md): a well-observed cell costs what the table says for its class, a barely observed one the
cost of the unknown; a partial cost file changes exactly the keys it names."""

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


def test_a_well_observed_cell_costs_its_class_and_an_unobserved_one_the_unknown():
    config = load_terrain_config()
    table = config.costs.classes
    for name in ("paved", "unpaved", "grass"):
        mean, _, lethal = class_cost(_alpha(**{name: 5000.0}), config, CLASSES)
        assert mean[0] == pytest.approx(table[name], abs=0.005) and lethal[0] == 0.0
    mean, _, lethal = class_cost(_alpha(), config, CLASSES)
    assert mean[0] == pytest.approx(config.costs.unknown_cost) and lethal[0] == 0.0
    # the expected rule pulls the unobserved cell to the table's mean instead
    expected = replace(config, costs=replace(config.costs, rule="expected"))
    assert class_cost(_alpha(), expected, CLASSES)[0][0] == pytest.approx(np.mean(list(table.values())))
    # half road, half unknown: halfway between road's cost and the unknown's
    half, _, _ = class_cost(_alpha(paved=9.0), config, CLASSES)
    assert half[0] == pytest.approx((table["paved"] + config.costs.unknown_cost) / 2)
    # the lethal share is the lethal classes' belief, not the prior's share of them
    _, _, lethal = class_cost(_alpha(object=9.0, vegetation=9.0), config, CLASSES)
    assert lethal[0] == pytest.approx(18 / 27)


def test_the_known_rule_costs_a_voxel_by_its_evidences_own_class_mix():
    config = load_terrain_config()
    known = replace(config, costs=replace(config.costs, rule="known"))
    table = config.costs.classes
    # however thin the evidence, its own mix: the prior's share (the uncommitted mass) costs nothing here
    for amount in (0.3, 9.0, 5000.0):
        mean, _, lethal = class_cost(_alpha(paved=amount), known, CLASSES)
        assert mean[0] == pytest.approx(table["paved"]) and lethal[0] == 0.0
    mean, _, _ = class_cost(_alpha(paved=3.0, grass=1.0), known, CLASSES)
    assert mean[0] == pytest.approx(0.75 * table["paved"] + 0.25 * table["grass"])
    _, _, lethal = class_cost(_alpha(object=2.0, grass=2.0), known, CLASSES)
    assert lethal[0] == pytest.approx(0.5)  # the lethal classes' share of the evidence (evidential: their belief, 4/13)
    mean, _, lethal = class_cost(_alpha(), known, CLASSES)  # no evidence at all (min_evidence 0): the unknown's cost
    assert mean[0] == config.costs.unknown_cost and lethal[0] == 0.0


def test_under_the_known_rule_a_cell_below_the_evidence_threshold_is_unknown_not_costed():
    voxels = {(i, j, 0): ("paved" if i < 10 else "grass", 400.0) for i in range(20) for j in range(20)}
    voxels[(3, 3, 0)] = ("paved", 0.3)  # seen once, from afar: known at the default min_evidence 0.2
    voxels[(15, 15, 0)] = ("grass", 0.1)  # a kernel tail: below it
    config = load_terrain_config()
    layers = compute_layers(_map(voxels), config=replace(config, costs=replace(config.costs, rule="known")))
    cost = layers.bands["traversability_cost"][::-1].T
    assert cost[3, 3] == pytest.approx(config.costs.classes["paved"])
    assert np.isnan(cost[15, 15]) and layers.bands["known"][::-1].T[15, 15] == 0
    assert np.median(cost[10:][np.isfinite(cost[10:])]) == pytest.approx(config.costs.classes["grass"], abs=0.01)


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
    keys = sorted(voxels)
    evidence = np.zeros((len(keys), len(CLASSES)))
    for row, key in enumerate(keys):
        name, amount = voxels[key]
        evidence[row, C[name]] = amount
    n = len(keys)
    mapper = Mapper(load_config([], method="ebs").mapping, len(CLASSES), class_names=CLASSES, workers=1)
    mapper.load_voxels(VoxelArrays(index=np.array(keys, np.int64), evidence=evidence, weight_sum=np.full(n, 2.0),
                                   weighted_uncertainty_sum=np.full(n, 0.2), hits=np.full(n, 3, np.int64), touched=np.ones(n, bool),
                                   weighted_height_sum=np.zeros(n)))
    return mapper


def test_a_road_beside_grass_costs_the_table_on_a_flat_plane():
    voxels = {(i, j, 0): ("paved" if i < 10 else "grass", 400.0) for i in range(20) for j in range(20)}
    voxels[(3, 3, 0)] = ("paved", 0.3)  # seen once, from afar
    layers = compute_layers(_map(voxels))
    cost = layers.bands["traversability_cost"][::-1].T  # [i, j]
    table = load_terrain_config().costs.classes
    assert np.median(cost[:10][np.arange(10) != 3]) == pytest.approx(table["paved"], abs=0.01)
    assert np.median(cost[10:]) == pytest.approx(table["grass"], abs=0.01)
    assert cost[3, 3] > 0.45  # mostly the unknown's cost, not the road's
    # the surface doubt, 1 - b_label: little where a class has all the evidence, most where there is hardly any
    doubt = layers.bands["surface_doubt"][::-1].T
    assert doubt[5, 5] == pytest.approx(9 / 409) and doubt[3, 3] == pytest.approx(1 - 0.3 / 9.3)


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

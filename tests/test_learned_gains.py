"""Issue 51: ebs-learned, EBS with per-class gains from ConvBKI's lengths learned on a labelled drive."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError, Fusion, Media, load_config, preset_path
from evsemmap_warp.core.mapper import Mapper, load_map, save_map
from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.methods import convbki
from evsemmap_warp.reference import scatter as ref

from conftest import run_cli

K = 5
REPO = Path(__file__).resolve().parents[1]


def _lengths_file(tmp_path, horizontal, vertical=None) -> Path:
    path = tmp_path / "lengths.json"
    path.write_text(json.dumps({"ell_h": list(horizontal), "ell_z": list(vertical if vertical is not None else horizontal)}))
    return path


def _config(method="ebs-learned", lengths_file=""):
    mapping = load_config([preset_path("offroad")], method=method).mapping
    return mapping.replace(convbki={"lengths_file": str(lengths_file)}) if lengths_file else mapping


def _scan(seed, n=1500):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-4, 4, (n, 3)).astype(np.float32).astype(np.float64)
    return points, rng.gamma(0.7, 6.0, (n, K)) + 1.0


def test_gains_are_the_kernel_mass_over_the_mean():
    lengths = convbki.ConvBkiLengths(np.array([0.2, 0.45, 0.7, 1.0, 0.3]), np.array([0.2, 0.45, 0.7, 1.0, 0.3]))
    gains = convbki.class_gains(lengths, 0.3, 2)
    mass = convbki.stencil_weights(lengths, 0.3, 2).sum(axis=0)
    np.testing.assert_allclose(gains, mass / mass.mean())
    assert gains.mean() == pytest.approx(1.0)
    # a kernel shorter than a voxel reaches its own voxel only (mass 1); longer ones gain with their length
    assert gains[0] == gains[4] and gains[0] < gains[1] < gains[2] < gains[3]
    assert convbki.class_gains(convbki.default_lengths(K), 0.3, 2).tolist() == [1.0] * K


def test_ebs_learned_matches_the_numpy_pipeline_with_its_gains(tmp_path, device):
    horizontal, vertical = [0.25, 0.9, 0.5, 1.0, 0.6], [0.3, 0.4, 1.0, 0.7, 0.2]
    cfg = _config(lengths_file=_lengths_file(tmp_path, horizontal, vertical))
    points, alpha = _scan(7)
    mapper = Mapper(cfg, K, device=device)
    mapper.integrate(points, alpha, payload_type="alpha")
    gains = convbki.class_gains(convbki.ConvBkiLengths(np.array(horizontal), np.array(vertical)), cfg.resolution_m, cfg.convbki.stencil_half)
    u = K / alpha.sum(1)
    keep = u <= np.sort(u)[min(int(np.floor(len(u) * cfg.keep_quantile)), len(u) - 1)]
    lengths = cfg.length_m * cfg.beta * np.exp(1 - cfg.gamma * u)
    weights = alpha / alpha.sum(1, keepdims=True) * gains
    expected = ref.scatter_points(points[keep], None, weights[keep], lengths[keep], u[keep], None, sc.MODE_RADIUS, cfg.resolution_m, 0.0,
                                  cfg.sigma0, 1, K)
    arrays, _ = mapper.voxels()
    got = {tuple(v): i for i, v in enumerate(arrays.index)}
    want = {tuple(v): i for i, v in enumerate(expected.voxel_index)}
    assert len(set(got) ^ set(want)) <= 0.002 * len(want)  # the d ~ l band of test_scatter; weights there are ~0
    common = sorted(set(got) & set(want))
    np.testing.assert_allclose(arrays.evidence[[got[v] for v in common]], expected.alpha_increment[[want[v] for v in common]], rtol=1e-4, atol=1e-5)


def test_with_one_length_for_every_class_it_is_ebs_bit_for_bit(tmp_path):
    points, alpha = _scan(8)
    maps = {}
    for method, lengths_file in (("ebs", ""), ("ebs-learned", _lengths_file(tmp_path, [0.7] * K))):
        mapper = Mapper(_config(method, lengths_file), K)
        mapper.integrate(points, alpha, payload_type="alpha")
        maps[method] = mapper.voxels().arrays
    np.testing.assert_array_equal(maps["ebs"].index, maps["ebs-learned"].index)
    np.testing.assert_array_equal(maps["ebs"].evidence, maps["ebs-learned"].evidence)


def test_other_methods_record_no_class_gains_and_ebs_learned_reads_back(tmp_path):
    assert "class_gains" not in _config("ebs").as_dict()  # every other method's map and store keep their bytes
    cfg = _config(lengths_file=_lengths_file(tmp_path, [0.3, 0.6, 0.9, 1.0, 0.5]))
    mapper = Mapper(cfg, K)
    mapper.integrate(*_scan(9, 300), payload_type="alpha")
    save_map(tmp_path / "m.npz", mapper)
    loaded = load_map(tmp_path / "m.npz")
    assert loaded.config.class_gains and loaded.config.method == "ebs-learned"


@pytest.mark.parametrize("change", [{"fusion": Fusion.DEMPSTER}, {"media": Media.ONEHOT}])
def test_gains_apply_to_soft_media_with_bayes_fusion_only(change):
    with pytest.raises(ConfigError, match=r"mapping\.class_gains = True: class gains scale the class probabilities"):
        dataclasses.replace(_config(), **change)


def test_without_learned_lengths_it_is_one_line_naming_the_key(tmp_path, capsys):
    toy = REPO / "configs/datasets/sbki_toy.yaml"  # its labels, in the clean mode
    clean = tmp_path / "clean.yaml"
    clean.write_text("mapping:\n  compat: clean\n")
    line = run_cli(capsys, "map", toy, clean, "--method", "ebs-learned", "--out", tmp_path / "m.npz", "--quiet")
    assert line.startswith("evsemmap: error: mapping.convbki.lengths_file = '': method ebs-learned") and "evsemmap train-convbki" in line
    extra = tmp_path / "lengths.yaml"
    extra.write_text(f"mapping:\n  convbki:\n    lengths_file: {_lengths_file(tmp_path, [0.4] * 9)}\n")
    assert run_cli(capsys, "map", toy, clean, extra, "--method", "ebs-learned", "--out", tmp_path / "m.npz").endswith(
        "lengths.json: ell_h has 9 values, the map has 4 classes")
    _lengths_file(tmp_path, [0.4, 0.2, 0.9, 0.6])  # the toy's four classes
    assert main(["map", str(toy), str(clean), str(extra), "--method", "ebs-learned", "--out", str(tmp_path / "m.npz"), "--quiet"]) == 0
    assert load_map(tmp_path / "m.npz").config.class_gains

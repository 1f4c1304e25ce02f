"""Configs: every shipped file loads, composition order, and errors that name file and key."""

import pytest

from evsemmap_warp.config import Compat, ConfigError, Kernel, Media, available_methods, load_config

from conftest import REPO

PRESETS = sorted((REPO / "configs" / "presets").glob("*.yaml"))
DATASETS = sorted((REPO / "configs" / "datasets").glob("*.yaml"))


def test_methods_ship_as_config_files():
    assert set(available_methods()) >= {"s-csm", "s-bki", "ebs", "prob", "prob-adap", "prob-thr", "prob-adap-thr"}


@pytest.mark.parametrize("method", available_methods())
@pytest.mark.parametrize("preset", PRESETS, ids=lambda p: p.stem)
def test_every_method_combines_with_every_preset(method, preset):
    if preset.stem == "release" and method not in ("ebs", "prob-adap-thr", "dempster"):
        # the release mode reproduces the released ebs and dempster only; others are refused by key
        with pytest.raises(ConfigError, match=r"mapping\.(kernel|media|adaptive_length|uncertainty_threshold|threshold_scope)"):
            load_config([preset], method=method)
        return
    run = load_config([preset], method=method)
    assert run.mapping.method == method


def test_switches_and_numbers_land_where_they_belong():
    run = load_config([REPO / "configs/presets/offroad.yaml"], method="prob-thr")
    m = run.mapping
    assert (m.kernel, m.media, m.adaptive_length, m.uncertainty_threshold) == (Kernel.SPARSE, Media.SOFT, False, True)
    assert (m.resolution_m, m.length_m, m.beta, m.gamma, m.uncertainty_drop_fraction) == (0.3, 0.3, 1.0, 3.0, 0.3)
    toy = load_config([REPO / "configs/datasets/sbki_toy.yaml"], method="s-csm")
    assert toy.mapping.compat is Compat.SBKI and toy.mapping.sigma0 == 10.0 and toy.dataset.num_classes == 4
    assert toy.dataset.resolve_path().exists()


def test_dataset_paths_stay_relative_to_the_file_that_names_them(tmp_path):
    override = tmp_path / "labels.yaml"
    override.write_text("dataset:\n  payload: label\nmapping:\n  compat: sbki\n")
    run = load_config([REPO / "configs/datasets/sbki_toy.yaml", override], method="s-bki")
    assert run.dataset.resolve_path().exists() and run.dataset.config_dir == str((REPO / "configs/datasets").resolve())


def test_later_files_win(tmp_path):
    extra = tmp_path / "fine.yaml"
    extra.write_text("mapping:\n  resolution_m: 0.1\n")
    run = load_config([REPO / "configs/presets/rellis3d.yaml", extra], method="ebs")
    assert run.mapping.resolution_m == 0.1 and run.mapping.gamma == 10.0


@pytest.mark.parametrize(
    "text, message",
    [
        ("mapping:\n  resolution: 0.1\n", "unknown key mapping.resolution"),
        ("mapping:\n  resolution_m: -1\n", r"mapping.resolution_m = -1.0: must be > 0"),
        ("mapping:\n  uncertainty_drop_fraction: 1.0\n", "must lie in"),
        ("mapping:\n  block_depth: 2.5\n", "block_depth = 2.5 is not a valid"),
        ("mapping:\n  media: softmax\n", "media = 'softmax' is not a valid"),
        ("mapping:\n  compat: sbki\n", "the sbki compatibility mode reproduces S-BKI/S-CSM"),
        ("method:\n  sigma0: 3\n", "method.sigma0 is not a method switch"),
        ("mapings:\n  a: 1\n", r"unknown section\(s\) \['mapings'\]"),
        ("- 1\n- 2\n", "expected a mapping of sections"),
        ("mapping: [1\n", "not valid YAML"),
        ("dataset:\n  paths: [/nonexistent/a, nope]\n", None),
    ],
)
def test_bad_configs_name_the_file_and_key(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    if message is None:  # paths resolve lazily, when a dataset is opened
        with pytest.raises(ConfigError, match="none of these exists"):
            load_config([path], method="ebs").dataset.resolve_path()
        return
    with pytest.raises(ConfigError, match=message) as err:
        load_config([path], method="ebs")
    assert "bad.yaml" in str(err.value)


def test_unknown_method_lists_the_known_ones():
    with pytest.raises(ConfigError, match="unknown method 'nope'; available: convbki, dempster, ebs"):
        load_config([], method="nope")

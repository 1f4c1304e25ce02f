"""Configs: every shipped file loads, composition order, and errors that name file and key."""

import pytest

from evsemmap_warp.config import (Compat, ConfigError, Kernel, MappingConfig, Media, SbkiSettings, ScatterStrategy, available_methods,
                                  legacy_flat_dict, load_config)

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


# ------------------------------------------------------------------------- mode sections (issue 27)
OLD_FLAT = ("mapping:\n  block_depth: 3\n  ds_resolution_m: 0.05\n  free_resolution_m: 2.0\n  max_range_m: -1\n  ds_multiplier: -1\n"
            "  convbki_lengths_file: x.json\n  convbki_stencil_half: 1\n  scatter_strategy: atomic\n")
NEW_NESTED = ("mapping:\n  sbki: {block_depth: 3, ds_resolution_m: 0.05, free_resolution_m: 2.0, max_range_m: null}\n"
              "  release: {ds_multiplier: null}\n  convbki: {lengths_file: x.json, stencil_half: 1}\n  clean: {scatter_strategy: atomic}\n")


@pytest.fixture
def told(monkeypatch, capsys):
    """The deprecation lines printed since the last call (each said once per process: reset here)."""
    from evsemmap_warp import config

    monkeypatch.setattr(config, "_WARNED", set())
    capsys.readouterr()
    return lambda: [line for line in capsys.readouterr().err.splitlines() if "is deprecated" in line]


def test_old_flat_keys_load_into_the_sections_each_told_once(tmp_path, told):
    old, new = tmp_path / "old.yaml", tmp_path / "new.yaml"
    old.write_text(OLD_FLAT)
    new.write_text(NEW_NESTED)
    from_old = load_config([old], method="ebs").mapping
    lines = told()
    assert from_old == load_config([new], method="ebs").mapping and told() == []
    m = from_old
    assert (m.sbki.block_depth, m.sbki.ds_resolution_m, m.sbki.free_resolution_m, m.sbki.max_range_m) == (3, 0.05, 2.0, None)
    assert (m.release.ds_multiplier, m.convbki.lengths_file, m.convbki.stencil_half) == (None, "x.json", 1)
    assert m.clean.scatter_strategy is ScatterStrategy.ATOMIC
    moved = {"block_depth": "sbki.block_depth", "ds_resolution_m": "sbki.ds_resolution_m", "free_resolution_m": "sbki.free_resolution_m",
             "max_range_m": "sbki.max_range_m", "ds_multiplier": "release.ds_multiplier", "convbki_lengths_file": "convbki.lengths_file",
             "convbki_stencil_half": "convbki.stencil_half", "scatter_strategy": "clean.scatter_strategy"}
    assert sorted(lines) == sorted(f"evsemmap: warning: {old}: mapping.{k} is deprecated, use mapping.{v} (the old name goes in the next "
                                   f"release)" for k, v in moved.items())
    load_config([old], method="ebs")
    assert told() == []  # once per key


@pytest.mark.parametrize("text, expected", [
    ("max_range_m: 0", ("sbki", "max_range_m", None)),
    ("max_range_m: -5.5", ("sbki", "max_range_m", None)),
    ("max_range_m: 30", ("sbki", "max_range_m", 30.0)),
    ("ds_multiplier: 0", ("release", "ds_multiplier", 0)),
    ("ds_multiplier: 7", ("release", "ds_multiplier", 7)),
])
def test_old_sentinels_read_none_and_other_values_stay(tmp_path, told, text, expected):
    path = tmp_path / "old.yaml"
    path.write_text(f"mapping:\n  {text}\n")
    section, key, value = expected
    got = getattr(getattr(load_config([REPO / "configs/presets/release.yaml", path], method="ebs").mapping, section), key)
    assert got == value and type(got) is type(value)
    assert len(told()) == 1


def test_a_later_file_changes_one_key_of_a_section(tmp_path):
    ranged = tmp_path / "ranged.yaml"
    ranged.write_text("mapping:\n  sbki:\n    max_range_m: 30\n")
    m = load_config([REPO / "configs/presets/release.yaml", ranged], method="ebs").mapping
    assert (m.sbki.block_depth, m.sbki.ds_resolution_m, m.sbki.max_range_m) == (2, 0.01, 30.0)  # the preset's stay
    unset = tmp_path / "unset.yaml"
    unset.write_text("mapping:\n  sbki:\n    max_range_m: null\n")
    assert load_config([REPO / "configs/presets/release.yaml", ranged, unset], method="ebs").mapping.sbki.max_range_m is None


@pytest.mark.parametrize("text, message", [
    ("mapping:\n  sbki: {block_depth: 9}\n", r"mapping.sbki.block_depth = 9: must lie in 1..8"),
    ("mapping:\n  block_depth: 9\n", r"mapping.sbki.block_depth = 9: must lie in 1..8"),  # an old key names its new place
    ("mapping:\n  sbki: {max_range_m: -1}\n", r"mapping.sbki.max_range_m = -1.0: must be > 0 \(or null: no range filter\)"),
    ("mapping:\n  sbki: {ds_resolution_m: .nan}\n", r"ds_resolution_m = nan must be a finite number"),
    ("mapping:\n  release: {ds_multiplier: -1}\n", r"mapping.release.ds_multiplier = -1: must be >= 0"),
    ("mapping:\n  ds_multiplier: -2\n", r"mapping.release.ds_multiplier = -2: must be >= 0"),
    ("mapping:\n  convbki: {stencil_half: 9}\n", r"mapping.convbki.stencil_half = 9: must lie in 0..8"),
    ("mapping:\n  clean: {scatter_strategy: fast}\n", r"mapping.clean: scatter_strategy = 'fast' is not a valid ScatterStrategy"),
    ("mapping:\n  clean: {scatter_strategy: sorted}\n  fusion: dempster\n", r"mapping.clean.scatter_strategy = <ScatterStrategy.SORTED"),
    ("mapping:\n  sbki: {depth: 2}\n", r"unknown key mapping.sbki.depth; known: \['block_depth'"),
    ("mapping:\n  sbki: 2\n", r"mapping.sbki must be a mapping, got int"),
    ("mapping:\n  block_depth: 3\n  sbki: {block_depth: 2}\n", r"mapping.block_depth and mapping.sbki.block_depth are the same key"),
])
def test_section_errors_name_the_dotted_key(tmp_path, told, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        load_config([path], method="ebs")
    assert "bad.yaml" in str(err.value)


def test_the_sections_are_checked_where_the_config_is_built():
    with pytest.raises(ConfigError, match=r"^mapping.sbki.free_resolution_m = 0.0: must be > 0$"):
        MappingConfig(sbki=SbkiSettings(free_resolution_m=0.0))
    with pytest.raises(ConfigError, match=r"^mapping.sbki.max_range_m = inf: must be a finite number$"):
        MappingConfig().replace(sbki={"max_range_m": float("inf")})
    with pytest.raises(ConfigError, match=r"^mapping.clean = 'atomic': must be a CleanSettings$"):
        MappingConfig(clean="atomic")
    assert MappingConfig().replace(sbki={"block_depth": 3}).sbki == SbkiSettings(block_depth=3)


@pytest.mark.parametrize("method", available_methods())
@pytest.mark.parametrize("preset", PRESETS, ids=lambda p: p.stem)
def test_as_dict_reads_back_and_flattens_to_the_old_form(method, preset):
    try:
        m = load_config([preset], method=method).mapping
    except ConfigError:  # combinations the release mode refuses (test_every_method_combines_with_every_preset)
        return
    assert MappingConfig.from_dict(m.as_dict()) == m
    flat = legacy_flat_dict(m.as_dict())
    old_fields = {"method", "kernel", "fusion", "media", "adaptive_length", "uncertainty_threshold", "compat", "resolution_m", "prior",
                  "length_m", "beta", "gamma", "uncertainty_drop_fraction", "threshold_scope", "sigma0", "block_depth", "ds_resolution_m",
                  "free_resolution_m", "max_range_m", "scatter_strategy", "ds_multiplier", "convbki_lengths_file", "convbki_stencil_half"}
    assert set(flat) == old_fields
    assert MappingConfig.from_dict(flat) == m  # and the flat form reads back (map files written before)


def test_the_experiment_cache_key_of_an_unchanged_config_is_the_old_one():
    # store_v1 recorded MappingConfig.as_dict() as it was before the sections (and before threshold_scope)
    import json

    recorded = json.loads((REPO / "tests/data/store_v1/store/store.json").read_text())["mapping"]
    m = MappingConfig.from_dict(recorded)
    assert (m.sbki.max_range_m, m.release.ds_multiplier, m.clean.scatter_strategy) == (None, None, ScatterStrategy.ATOMIC)
    flat = legacy_flat_dict(m.as_dict())
    assert flat.pop("threshold_scope") == "insertion"  # map_and_score leaves it out when it is "insertion"
    assert flat == recorded | {"media": "soft"}  # renamed since (RENAMED_VALUES)
    assert legacy_flat_dict(MappingConfig().as_dict()) == {
        "method": "ebs", "kernel": "sparse", "fusion": "bayes", "media": "soft", "adaptive_length": True, "uncertainty_threshold": True,
        "compat": "clean", "resolution_m": 0.2, "prior": 1.0, "length_m": 0.2, "beta": 0.5, "gamma": 10.0, "uncertainty_drop_fraction": 0.1,
        "threshold_scope": "insertion", "sigma0": 1.0, "block_depth": 2, "ds_resolution_m": 0.1, "free_resolution_m": 4.0,
        "max_range_m": -1.0, "scatter_strategy": "atomic", "ds_multiplier": -1, "convbki_lengths_file": "", "convbki_stencil_half": 2}

"""Configs: every shipped file loads, composition order, and errors that name file and key."""

import pytest

from evsemmap_warp.config import (Compat, ConfigError, Kernel, MappingConfig, Media, SbkiSettings, ScatterStrategy, ThresholdScope,
                                  available_methods, load_config)

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
        with pytest.raises(ConfigError, match=r"mapping\.(kernel|media|adaptive_length|uncertainty_threshold|threshold_scope|class_gains)"):
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
        ("mapping:\n  sbki: {block_depth: 2.5}\n", "block_depth = 2.5 is not a valid"),
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


# ------------------------------------------------------------------------- mode sections
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
    ("mapping:\n  sbki: {max_range_m: -1}\n", r"mapping.sbki.max_range_m = -1.0: must be > 0 \(or null: no range filter\)"),
    ("mapping:\n  sbki: {ds_resolution_m: .nan}\n", r"ds_resolution_m = nan must be a finite number"),
    ("mapping:\n  release: {ds_multiplier: -1}\n", r"mapping.release.ds_multiplier = -1: must be >= 0"),
    ("mapping:\n  convbki: {stencil_half: 9}\n", r"mapping.convbki.stencil_half = 9: must lie in 0..8"),
    ("mapping:\n  clean: {scatter_strategy: fast}\n", r"mapping.clean: scatter_strategy = 'fast' is not a valid ScatterStrategy"),
    ("mapping:\n  clean: {scatter_strategy: sorted}\n  fusion: dempster\n", r"mapping.clean.scatter_strategy = <ScatterStrategy.SORTED"),
    ("mapping:\n  sbki: {depth: 2}\n", r"unknown key mapping.sbki.depth; known: \['block_depth'"),
    ("mapping:\n  sbki: 2\n", r"mapping.sbki must be a mapping, got int"),
])
def test_section_errors_name_the_dotted_key(tmp_path, text, message):
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
def test_as_dict_reads_back(method, preset):
    try:
        m = load_config([preset], method=method).mapping
    except ConfigError:  # combinations the release mode refuses (test_every_method_combines_with_every_preset)
        return
    assert MappingConfig.from_dict(m.as_dict()) == m


@pytest.mark.parametrize("key, place", [("block_depth", "sbki.block_depth"), ("ds_multiplier", "release.ds_multiplier"),
                                        ("convbki_stencil_half", "convbki.stencil_half"), ("scatter_strategy", "clean.scatter_strategy")])
def test_a_mode_key_outside_its_section_is_an_unknown_key(tmp_path, key, place):
    """One spelling per key: a mode setting at the top of mapping is refused in one line naming it, and the
    sections it may go in."""
    path = tmp_path / "flat.yaml"
    path.write_text(f"mapping:\n  {key}: 1\n")
    with pytest.raises(ConfigError, match=rf"flat.yaml: unknown key mapping.{key}; known: \[.*'{place.split('.')[0]}'") as err:
        load_config([path], method="ebs")
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=rf"meta.mapping: unknown key\(s\) \['{key}'\]"):
        MappingConfig.from_dict({key: 1}, "meta.mapping")


# The experiment's map cache keys of every method under the rellis3d preset, as this release first computed
# them: a change to how the key is built would make every user's cached maps be mapped again.
CACHE_KEYS = {"convbki": "6f6395684c51", "dempster": "1a682ce38195", "ebs": "fd55823a294b", "ebs-learned": "6369676fd18b",
              "ebs-per-class": "67905c6241a0",
              "prob": "a447761a8627", "prob-adap": "eec728021297", "prob-adap-thr": "c4493613e889", "prob-thr": "9d9db24e4b8e",
              "s-bki": "b6f638f78ba3", "s-csm": "8085c051904d", "see-csom": "eb8f3f15cfc5"}


@pytest.mark.parametrize("method", sorted(CACHE_KEYS))
def test_the_experiment_map_cache_key_is_stable(method):
    from evsemmap_warp.apps import experiment

    mapping = load_config([REPO / "configs/presets/rellis3d.yaml"], method=method).mapping
    assert experiment._digest(experiment.map_cache_fields(mapping)) == CACHE_KEYS[method]


def test_the_map_cache_fields_are_one_level_and_a_new_section_key_is_in_them():
    from types import SimpleNamespace

    from evsemmap_warp.apps.experiment import map_cache_fields

    fields = map_cache_fields(MappingConfig())
    assert fields["max_range_m"] == -1.0 and fields["ds_multiplier"] == -1 and "threshold_scope" not in fields
    assert "sbki" not in fields and fields["block_depth"] == 2
    assert map_cache_fields(MappingConfig(threshold_scope=ThresholdScope.PREDICTED_CLASS))["threshold_scope"] == "predicted-class"
    assert "class_gains" not in fields and map_cache_fields(MappingConfig(class_gains=True))["class_gains"] is True
    # a key a section gains is in the cache key (a cached map of other parameters is not taken for this one)
    grown = MappingConfig().as_dict()
    grown["sbki"]["new_key"] = 3
    assert map_cache_fields(SimpleNamespace(as_dict=lambda: grown)) == fields | {"sbki.new_key": 3}


def test_each_enum_is_one_class_whichever_module_names_it():
    """The dataclasses' enum fields take the members ``evsemmap_warp.config`` exports (one class per enum)."""
    import dataclasses
    import enum

    from evsemmap_warp import config
    from evsemmap_warp.config import CleanSettings, DatasetConfig

    for cls in (MappingConfig, CleanSettings, DatasetConfig):
        for f in dataclasses.fields(cls):
            if isinstance(f.default, enum.Enum):
                assert type(f.default) is getattr(config, type(f.default).__name__), f"{cls.__name__}.{f.name}"
    assert MappingConfig(clean=CleanSettings(scatter_strategy=ScatterStrategy.SORTED)).clean.scatter_strategy is ScatterStrategy.SORTED


@pytest.mark.parametrize("text, message", [
    ("mapping:\n  kernel: convbki\n", r"bad.yaml: mapping: kernel = 'convbki' is not a valid Kernel \(one of sparse, count, compound, triangular\)$"),
    ("mapping:\n  media: prob\n", r"bad.yaml: mapping: media = 'prob' is not a valid Media \(one of onehot, soft\)$"),
    ("mapping:\n  compat: evsemmap\n", r"bad.yaml: mapping: compat = 'evsemmap' is not a valid Compat \(one of clean, sbki, release\)$"),
])
def test_a_value_that_is_not_one_of_an_enums_is_named_with_the_ones_it_may_be(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config([path])


def test_an_unknown_preset_and_an_unknown_experiment_key_are_one_line_naming_them(tmp_path):
    from evsemmap_warp.apps.experiment import load_experiment

    with pytest.raises(ConfigError, match=r"^unknown mapping preset 'evsemmap-release'; available: .*release"):
        load_config(["evsemmap-release"], method="ebs")
    study = tmp_path / "study.yaml"
    study.write_text("name: s\nsequences:\n  a: {preset: tiny}\n")
    with pytest.raises(ConfigError, match=r"study.yaml: sequences.a: unknown key\(s\) \['preset'\]; known: \[.*'world'"):
        load_experiment(study)

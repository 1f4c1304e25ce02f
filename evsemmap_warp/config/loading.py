"""Resolving a run's configuration (``load_config``): the method file, presets and dataset files merged
in order, later files winning key by key, and the inputs named on the command line (sequence folders,
robot logs, built-in presets) found.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from .convert import convert_value, dataclass_from_dict, read_yaml_file
from .dataset import BagConfig, DatasetConfig
from .errors import ConfigError
from .mapping import MAPPING_SECTIONS, MappingConfig


@dataclass(frozen=True)
class RunConfig:
    """One run's resolved configuration (``load_config``): the mapping parameters, the dataset (None when no
    file names one), the files it came from, and how many camera-labelled frames are integrated together
    (``pipeline.bin_frames``)."""
    mapping: MappingConfig
    dataset: DatasetConfig | None = None
    sources: tuple[str, ...] = field(default_factory=tuple)
    bin_frames: int = 1  # pipeline.bin_frames: camera-labelled frames integrated together (docs/algorithm.md §2)


_SECTIONS = {"method": MappingConfig, "mapping": MappingConfig, "dataset": DatasetConfig}
# The keys a method file's ``method`` section may set (``name`` is ``MappingConfig.method``).
METHOD_KEYS = {"name", "kernel", "fusion", "media", "adaptive_length", "uncertainty_threshold", "threshold_scope", "class_gains", "compat"}


def methods_dir() -> Path:
    """The folder of the method files (``configs/methods/``, installed as ``evsemmap_warp.configs.methods``)."""
    return Path(str(resources.files("evsemmap_warp.configs") / "methods"))


def preset_path(name_or_path: str) -> Path:
    """A mapping preset by name (``configs/presets/NAME.yaml``, e.g. rellis3d, offroad) or path."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") and path.exists():
        return path
    presets = Path(str(resources.files("evsemmap_warp.configs") / "presets"))
    candidate = presets / f"{name_or_path}.yaml"
    if "/" in str(name_or_path) or "\\" in str(name_or_path) or not candidate.exists():
        if "/" in str(name_or_path) or "\\" in str(name_or_path):  # a path, not a preset's name
            raise ConfigError(f"{name_or_path}: no such file or folder")
        known = sorted(p.stem for p in presets.glob("*.yaml"))
        raise ConfigError(f"unknown mapping preset {name_or_path!r}; available: {', '.join(known)} (or a .yaml path)")
    return candidate


def available_methods() -> list[str]:
    """The built-in method names (``configs/methods/*.yaml``), sorted."""
    return sorted(p.stem for p in methods_dir().glob("*.yaml"))


def method_path(name_or_path: str) -> Path:
    """A method file by name (``configs/methods/NAME.yaml``) or path; raises ConfigError naming the known
    methods when there is none of that name."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") and path.exists():
        return path
    candidate = methods_dir() / f"{name_or_path}.yaml"
    if not candidate.exists():
        raise ConfigError(f"unknown method {name_or_path!r}; available: {', '.join(available_methods())}")
    return candidate


def _read_yaml(path: Path) -> dict[str, Any]:
    data = read_yaml_file(path)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level, got {type(data).__name__}")
    not_names = [k for k in data if not isinstance(k, str)]
    if not_names:
        raise ConfigError(f"{path}: top-level key {not_names[0]!r} is not a section name (a {type(not_names[0]).__name__})")
    unknown = set(data) - set(_SECTIONS) - {"pipeline"}
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {sorted(unknown)}; known: {sorted(_SECTIONS)} and pipeline")
    return data


def dataset_for_folder(folder: Path) -> dict[str, Any]:
    """The dataset section for a sequence folder named on the command line instead of a dataset
    config: SemanticKITTI when it has velodyne/, else the RELLIS-3D layout (also what synth writes)."""
    kind = "semantickitti" if (folder / "velodyne").is_dir() else "rellis3d"
    if not ((folder / "velodyne").is_dir() or (folder / "os1_cloud_node_kitti_bin").is_dir() or any(folder.glob("[0-9]*.bin"))):
        what = ("a map store: give it to export, merge, view or info" if (folder / "store.json").is_file()
                else "a ROS 2 bag folder without metadata.yaml, still being recorded or cut short: name its .db3 or .mcap file"
                if any(p.suffix in (".db3", ".mcap") for p in folder.glob("*"))
                else "it holds map files: give them to merge, view or info" if any(folder.glob("*.npz"))
                else "no os1_cloud_node_kitti_bin/, velodyne/ or NNNNNN.bin scans")
        raise ConfigError(f"{folder}: not a sequence folder ({what})")
    return {"kind": kind, "paths": (str(folder.resolve()),), "config_dir": str(folder.resolve())}


LOG_SUFFIXES = (".bag", ".mcap", ".db3")


def is_robot_log(path) -> bool:
    """A ROS 1 .bag, a bare .mcap or .db3 file, or a ROS 2 bag folder (it has metadata.yaml)."""
    path = Path(path)
    return (path.is_file() and path.suffix in LOG_SUFFIXES) or (path.is_dir() and (path / "metadata.yaml").is_file())


@dataclass
class _Merged:
    """What the inputs and files read so far set, key by key (a later file's key wins)."""

    mapping: dict[str, Any] = field(default_factory=dict)
    dataset: dict[str, Any] = field(default_factory=dict)
    bag: dict[str, Any] = field(default_factory=dict)
    bin_frames: int = 1
    sources: list[str] = field(default_factory=list)
    logs_given: bool = False  # robot logs were named among the inputs: they win over a config's dataset.logs


def load_config(config_paths: list[str | Path], method: str | None = None, *, frame: str | None = None, crs: str | None = None) -> RunConfig:
    """Merge the method file (if any) and the given files, later ones winning; validate. A folder
    among the paths is a sequence to map (``dataset_for_folder``), robot logs are a ``bag`` dataset
    (read in the order given), a bare name a built-in preset. ``frame`` and ``crs`` (the --frame and
    --crs flags) override the files' dataset.frame and dataset.crs."""
    merged = _Merged()
    config_paths = _take_data_inputs(config_paths, merged)
    # a bare name (no .yaml, no such file) is a built-in mapping preset: rellis3d, offroad, ...
    files = ([method_path(method)] if method else []) + [
        preset_path(str(p)) if not Path(p).exists() and Path(p).suffix == "" else Path(p) for p in config_paths if not Path(p).is_dir()]
    for path in files:
        _merge_file(path, merged)
    return _resolve(merged, frame, crs)


def _take_data_inputs(config_paths: list[str | Path], merged: _Merged) -> list[str | Path]:
    """Read the robot logs and the sequence folder among the inputs into ``merged``'s dataset; the
    inputs left (config files, presets) are returned."""
    logs = [Path(p) for p in config_paths if is_robot_log(p)]
    if logs:
        merged.dataset.update(kind="bag", logs=tuple(str(p.resolve()) for p in logs))
        merged.sources += [str(p) for p in logs]
        merged.logs_given = True
    config_paths = [p for p in config_paths if not is_robot_log(p)]
    folders = [Path(p) for p in config_paths if Path(p).is_dir()]
    if folders and logs:
        raise ConfigError(f"map either a sequence folder or robot logs, got both: {str(folders[0])!r} and {str(logs[0])!r}")
    if len(folders) > 1:
        raise ConfigError(f"one sequence folder per run, got {len(folders)}: {[str(f) for f in folders]}")
    if folders:
        merged.dataset.update(dataset_for_folder(folders[0]))
        merged.sources.append(str(folders[0]))
    return config_paths


def _merge_file(path: Path, merged: _Merged) -> None:
    """One config file's sections merged into ``merged``, each key checked as it is read."""
    data = _read_yaml(path)
    merged.sources.append(str(path))
    for section, values in data.items():
        if section == "pipeline":
            if not isinstance(values, dict) or set(values) - {"bin_frames"}:
                raise ConfigError(f"{path}: pipeline takes only bin_frames, got {values!r}")
            if "bin_frames" in values:
                bins = values["bin_frames"]
                if isinstance(bins, bool) or not isinstance(bins, int) or bins < 1:
                    raise ConfigError(f"{path}: pipeline.bin_frames = {bins!r} must be a whole number >= 1")
                merged.bin_frames = bins
            continue
        if not isinstance(values, dict):
            raise ConfigError(f"{path}: section {section!r} must be a mapping")
        for key, value in values.items():
            _merge_key(path, section, key, value, merged)


def _merge_key(path: Path, section: str, key: Any, value: Any, merged: _Merged) -> None:
    """``section.key: value`` of the file ``path`` merged into ``merged``; an unknown key or a wrong
    value raises a ConfigError naming the file and the dotted key."""
    cls = _SECTIONS[section]
    if not isinstance(key, str):
        raise ConfigError(f"{path}: key {key!r} in section {section!r} is not a name (a {type(key).__name__})")
    if section == "method":
        if key not in METHOD_KEYS:
            raise ConfigError(f"{path}: method.{key} is not a method switch; allowed: {sorted(METHOD_KEYS)}")
        key = "method" if key == "name" else key
    known = {f.name for f in dataclasses.fields(cls)} - {"config_dir"}
    if key not in known:
        raise ConfigError(f"{path}: unknown key {section}.{key}; known: {sorted(known)}")
    if section == "dataset" and key == "bag":
        # key by key, so a user's file can change one topic of a preset
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: dataset.bag must be a mapping, got {type(value).__name__}")
        known = {f.name for f in dataclasses.fields(BagConfig)}
        unknown = sorted(str(k) for k in value if k not in known)
        if unknown:  # named now, with its file; values are checked once all files are merged
            raise ConfigError(f"{path}: unknown key(s) dataset.bag.{unknown[0]}; known: {sorted(known)}")
        merged.bag.update(value)
        return
    if section == "mapping" and key in MAPPING_SECTIONS:
        # key by key, so a dataset file can change one of a preset's mode settings
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: mapping.{key} must be a mapping, got {type(value).__name__}")
        sub = MAPPING_SECTIONS[key]
        known = {f.name for f in dataclasses.fields(sub)}
        for subkey, subvalue in value.items():
            if subkey not in known:
                raise ConfigError(f"{path}: unknown key mapping.{key}.{subkey}; known: {sorted(known)}")
            merged.mapping.setdefault(key, {})[subkey] = convert_value(sub, subkey, subvalue, f"{path}: mapping.{key}")
        return
    if section == "dataset" and key == "logs" and merged.logs_given:
        return  # logs named on the command line win over a config's
    converted = convert_value(cls, key, value, f"{path}: {section}")
    if section == "dataset":
        merged.dataset[key] = converted
        if key in ("paths", "logs"):  # relative paths belong to the file that names them
            merged.dataset["config_dir"] = str(path.resolve().parent)
    else:
        merged.mapping[key] = converted


def _resolve(merged: _Merged, frame: str | None, crs: str | None) -> RunConfig:
    """The RunConfig of everything merged, validated as a whole; ``frame`` and ``crs`` (the flags) win
    over the files' dataset.frame and dataset.crs."""
    sources, dataset = merged.sources, merged.dataset
    try:
        mapping_cfg = MappingConfig(**{k: MAPPING_SECTIONS[k](**v) if k in MAPPING_SECTIONS else v for k, v in merged.mapping.items()})
    except ConfigError as exc:
        raise ConfigError(f"{' + '.join(sources)}: {exc}") from None
    if merged.bag:
        dataset["bag"] = dataclass_from_dict(BagConfig, merged.bag, " + ".join(sources) + ": dataset.bag")
    if (frame is not None or crs is not None) and not dataset:
        raise ConfigError(f"{' + '.join(sources) or 'no config'}: --frame / --crs place a dataset's scans, and none is named")
    if crs is not None:  # a bad flag named as the flag, not as the dataset.crs key it stands for
        from ..frames import FrameError, check_crs

        try:
            check_crs(crs, "--crs")
        except FrameError as exc:
            raise ConfigError(str(exc)) from None
    if dataset:
        dataset.update({k: v for k, v in (("frame", frame), ("crs", crs)) if v is not None})
    try:
        dataset_cfg = DatasetConfig(**dataset) if dataset else None
    except ConfigError as exc:
        raise ConfigError(f"{' + '.join(sources) or '--frame/--crs'}: {exc}") from None
    return RunConfig(mapping=mapping_cfg, dataset=dataset_cfg, sources=tuple(sources), bin_frames=merged.bin_frames)

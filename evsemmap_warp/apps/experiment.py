"""A whole study from one config: data -> network -> alpha -> projection -> maps -> scores -> tables.

Stages are cached under ``OUT/cache`` (or a shared ``cache`` folder) by a hash of everything they depend on, and each stage writes
its "done" file last, so a rerun with one changed method redoes only that method's maps, and an
interrupted run resumes from the stages it finished (training resumes from its last epoch).

Config (YAML)::

    name: demo
    sequences:            # synthetic (a world preset + overrides) or real (path) RELLIS-3D-layout sequences
      train: {world: demo, seed: 11, spacing_m: 0.5, frames: 150}
      test: {world: demo, seed: 12}
      test-dusk: {world: demo, seed: 12, domain: dusk}
      rellis: {path: /data/Rellis-3D/00004}
    networks:             # segmentation networks and what they train on (or a checkpoint path)
      summer: {train_on: [train], epochs: 12}   # time_budget_s: S stops early, reported as a warning
    conditions:           # a network's alpha on a sequence, mapped and scored: one table row set each
      in-domain: {network: summer, sequence: test}
    mapping_preset: offroad   # configs/presets/NAME.yaml or a path, under every method
    projection: {bin_frames: 1}
    methods: [s-csm, s-bki, ebs]
    ablation: {condition: in-domain, methods: [s-bki, prob, prob-adap, prob-thr, prob-adap-thr]}
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import platform
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import __version__, files
from ..config import (MAPPING_SECTIONS, ConfigError, Kernel, MappingConfig, PayloadType, dataclass_from_dict, is_robot_log, load_config,
                      preset_path, read_yaml_file)
from .evaluation import PAPER_SCORED_CLASSES, MapScores, evaluate_map, markdown_table, pool_scores
from ..classes import class_set
from ..data.datasets import Scan
from ..geometry.projection import ProjectionConfig, bin_frames, label_map_for, project_frames
from ..core.mapper import Mapper
from .scan_sources import ScanList, map_scans


@dataclass(frozen=True)
class SequenceSpec:
    """A sequence of a study: a synthetic one rendered from the world preset ``world`` (with its overrides)
    or a real one at ``path``; exactly one of the two."""

    world: str = ""  # a synthetic world preset to render (configs/synthetic/NAME.yaml or a path)
    path: str = ""  # a RELLIS-3D-layout folder, or a robot log read with log_config
    log_config: str = "rellis3d-bag"  # for a log: the preset or dataset config that says its topics
    seed: int = -1  # -1: the world preset's
    domain: str = ""  # appearance domain of a synthetic sequence; "": the world preset's
    frames: int = 0  # 0: the world preset's
    spacing_m: float = 0.0  # 0: the world preset's


@dataclass(frozen=True)
class NetworkSpec:
    """A segmentation network of a study: trained on the camera images of ``train_on`` (or read from
    ``checkpoint``)."""

    train_on: tuple = ()  # names of sequences (above) whose camera images and label images it trains on
    checkpoint: str = ""  # use this trained checkpoint instead of training
    fraction: float = 1.0  # share of the training frames used (the paper's "trained on a subset")
    arch: str = "r18-os16"  # r18-os16 (CPU default), r50-os8 (full size) or torchvision-r50
    input_size: tuple = (128, 256)  # network input, height and width (px)
    epochs: int = 12  # passes over the training frames
    batch_size: int = 8  # images per training step
    lr: float = 2e-3  # learning rate
    time_budget_s: float = 0.0  # 0: no limit
    seed: int = 1  # of the split, the initialisation and the data order (and of the subset when subset: random)
    subset: str = "first"  # with fraction < 1: first (each sequence's first frames) or random (frames drawn by seed)


@dataclass(frozen=True)
class ConditionSpec:
    """One condition of a study: the alpha of ``network`` on ``sequence``, mapped with every method and
    scored against that sequence's 3D ground truth."""

    network: str = ""  # a network's name (above): its alpha is mapped
    sequence: str = ""  # a sequence's name (above): mapped and scored


@dataclass(frozen=True)
class AblationSpec:
    """The ablation table: ``methods`` mapped and scored on one condition (or pool)."""

    condition: str = ""  # the condition (or pool) the ablation runs on
    methods: tuple = ()  # the methods of the ablation table


@dataclass(frozen=True)
class ConvBkiTraining:
    """How ConvBKI's length scales are learned when a method needs them and no file is given: on the
    network's own training sequences (its alpha, projected; the LiDAR's per-point labels as truth)."""

    window_scans: int = 10  # scans per training window (one stencil update)
    windows: int = 8  # windows drawn from the training sequences
    queries_per_window: int = 4000  # points of a window's last scan the loss is taken at
    epochs: int = 10  # passes over the windows


@dataclass(frozen=True)
class ExperimentConfig:
    """A whole study (``evsemmap experiment CONFIG``): its sequences, networks and conditions by name, the
    mapping preset under every method, the projection, the methods and the ablation, the scored classes
    and pools."""

    name: str = "experiment"  # names the results folder (results_NAME)
    sequences: dict = field(default_factory=dict)  # name -> a sequence (sequences.NAME below)
    networks: dict = field(default_factory=dict)  # name -> a network (networks.NAME below)
    conditions: dict = field(default_factory=dict)  # name -> a network's alpha on a sequence (conditions.NAME below)
    mapping_preset: str = "offroad"  # configs/presets/NAME.yaml or a path, under every method
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)  # the projection section below
    methods: tuple = ()  # the methods mapped and scored in every condition
    ablation: AblationSpec = field(default_factory=AblationSpec)  # the ablation section below
    scored_classes: tuple = PAPER_SCORED_CLASSES  # the classes scored (the paper's seven)
    # name -> conditions scored as one (docs/algorithm.md §4.5: the RELLIS-3D folds; pooled confusion matrices,
    # and the mean of the per-condition scores beside them)
    pools: dict = field(default_factory=dict)
    convbki: ConvBkiTraining = field(default_factory=ConvBkiTraining)  # the convbki section below
    # every network trained once per seed (NAME@sSEED), every condition and pool with it; the tables give the
    # mean and spread over the seeds, so that a difference can be judged against the training noise
    seeds: tuple = ()
    # per condition: does the network's u flag its errors, what each method's threshold and adaptive length do
    # with the points, and the maps' errors by variance decile (apps/uncertainty_study.py); tables and plots
    diagnostics: bool = False
    # `--quick`: overrides for every sequence (e.g. world, frames) and network (e.g. epochs), and the seeds:
    # the same study, scaled down to check that it runs (CI), not to read its numbers
    quick: dict = field(default_factory=dict)


def experiments_dir() -> Path:
    """The folder of the built-in experiment configs (``configs/experiments/``, installed as
    ``evsemmap_warp.configs.experiments``)."""
    return Path(str(resources.files("evsemmap_warp.configs") / "experiments"))


def load_experiment(name_or_path, *, quick: bool = False) -> tuple[ExperimentConfig, Path]:
    """An experiment config by path or built-in name, and its path; ``quick``: with its ``quick`` overrides
    applied. Networks and conditions come once per seed when it lists ``seeds``. Raises ConfigError naming the
    file and the key when it is missing, not YAML, or names sequences, networks, conditions or methods that do
    not exist, before any work is done."""
    path = Path(name_or_path)
    if not path.exists():
        path = experiments_dir() / f"{name_or_path}.yaml"
        if not path.exists():
            known = sorted(p.stem for p in experiments_dir().glob("*.yaml"))
            raise ConfigError(f"{name_or_path}: no such experiment config (built in: {', '.join(known)})")
    data = read_yaml_file(path, "experiment config") or {}
    src = str(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{src}: expected a mapping of sections at the top level, got {type(data).__name__}")
    for section, cls in (("sequences", SequenceSpec), ("networks", NetworkSpec), ("conditions", ConditionSpec)):
        if not isinstance(data.get(section, {}), dict):
            raise ConfigError(f"{src}: {section} must be a mapping of names")
        entries = data.get(section) or {}
        data[section] = {k: dataclass_from_dict(cls, v, f"{src}: {section}.{k}") for k, v in entries.items()}
    config = dataclass_from_dict(ExperimentConfig, data, src)
    if quick:
        config = _quick(config, src)
    for name, seq in config.sequences.items():
        if bool(seq.world) == bool(seq.path):
            raise ConfigError(f"{src}: sequences.{name} needs exactly one of world (synthetic) or path (a RELLIS-3D-layout folder or a robot log)")
        if seq.frames < 0 or seq.spacing_m < 0:
            raise ConfigError(f"{src}: sequences.{name}: frames ({seq.frames}) and spacing_m ({seq.spacing_m}) must be >= 0 (0: the world preset's)")
    for name, net in config.networks.items():
        if net.epochs < 1 or net.batch_size < 1 or not net.lr > 0 or net.time_budget_s < 0 or not 0 < net.fraction <= 1:
            raise ConfigError(f"{src}: networks.{name}: need epochs >= 1, batch_size >= 1, lr > 0, time_budget_s >= 0 "
                              f"and fraction in (0, 1]; got {net.epochs}, {net.batch_size}, {net.lr}, {net.time_budget_s}, {net.fraction}")
        if net.subset not in ("first", "random"):
            raise ConfigError(f"{src}: networks.{name}.subset must be first or random, got {net.subset!r}")
        missing = [s for s in net.train_on if s not in config.sequences]
        if missing or (not net.train_on and not net.checkpoint):
            raise ConfigError(f"{src}: networks.{name} trains on unknown sequences {missing} or on nothing (give train_on or checkpoint)")
    for name, cond in config.conditions.items():
        if cond.network not in config.networks or cond.sequence not in config.sequences:
            raise ConfigError(f"{src}: conditions.{name} names network {cond.network!r} / sequence {cond.sequence!r}, not defined above")
    if not config.conditions or not config.methods:
        raise ConfigError(f"{src}: an experiment needs at least one condition and one method")
    for method in tuple(config.methods) + tuple(config.ablation.methods):
        load_config([], method=method)  # unknown methods fail now, not after training
    preset_path(config.mapping_preset)  # an unknown preset fails now too
    for name, members in config.pools.items():
        if not isinstance(members, list) or not members or any(m not in config.conditions for m in members):
            raise ConfigError(f"{src}: pools.{name} must list conditions defined above, got {members!r}")
    if config.ablation.methods and config.ablation.condition not in config.conditions and config.ablation.condition not in config.pools:
        raise ConfigError(f"{src}: ablation.condition {config.ablation.condition!r} is neither a condition nor a pool")
    if config.seeds:
        if config.ablation.methods:
            raise ConfigError(f"{src}: seeds and ablation together are not supported (the ablation runs on one network)")
        if len(set(config.seeds)) != len(config.seeds) or not all(isinstance(s, int) and s >= 0 for s in config.seeds):
            raise ConfigError(f"{src}: seeds must be distinct integers >= 0, got {list(config.seeds)}")
        config = _per_seed(config)
    return config, path


SEED_MARK = "@s"  # a network, condition or pool of one seed: NAME@sSEED


def seed_group(name: str) -> str:
    """The name a per-seed network, condition or pool was expanded from (``in-domain@s2`` -> ``in-domain``)."""
    return name.rsplit(SEED_MARK, 1)[0] if SEED_MARK in name else name


def _per_seed(config: ExperimentConfig) -> ExperimentConfig:
    def each(name: str) -> list[str]:
        return [f"{name}{SEED_MARK}{seed}" for seed in config.seeds]

    networks = {f"{name}{SEED_MARK}{seed}": dataclasses.replace(net, seed=seed) for name, net in config.networks.items() for seed in config.seeds}
    conditions = {f"{name}{SEED_MARK}{seed}": dataclasses.replace(cond, network=f"{cond.network}{SEED_MARK}{seed}")
                  for name, cond in config.conditions.items() for seed in config.seeds}
    pools = {f"{name}{SEED_MARK}{seed}": [f"{m}{SEED_MARK}{seed}" for m in members] for name, members in config.pools.items() for seed in config.seeds}
    return dataclasses.replace(config, networks=networks, conditions=conditions, pools=pools)


def _quick(config: ExperimentConfig, src: str) -> ExperimentConfig:
    quick = dict(config.quick)
    unknown = set(quick) - {"sequences", "networks", "seeds"}
    if not quick or unknown:
        raise ConfigError(f"{src}: --quick needs a quick section with sequences, networks and/or seeds"
                          + (f"; unknown key(s) {sorted(unknown)}" if unknown else ""))

    def overridden(entry, overrides, where):
        if entry.path:  # a real sequence stays what it is
            return entry
        return dataclass_from_dict(type(entry), dataclasses.asdict(entry) | dict(overrides or {}), where)

    sequences = {k: overridden(v, quick.get("sequences"), f"{src}: quick.sequences") for k, v in config.sequences.items()}
    networks = {k: dataclass_from_dict(NetworkSpec, dataclasses.asdict(v) | dict(quick.get("networks") or {}), f"{src}: quick.networks")
                for k, v in config.networks.items()}
    return dataclasses.replace(config, sequences=sequences, networks=networks, seeds=tuple(quick.get("seeds", config.seeds)))


# The mode sections' keys as the map cache key names them, one level deep: cache key -> (section, key).
_CACHE_KEY_FIELDS = {
    "block_depth": ("sbki", "block_depth"), "ds_resolution_m": ("sbki", "ds_resolution_m"),
    "free_resolution_m": ("sbki", "free_resolution_m"), "max_range_m": ("sbki", "max_range_m"),
    "scatter_strategy": ("clean", "scatter_strategy"), "ds_multiplier": ("release", "ds_multiplier"),
    "convbki_lengths_file": ("convbki", "lengths_file"), "convbki_stencil_half": ("convbki", "stencil_half"),
}


def map_cache_fields(mapping: MappingConfig) -> dict:
    """The mapping parameters as a cached map's key holds them: one level of keys, the mode sections'
    under their ``_CACHE_KEY_FIELDS`` names (any other as section.key), None as -1 (max_range_m -1.0,
    ds_multiplier -1), and threshold_scope only when it is not its default ``insertion`` (class_gains is in
    the mapping's dict only when true). The form is fixed: a key built any other way would change every
    cached map's key, and a rerun would map them all again."""
    nested = mapping.as_dict()
    out = {k: v for k, v in nested.items() if k not in MAPPING_SECTIONS}
    named = {place: name for name, place in _CACHE_KEY_FIELDS.items()}
    for section in MAPPING_SECTIONS:
        for key, value in nested[section].items():  # a key added to a section later is in the key as section.key
            out[named.get((section, key), f"{section}.{key}")] = value
    if out["max_range_m"] is None:
        out["max_range_m"] = -1.0
    if out["ds_multiplier"] is None:
        out["ds_multiplier"] = -1
    if out["threshold_scope"] == "insertion":
        del out["threshold_scope"]
    return out


def _digest(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


class Experiment:
    """Runs a study stage by stage into ``out``: sequences, networks, alpha, projection, maps and scores,
    each stage cached under ``cache`` by a hash of its inputs, so a rerun redoes only what changed."""

    def __init__(self, config: ExperimentConfig, out, *, cache=None, device: str | None = "cpu", progress: bool = True, log=print):
        """``cache``: the stage cache folder (default OUT/cache); studies that share it share data,
        networks and alpha (stages are keyed by their inputs, not by the study)."""
        self.config, self.out, self.device, self.progress, self.log = config, Path(out), device, progress, log
        self.cache = Path(cache) if cache is not None else self.out / "cache"
        self.timings: dict[str, float] = {}
        self.notes: list[str] = []
        self._networks: dict[str, Path] = {}
        self._sequence_dirs: dict[str, Path] = {}
        self._sequences: dict = {}
        self._mappers: dict = {}  # (condition, method) -> (the map, its mapping config), for the diagnostics

    # -- stages ----------------------------------------------------------------------------------
    def _source_key(self, name: str) -> str:
        """What a sequence's cached stages depend on: its path, and for a log the config that reads it."""
        path = self.sequence_dir(name)
        return f"{path} {self.config.sequences[name].log_config}" if is_robot_log(path) else str(path)

    def sequence(self, name: str):
        """The sequence (folder or robot log) named ``name``; a log is indexed once per study."""
        from ..data.datasets import open_sequence

        if name not in self._sequences:
            path = self.sequence_dir(name)
            self._sequences[name] = open_sequence([path] + ([self.config.sequences[name].log_config] if is_robot_log(path) else []))
        return self._sequences[name]

    def sequence_dir(self, name: str) -> Path:
        """The folder (or robot log) of sequence ``name``, rendered into the cache first when it is
        synthetic; raises ConfigError when a real sequence's path is neither a folder nor a log."""
        if name in self._sequence_dirs:
            return self._sequence_dirs[name]
        spec = self.config.sequences[name]
        if spec.path:
            path = Path(spec.path).expanduser()
            if not path.is_dir() and not is_robot_log(path):
                raise ConfigError(f"sequences.{name}.path: {path} is neither a folder nor a robot log (.bag, .mcap, .db3)")
            self._sequence_dirs[name] = path
            return path
        from ..synthetic.writer import generate_sequence

        preset, folder = self._synthetic_sequence(name)
        if not (folder / "synth.yaml").exists():  # written last by the generator
            self.log(f"[data] rendering {name} ({preset.name}, seed {preset.seed}, {preset.appearance.domain})")
            started = time.perf_counter()
            generate_sequence(preset, folder, device=self.device, progress=self.progress)
            self.timings[f"render {name}"] = time.perf_counter() - started
        self._sequence_dirs[name] = folder
        return folder

    def _synthetic_sequence(self, name: str):
        """A synthetic sequence's world preset (with the spec's overrides) and the cache folder it renders into."""
        from ..synthetic.preset import load_preset

        spec = self.config.sequences[name]
        preset = load_preset(spec.world, seed=None if spec.seed < 0 else spec.seed, appearance__domain=spec.domain or None,
                             trajectory__frames=spec.frames or None, trajectory__spacing_m=spec.spacing_m or None)
        return preset, self.cache / "sequences" / f"{name}-{_digest(dataclasses.asdict(preset), __version__)}"

    def _network_folder(self, name: str, source_names: list[str]) -> Path:
        spec = self.config.networks[name]
        described = dataclasses.asdict(spec)
        if spec.subset == "first":  # the key networks had before subsets could be drawn: their caches stay valid
            del described["subset"]
        return self.cache / "networks" / f"{name}-{_digest(described, source_names, __version__)}"

    def training_work(self) -> dict[str, float]:
        """Per network still to train (not finished in the cache): about how many frame-epochs its training
        takes, from the specs alone (nothing is rendered); the study's ETA weighs its stages by them."""
        work = {}
        for name, spec in self.config.networks.items():
            if spec.checkpoint or any(self.config.sequences[s].path for s in spec.train_on):
                continue  # real data: its size is known once read; left out of the estimate
            folders = [self._synthetic_sequence(s) for s in spec.train_on]
            finished = self._network_folder(name, [folder.name for _, folder in folders]) / "metrics.json"
            if finished.exists() and json.loads(finished.read_text()).get("epochs_run", spec.epochs) >= spec.epochs:
                continue
            work[name] = sum(max(1, round(preset.trajectory.frames * spec.fraction)) for preset, _ in folders) * spec.epochs
        return work

    def network(self, name: str) -> Path:
        """The trained checkpoint of network ``name`` (trained, resumed or found in the cache once per run)."""
        if name not in self._networks:
            self._networks[name] = self._network(name)
        return self._networks[name]

    def _network(self, name: str) -> Path:
        from ..classes import class_set
        from ..segmentation.config import ModelConfig
        from ..segmentation.data import Rellis3DImages, SequenceImages
        from ..segmentation.train import TimeBudgetWarning, TrainConfig, evaluate_checkpoint, load_checkpoint, split_indices, train

        spec = self.config.networks[name]
        if spec.checkpoint:
            return Path(spec.checkpoint).expanduser()
        sources = [self.sequence_dir(s) for s in spec.train_on]
        classes = class_set()
        config = TrainConfig(model=ModelConfig(arch=spec.arch, num_classes=len(classes)), input_size=tuple(spec.input_size),
                             epochs=spec.epochs, batch_size=spec.batch_size, lr=spec.lr, seed=spec.seed,
                             time_budget_s=spec.time_budget_s or None)
        folder = self._network_folder(name, [s.name for s in sources])
        if (folder / "metrics.json").exists():  # written last by train()
            summary = json.loads((folder / "metrics.json").read_text())
            if summary.get("epochs_run", spec.epochs) >= spec.epochs:
                return folder / "best.pt"
            # stopped by its time budget: never reused as finished; training goes on from its last epoch
            self._note(f"network {name}: the cached network stopped after {summary['epochs_run']} of {spec.epochs} epochs "
                       f"(time budget); training resumes")
        folder.mkdir(parents=True, exist_ok=True)
        images = [SequenceImages(self.sequence(s)) if is_robot_log(path) else Rellis3DImages(path) for s, path in zip(spec.train_on, sources)]
        source = _Frames([(s, i) for s in images for i in _subset(len(s), spec)])
        try:
            split_indices(len(source), config.val_fraction, config.seed)
        except ValueError as exc:
            raise ConfigError(f"networks.{name}: fraction {spec.fraction:g} of {', '.join(spec.train_on)} is {len(source)} frames: {exc}") from None
        resume = folder / "last.pt" if (folder / "last.pt").exists() else None
        if resume is not None and int(load_checkpoint(resume)[2]["epoch"]) >= config.epochs:
            # interrupted after the last epoch's checkpoint, before the summary: only the summary is missing
            _, val = split_indices(len(source), config.val_fraction, config.seed)
            evaluate_checkpoint(folder / "best.pt", _Frames([source.items[i] for i in val]), folder)
            return folder / "best.pt"
        self.log(f"[network] training {name} on {len(source)} frames of {', '.join(spec.train_on)}" + (" (resuming)" if resume else ""))
        started = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TimeBudgetWarning)  # reported below, into the results too
            summary = train(source, classes.names, config, folder, resume=resume, progress=self.progress)
        self.timings[f"train {name}"] = time.perf_counter() - started
        if summary["epochs_run"] < spec.epochs:
            self._note(f"network {name}: training stopped by its time budget ({spec.time_budget_s:g} s) after "
                       f"{summary['epochs_run']} of {spec.epochs} epochs; its scores depend on this machine's speed")
        return folder / "best.pt"

    def _progress(self, done: int, elapsed: float, work_left: float, work_done: float, training_s: float, other_s: float) -> str:
        """'[study] 5 of 36 conditions, 12 min, about 40 min left': training time left at this run's seconds per
        frame-epoch, the other stages at their mean per condition so far."""
        total = len(self.config.conditions)
        left = (total - done) * other_s / done + (work_left * training_s / work_done if work_done else 0.0)
        unknown = " (and the training still to come, not yet timed)" if work_left and not work_done else ""
        return f"[study] {done} of {total} conditions, {elapsed / 60:.1f} min, about {left / 60:.0f} min left{unknown}"

    def _note(self, text: str) -> None:
        """A warning the user must see: on the console now, and in results.md and record.json."""
        self.log(f"WARNING: {text}")
        self.notes.append(text)

    def alpha_dir(self, condition: str) -> Path:
        """The folder of the per-frame alpha files (float16 .npy) of condition ``condition``'s network on its
        sequence."""
        cond = self.config.conditions[condition]
        return self.alpha_for(cond.network, cond.sequence)

    def alpha_for(self, network: str, sequence: str) -> Path:
        """The folder of ``network``'s alpha on ``sequence``, one float16 [K, H, W] .npy per camera frame;
        inferred into the cache first when it is not there."""
        from ..segmentation.train import infer_alpha, load_checkpoint

        checkpoint = self.network(network)
        folder = self.cache / "alpha" / f"{network}-{sequence}-{_digest(str(checkpoint), checkpoint.stat().st_mtime_ns, self._source_key(sequence))}"
        if (folder / "done").exists():
            return folder
        folder.mkdir(parents=True, exist_ok=True)
        seq = self.sequence(sequence)
        frames = [f for f in seq.frames if f.image is not None]
        model, config, meta, _ = load_checkpoint(checkpoint)
        started = time.perf_counter()
        self.log(f"[alpha] {network} on {len(frames)} frames of {sequence}")
        outputs = infer_alpha(model, config, meta, (seq.read_image(f) for f in frames), batch_size=8)
        for frame, (alpha, _) in tqdm(zip(frames, outputs), total=len(frames), unit="img", disable=not self.progress, desc="infer"):
            files.save_npy_atomically(folder / f"{frame.index:06d}.npy", alpha)
        files.write_bytes_atomically(folder / "done", b"")
        self.timings[f"infer {network} on {sequence}"] = time.perf_counter() - started
        return folder

    def convbki_lengths(self, network: str, resolution_m: float) -> Path:
        """ConvBKI's per-class length scales learned on the network's training sequences (cached)."""
        from ..methods import convbki
        from ..classes import class_set
        spec, training = self.config.networks[network], self.config.convbki
        folder = self.cache / "convbki"
        path = folder / f"{network}-{_digest(str(self.network(network)), spec.train_on, resolution_m, dataclasses.asdict(training), __version__)}.json"
        if path.exists():
            return path
        windows = []
        for sequence in spec.train_on:
            alpha = self.alpha_for(network, sequence)
            windows += convbki.training_windows(
                self.sequence(sequence),
                lambda f, alpha=alpha: np.load(alpha / f"{f.index:06d}.npy").astype(np.float32) if (alpha / f"{f.index:06d}.npy").exists() else None,
                self.config.projection, window_scans=training.window_scans, queries_per_window=training.queries_per_window)
        if not windows:
            raise ConfigError(f"networks.{network}: its training sequences have no scans with per-point labels to learn ConvBKI's lengths from")
        windows = [windows[i] for i in np.linspace(0, len(windows) - 1, min(training.windows, len(windows))).astype(int)]
        self.log(f"[convbki] learning length scales on {len(windows)} windows of {training.window_scans} scans")
        started = time.perf_counter()
        lengths, history = convbki.train_lengths(windows, len(class_set().names), resolution_m, epochs=training.epochs, progress=self.progress)
        folder.mkdir(parents=True, exist_ok=True)
        files.write_json_atomically(path, lengths.as_dict() | {"loss_history": history}, indent=1)
        self.timings[f"convbki lengths {network}"] = time.perf_counter() - started
        return path

    def ground_truth(self, sequence: str) -> tuple[np.ndarray, np.ndarray]:
        """The 3D ground truth of ``sequence``: points [M, 3] (m, the sequence's world frame) and their
        labels [M], its 2D label images projected onto its LiDAR points (cached). Raises ConfigError when
        no frame has a label image."""
        seq = self.sequence(sequence)
        # the frame is part of the key: ground truth projected into another frame is another file
        key = _digest(self._source_key(sequence), dataclasses.asdict(self.config.projection), seq.world.frame.as_dict())
        path = self.cache / "ground_truth" / f"{sequence}-{key}.npz"
        if not path.exists():
            frames = [f for f in seq.frames if f.label_image is not None]
            if not frames:
                raise ConfigError(f"sequences.{sequence}: no frame has a 2D label image, so there is no 3D ground truth")
            projected = list(project_frames(seq, frames, label_map_for(seq), self.config.projection, seq.world))
            path.parent.mkdir(parents=True, exist_ok=True)
            files.savez_atomically(path, compressed=True, points=np.concatenate([p.points for p in projected]), labels=np.concatenate([p.values for p in projected]))
        data = np.load(path)
        return data["points"], data["labels"]

    def bins(self, condition: str) -> ScanList:
        """The condition's camera-labelled scans, projected and binned, in the sequence's world frame."""
        cond = self.config.conditions[condition]
        alpha = self.alpha_dir(condition)
        seq = self.sequence(cond.sequence)
        frames = [f for f in seq.frames if (alpha / f"{f.index:06d}.npy").exists()]

        def values(frame):
            return np.load(alpha / f"{frame.index:06d}.npy").astype(np.float32)

        # The drive in the maps' frame, for `evsemmap view MAP --trajectory trajectory.txt`.
        trajectory = np.array([seq.world.to_world(seq.pose(f))[:3, 3] for f in frames]).reshape(-1, 3)
        (self.out / "maps" / condition).mkdir(parents=True, exist_ok=True)
        files.write_text_atomically(self.out / "maps" / condition / "trajectory.txt",
                                    "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in trajectory))
        projected = project_frames(seq, frames, values, self.config.projection, seq.world)
        scans = [Scan(f"{cond.sequence} frames {b.frames[0]}..{b.frames[-1]}", b.points, b.values, PayloadType.ALPHA, b.sensor_origin)
                 for b in bin_frames(projected, self.config.projection.bin_frames)]
        names = class_set().names
        return ScanList(scans, len(names), names, seq.world.frame)

    def map_and_score(self, condition: str, method: str, bins: ScanList, gt) -> MapScores:
        """Map condition ``condition``'s projected alpha ``bins`` with ``method`` (under the study's mapping
        preset; ConvBKI, and the class gains of ebs-learned, with lengths learned on the network's training
        data), save the map under ``out/maps/CONDITION/METHOD.npz`` (reused when its inputs are unchanged)
        and score it against ``gt`` (points, labels)."""
        from ..core.mapper import load_map, save_map

        run = load_config([preset_path(self.config.mapping_preset)], method=method)
        mapping = run.mapping
        if (mapping.kernel is Kernel.COMPOUND or mapping.class_gains) and not mapping.convbki.lengths_file:
            lengths = self.convbki_lengths(self.config.conditions[condition].network, mapping.resolution_m)
            mapping = mapping.replace(convbki={"lengths_file": str(lengths)})
        key = _digest(map_cache_fields(mapping), str(self.alpha_dir(condition)), dataclasses.asdict(self.config.projection),
                      bins.frame.as_dict(), __version__)
        map_path = self.out / "maps" / condition / f"{method}.npz"
        record_path = map_path.with_suffix(".json")
        if record_path.exists() and map_path.exists() and json.loads(record_path.read_text()).get("key") == key:
            mapper = load_map(map_path)
        else:
            mapper = Mapper.for_dataset(bins, mapping, device=self.device)
            started = time.perf_counter()
            with tqdm(total=len(bins), unit="bin", disable=not self.progress, desc=f"{condition}/{method}", leave=False) as bar:
                points = sum(s.input_points for s in map_scans(mapper, bins, progress=lambda scan, _: bar.update(1)))
            elapsed = time.perf_counter() - started
            map_path.parent.mkdir(parents=True, exist_ok=True)
            save_map(map_path, mapper)
            files.write_json_atomically(record_path, {"key": key, "seconds": elapsed, "points": points, "voxels": mapper.voxel_count})
        scores = evaluate_map(mapper, gt[0], gt[1], self.config.scored_classes)
        scores.extra["voxels"] = mapper.voxel_count
        scores.extra["map_key"] = key
        self._mappers[(condition, method)] = (mapper, mapping)
        return scores

    def diagnose(self, condition: str, scores: dict[str, MapScores], gt) -> "ConditionDiagnostics":
        """The condition's uncertainty diagnostics (apps/uncertainty_study.py) for the methods mapped in
        ``scores``; cached beside its maps, keyed by them."""
        from . import uncertainty_study as us
        from ..geometry.projection import sample_map

        key = _digest(str(self.alpha_dir(condition)), {m: s.extra["map_key"] for m, s in scores.items()}, self.config.scored_classes,
                      us.DIAGNOSTICS_VERSION, __version__)
        path = self.out / "maps" / condition / "diagnostics.json"
        if path.exists():
            cached = json.loads(path.read_text())
            if cached.get("key") == key:
                return us.ConditionDiagnostics.from_arrays(cached["arrays"])
        cond = self.config.conditions[condition]
        alpha_dir, seq = self.alpha_dir(condition), self.sequence(cond.sequence)
        frames = [f for f in seq.frames if f.label_image is not None and (alpha_dir / f"{f.index:06d}.npy").exists()]
        num_classes, scored = len(class_set().names), np.asarray(self.config.scored_classes)
        labels_of = label_map_for(seq)
        pixels = us.SegmentationMetrics(num_classes)
        per_frame = []
        camera = seq.camera
        for frame in frames:
            alpha = np.load(alpha_dir / f"{frame.index:06d}.npy").astype(np.float32)
            labels = labels_of(frame)
            probabilities, u = us.uncertainty_of(alpha, axis=0)
            truth = us.pixel_labels_at_alpha(labels, alpha.shape[1:])
            pixels = pixels.merged(us.network_metrics(num_classes, probabilities.reshape(num_classes, -1).T, u.ravel(), truth.ravel(), scored))
            projected = next(project_frames(seq, [frame], lambda f, a=alpha: a, self.config.projection, seq.world))
            point_truth = sample_map(labels, projected.pixel, (camera.width, camera.height), "nearest").astype(np.int64)
            p, pu = us.uncertainty_of(projected.values, axis=1)
            per_frame.append((projected.points, pu, p.argmax(axis=1) == point_truth, point_truth, p.argmax(axis=1), p))
        n = self.config.projection.bin_frames
        insertions = [tuple(np.concatenate([f[j] for f in per_frame[i:i + n]]) for j in range(5)) for i in range(0, len(per_frame), n)]
        points = us.network_metrics(num_classes, np.concatenate([f[5] for f in per_frame]) if per_frame else np.zeros((0, num_classes)),
                                    np.concatenate([f[1] for f in per_frame]) if per_frame else np.zeros(0),
                                    np.concatenate([f[3] for f in per_frame]) if per_frame else np.zeros(0, np.int64), scored)
        methods = {}
        for method, s in scores.items():
            mapper, mapping = self._mappers[(condition, method)]
            methods[method] = us.method_diagnostics(mapping, num_classes, insertions, scored, mapper=mapper, gt=gt,
                                                    brier=(s.brier_minmax, s.brier_analytic, s.brier_per_query))
        result = us.ConditionDiagnostics(pixels, points, methods)
        files.write_json_atomically(path, {"key": key, "arrays": result.arrays()})
        return result

    # -- the whole study -------------------------------------------------------------------------
    def run(self) -> dict:
        """The whole study: every condition mapped with every method (and the ablation's methods on its
        condition), scored, pooled, and written as ``results.md``, ``scores.csv``, ``scores.json``, plots
        and ``record.json``; returns the scores by condition (and ``pool:NAME``) and method."""
        started = time.perf_counter()
        self.out.mkdir(parents=True, exist_ok=True)
        results: dict[str, dict[str, MapScores]] = {}
        diagnostics: dict = {}
        ablation = self.config.ablation
        to_train = self.training_work()
        trained_work = trained_seconds = other_seconds = 0.0
        for done, (condition, cond) in enumerate(self.config.conditions.items()):
            condition_started = time.perf_counter()
            training = to_train.pop(cond.network, 0.0)
            methods = list(self.config.methods)
            if condition in self.config.pools.get(ablation.condition, [ablation.condition]):
                methods += [m for m in ablation.methods if m not in methods]
            bins = self.bins(condition)
            gt = self.ground_truth(cond.sequence)
            stage = time.perf_counter()
            results[condition] = {}
            for method in methods:
                results[condition][method] = self.map_and_score(condition, method, bins, gt)
                self.log(f"[map] {condition:>12} {method:>14}: mIoU {100 * results[condition][method].miou:5.1f}  "
                         f"Acc {100 * results[condition][method].accuracy:5.1f}")
            if self.config.diagnostics:
                diagnostics[condition] = self.diagnose(condition, results[condition], gt)
            self._mappers.clear()  # maps are large; the diagnostics hold what they need
            self.timings[f"map+score {condition}"] = time.perf_counter() - stage
            training_s = self.timings.get(f"train {cond.network}", 0.0) if training else 0.0
            trained_work, trained_seconds = trained_work + training, trained_seconds + training_s
            other_seconds += time.perf_counter() - condition_started - training_s
            self.log(self._progress(done + 1, time.perf_counter() - started, sum(to_train.values()), trained_work, trained_seconds, other_seconds))
        self.timings["total"] = time.perf_counter() - started
        pooled = {f"pool:{name}": {m: pool_scores([results[c][m] for c in members]) for m in results[members[0]]}
                  for name, members in self.config.pools.items()}
        self._write_results(results, pooled, diagnostics)
        return results | pooled

    def _write_results(self, results: dict[str, dict[str, MapScores]], pooled: dict[str, dict[str, MapScores]], diagnostics: dict) -> None:
        from .evaluation import scored_class_names

        config = self.config
        any_scores = next(iter(next(iter(results.values())).values()))
        class_names = scored_class_names(any_scores)
        sections = [f"# {config.name}: results\n", "Queries of the 3D ground truth (2D labels projected onto the LiDAR points); IoU, mIoU, "
                    "Acc, O.Acc in %; BS x100 (lower is better; min-max normalised variance per scored voxel). "
                    "'-' marks classes absent from the ground truth.\n"]
        if config.seeds:
            sections.append(self._spread_section(results, pooled))
        else:
            sections += self._condition_sections(results, pooled, class_names)
        if config.ablation.methods:
            by_method = results.get(config.ablation.condition) or pooled[f"pool:{config.ablation.condition}"]
            rows = {m: by_method[m].row() for m in config.ablation.methods}
            sections.append(f"## Ablation ({config.ablation.condition})\n")
            sections.append(markdown_table(rows, ["mIoU", "Acc", "O.Acc", "BS", "BS (analytic)", "BS (per query)"]) + "\n")
        if diagnostics:
            sections.append(self._diagnostics_section(diagnostics))
        if self.notes:
            sections.insert(1, "**Warnings**\n\n" + "\n".join(f"- {n}" for n in self.notes) + "\n")
        files.write_text_atomically(self.out / "results.md", "\n".join(sections))
        with io.StringIO(newline="") as f:
            columns = ["condition", "method"] + class_names + ["mIoU", "Acc", "O.Acc", "BS", "BS (analytic)", "BS (per query)", "scored_queries", "occupied_queries"]
            writer = csv.DictWriter(f, columns)
            writer.writeheader()
            for condition, by_method in (results | pooled).items():
                for method, scores in by_method.items():
                    row = scores.row() | {"condition": condition, "method": method, "scored_queries": scores.scored_queries,
                                          "occupied_queries": scores.occupied_queries}
                    writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in columns})
            files.write_text_atomically(self.out / "scores.csv", f.getvalue())
        files.write_json_atomically(self.out / "scores.json", {c: {m: s.as_dict() for m, s in r.items()} for c, r in (results | pooled).items()},
                                    indent=1)
        self._plots(results, pooled, class_names)
        for name in config.networks:
            folder = self.network(name).parent
            for plot in ("reliability.png", "uncertainty.png"):
                if (folder / plot).exists():
                    shutil.copy(folder / plot, self.out / f"network_{name}_{plot}")
        record = {"experiment": dataclasses.asdict(config), "warnings": self.notes,
                  "timings_s": {k: round(v, 2) for k, v in self.timings.items()},
                  "versions": _versions(), "sequences": {k: str(v) for k, v in self._sequence_dirs.items()}}
        files.write_json_atomically(self.out / "record.json", record, indent=1, default=str)

    def _condition_sections(self, results, pooled, class_names) -> list[str]:
        config, sections = self.config, []
        for condition, by_method in results.items():
            cond = config.conditions[condition]
            rows = {m: s.row() for m, s in by_method.items() if m in config.methods}
            sections.append(f"## {condition} (network '{cond.network}' on sequence '{cond.sequence}')\n")
            sections.append(markdown_table(rows, class_names + ["mIoU", "Acc"]) + "\n")
        for pool, members in config.pools.items():
            rows = {m: p.row() for m, p in pooled[f"pool:{pool}"].items() if m in config.methods}
            for m in config.methods:
                rows[m]["mean mIoU"] = float(np.mean([100 * results[c][m].miou for c in members]))
                rows[m]["mean Acc"] = float(np.mean([100 * results[c][m].accuracy for c in members]))
            sections.append(f"## Pooled: {pool} ({', '.join(members)}; confusion matrices summed, then the mean of the per-condition scores)\n")
            sections.append(markdown_table(rows, class_names + ["mIoU", "Acc", "mean mIoU", "mean Acc"]) + "\n")
        if len(results) > 1:
            rows = {m: {} for m in config.methods}
            for condition, by_method in results.items():
                for m in config.methods:
                    rows[m][condition] = f"{100 * by_method[m].miou:.1f} / {100 * by_method[m].accuracy:.1f}"
            sections.append("## Robustness: mIoU / Acc per condition\n")
            sections.append(markdown_table(rows, list(results)) + "\n")
        return sections

    def spread(self, results, pooled) -> dict[str, dict[str, dict]]:
        """Per group (a condition or pool as configured, over the seeds) and method: mIoU and Acc (%) of each
        seed, their mean and sample standard deviation."""
        everything = results | {name[len("pool:"):]: by_method for name, by_method in pooled.items()}
        pooled_conditions = {m for members in self.config.pools.values() for m in members}
        groups: dict[str, list[str]] = {}  # a pool's scores stand for its conditions
        for name in everything:
            if name in self.config.pools or name not in pooled_conditions:
                groups.setdefault(seed_group(name), []).append(name)
        table: dict[str, dict[str, dict]] = {}
        for group, names in groups.items():
            for method in self.config.methods:
                miou = [100 * everything[n][method].miou for n in names]
                acc = [100 * everything[n][method].accuracy for n in names]
                table.setdefault(group, {})[method] = {
                    "seeds": len(names), "mIoU": miou, "Acc": acc, "mIoU mean": float(np.mean(miou)), "Acc mean": float(np.mean(acc)),
                    "mIoU sd": float(np.std(miou, ddof=1)) if len(miou) > 1 else 0.0, "Acc sd": float(np.std(acc, ddof=1)) if len(acc) > 1 else 0.0}
        return table

    def condition_groups(self) -> dict[str, list[str]]:
        """The groups the tables report: a pool's conditions over all seeds, or a condition not pooled over all seeds."""
        groups: dict[str, list[str]] = {}
        pooled = {m for members in self.config.pools.values() for m in members}
        for name, members in self.config.pools.items():
            groups.setdefault(seed_group(name), []).extend(members)
        for name in self.config.conditions:
            if name not in pooled:
                groups.setdefault(seed_group(name), []).append(name)
        return groups

    def _diagnostics_section(self, diagnostics: dict) -> str:
        from . import uncertainty_study as us

        resolution = load_config([preset_path(self.config.mapping_preset)], method=self.config.methods[0]).mapping.resolution_m
        network_rows, method_rows, class_rows, summary = {}, {}, {}, {}
        names = class_set().names
        for group, members in self.condition_groups().items():
            parts = [diagnostics[c] for c in members if c in diagnostics]
            if not parts:
                continue
            merged = parts[0]
            for part in parts[1:]:
                merged = merged.merge(part)
            summary[group] = merged.summary()
            us.plot_group(f"{group} ({len(parts)} maps of each method)", merged, self.config.methods, resolution,
                          self.out / f"diagnostics_{group}.png")
            px, pt = summary[group]["pixels"], summary[group]["points"]
            network_rows[group] = {"pixel Acc": 100 * px["accuracy"], "pixel AUROC": px["uncertainty_auroc"], "pixel ECE": px["ece"],
                                   "point Acc": 100 * pt["accuracy"], "point AUROC": pt["uncertainty_auroc"], "point ECE": pt["ece"],
                                   "u right": pt["mean_u_right"], "u wrong": pt["mean_u_wrong"]}
            for method, d in summary[group]["methods"].items():
                deciles = d["error_rate_by_variance_decile"]

                def pct(v):
                    return None if v is None else 100 * v

                method_rows[f"{group} / {method}"] = {
                    "dropped": pct(d["dropped_share"]), "right among dropped": pct(d["dropped_right_share"]),
                    "right among kept": pct(d["kept_right_share"]), "kept l < half voxel": pct(d["kept_short_share"]),
                    "kept reaching no voxel": pct(d["kept_reaching_nothing_share"]), "median l (cm)": None if d["median_length_m"] is None else 100 * d["median_length_m"],
                    "BS (per query)": d["brier_per_query"], "error, least-variance decile": pct(deciles[0]),
                    "error, most-variance decile": pct(deciles[-1])}
                if d["dropped_share"]:
                    class_rows[f"{group} / {method}"] = {names[c]: pct(d["dropped_share_by_true_class"][c]) for c in self.config.scored_classes}
        files.write_json_atomically(self.out / "diagnostics.json", summary, indent=1)
        network_table = markdown_table(network_rows, list(next(iter(network_rows.values()))), digits=3).replace("| method |", "| condition |", 1)
        method_table = markdown_table(method_rows, list(next(iter(method_rows.values()))), digits=1).replace("| method |", "| condition / method |", 1)
        return ("## Uncertainty diagnostics (all seeds and drives of each condition together)\n\n"
                "The network at the camera pixels and at the projected points (scored classes): accuracy (%), the AUROC of "
                "u = K / S for its wrong labels (0.5: u says nothing), the expected calibration error, and the mean u of its "
                "right and wrong labels.\n\n" + network_table + "\n\n"
                "What each method does with the points (%, of the scored points): the share its uncertainty threshold drops "
                "and how many of those the network had right, beside the accuracy of the points it keeps; of the kept points, "
                "the share whose adaptive kernel is shorter than half a voxel and the share whose kernel reaches no voxel "
                "center (they update nothing); the median kernel length; the map's Brier score and its error rate in the "
                "lowest and highest variance decile. Plots: diagnostics_CONDITION.png.\n\n" + method_table + "\n\n"
                + ("The share of each true class's points that the thresholds drop (%):\n\n"
                   + markdown_table(class_rows, [names[c] for c in self.config.scored_classes]).replace("| method |", "| condition / method |", 1) + "\n"
                   if class_rows else ""))

    def _spread_section(self, results, pooled) -> str:
        table = self.spread(results, pooled)
        groups = list(table)
        rows = {m: {g: (f"{table[g][m]['mIoU mean']:.1f} ± {table[g][m]['mIoU sd']:.1f} / "
                        f"{table[g][m]['Acc mean']:.1f} ± {table[g][m]['Acc sd']:.1f}") for g in groups} for m in self.config.methods}
        files.write_json_atomically(self.out / "spread.json", table, indent=1)
        return (f"## mIoU / Acc over {len(self.config.seeds)} training seeds ({', '.join(map(str, self.config.seeds))}): mean ± sd\n\n"
                "Each seed trains every network anew (initialisation, data order, validation split, and the subset when it is "
                "drawn); per-seed scores are in scores.csv and spread.json.\n\n" + markdown_table(rows, groups) + "\n")

    def _plots(self, results, pooled, class_names) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        for condition, by_method in ({} if self.config.seeds else results).items():
            methods = [m for m in self.config.methods if m in by_method]
            fig, ax = plt.subplots(figsize=(1.4 * len(class_names) + 3, 4.5))
            width = 0.8 / len(methods)
            for i, m in enumerate(methods):
                row = by_method[m].row()
                x = np.arange(len(class_names)) + i * width
                scored = [j for j, c in enumerate(class_names) if row[c] is not None]
                bars = ax.bar(x[scored], [row[class_names[j]] for j in scored], width, label=m)
                ax.bar_label(bars, fmt="%.0f", fontsize=6, padding=1)
            # a class absent from the ground truth has no IoU at all: marked, not drawn as a 0 bar
            for j, c in enumerate(class_names):
                if all(by_method[m].row()[c] is None for m in methods):
                    ax.axvspan(j - width / 2, j + 0.8 - width / 2, color="0.9", zorder=0)
                    ax.text(j + 0.4 - width / 2, 2, "absent from\nground truth", ha="center", va="bottom", fontsize=7, color="0.4")
            ax.set_xticks(np.arange(len(class_names)) + 0.4 - width / 2, class_names)
            ax.set_xlabel("class")
            ax.set_ylabel("IoU [%]")
            ax.set_ylim(0, 105)
            ax.set_title(f"Per-class IoU, {condition} (bars labelled with their value; 0 = scored and missed)")
            ax.legend(fontsize=8, ncol=min(len(methods), 6), loc="upper left")
            fig.tight_layout()
            fig.savefig(self.out / f"iou_{condition}.png", dpi=110)
            plt.close(fig)
        if self.config.ablation.methods:
            by_method = results.get(self.config.ablation.condition) or pooled[f"pool:{self.config.ablation.condition}"]
            methods = list(self.config.ablation.methods)
            panels = [(["mIoU", "Acc", "O.Acc"], "score [%] (higher is better)"), (["BS"], "Brier score x100 (lower is better)")]
            fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [3, 1.3]})
            width = 0.8 / len(methods)
            for ax, (metrics, ylabel) in zip(axes, panels):
                for i, m in enumerate(methods):
                    row = by_method[m].row()
                    bars = ax.bar(np.arange(len(metrics)) + i * width, [row[k] or 0.0 for k in metrics], width, label=m)
                    ax.bar_label(bars, fmt="%.1f", fontsize=6, padding=1)
                ax.set_xticks(np.arange(len(metrics)) + 0.4 - width / 2, metrics)
                ax.set_xlabel("metric")
                ax.set_ylabel(ylabel)
            axes[0].set_ylim(0, 110)
            handles, labels = axes[0].get_legend_handles_labels()
            fig.legend(handles, labels, loc="lower center", ncol=len(methods), fontsize=8)
            fig.suptitle(f"Ablation, {self.config.ablation.condition}")
            fig.tight_layout(rect=(0, 0.07, 1, 1))
            fig.savefig(self.out / "ablation.png", dpi=110)
            plt.close(fig)


def _subset(frames: int, spec: NetworkSpec) -> list[int]:
    """The frames of a training sequence a network trains on: all, or its share ``fraction`` (at least one),
    the first ones or drawn by the network's seed."""
    keep = max(1, int(round(frames * spec.fraction)))
    if spec.subset == "first" or keep >= frames:
        return list(range(keep))
    return sorted(int(i) for i in np.random.default_rng(spec.seed).choice(frames, keep, replace=False))


class _Frames:
    """An image dataset made of chosen frames (source, index) of other image datasets."""

    num_classes = 9

    def __init__(self, items):
        self.items = list(items)

    def __len__(self) -> int:
        return len(self.items)

    def name(self, i: int) -> str:
        source, j = self.items[i]
        return source.name(j)

    def __getitem__(self, i: int):
        source, j = self.items[i]
        return source[j]


def _versions() -> dict:
    import torch
    import warp

    return {"evsemmap_warp": __version__, "python": sys.version.split()[0], "platform": platform.platform(),
            "numpy": np.__version__, "torch": torch.__version__, "warp": warp.config.version}

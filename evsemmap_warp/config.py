"""Configs are data: small dataclasses resolved from YAML files in one place (``load_config``).

A run combines a *method* file (``configs/methods/NAME.yaml``: which kernel, which media, which
uncertainty switches) with any number of preset and dataset files (numbers and data sources). Files
are merged in order, later files winning key by key; unknown keys and inconsistent values raise.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import sys
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml


class ConfigError(ValueError):
    """A config file or value is wrong; the message names the file and the key."""


class _RenamedMembers(enum.EnumMeta):
    """Enum type whose members renamed in this release still answer to their old names, one release
    long, with a DeprecationWarning (``_RENAMED_MEMBERS``)."""

    def __getattr__(cls, name):
        new = globals().get("_RENAMED_MEMBERS", {}).get(cls.__name__, {}).get(name)
        if new is None:
            if hasattr(enum.EnumMeta, "__getattr__"):  # before Python 3.12, members that shadow a class attribute
                return enum.EnumMeta.__getattr__(cls, name)
            raise AttributeError(f"type object {cls.__name__!r} has no attribute {name!r}")
        warnings.warn(f"{cls.__name__}.{name} is deprecated, use {cls.__name__}.{new} (the old name goes in the next release)",
                      DeprecationWarning, stacklevel=2)
        return cls[new]


class _RenamedValues(str, enum.Enum, metaclass=_RenamedMembers):
    """A config enum whose values renamed in this release still read, one release long: map files and
    stores written before carry them (read silently), config files are told by ``load_config``."""

    @classmethod
    def _missing_(cls, value):
        new = RENAMED_VALUES.get(cls.__name__, {}).get(value)
        return cls(new) if new is not None else None


class Kernel(_RenamedValues):
    """How a point spreads its evidence over the voxels around it (``mapping.kernel``). A kernel other
    than sparse and count comes with its method's own integration (``core.integrators``)."""
    SPARSE = "sparse"  # BKI sparse kernel k'(d, l, sigma0)
    COUNT = "count"  # counting sensor model: weight 1 inside the point's own voxel
    COMPOUND = "compound"  # ConvBKI's per-class compound kernel on a voxel-center stencil (docs/compatibility.md §2)
    TRIANGULAR = "triangular"  # SEE-CSOM's triangular kernel on entropy-gated blocks (docs/compatibility.md §3)


class Fusion(str, enum.Enum):
    """How the evidence that reaches a voxel combines (``mapping.fusion``)."""
    BAYES = "bayes"  # Dirichlet concentrations add up (every BKI / CSM method)
    DEMPSTER = "dempster"  # belief masses fused with Dempster's rule (docs/algorithm.md §3.7)


class Media(_RenamedValues):
    """What a point contributes per class (``mapping.media``), whatever its payload (``PayloadType``)."""
    ONEHOT = "onehot"  # one-hot of the payload's argmax class, lowest index on ties (S-CSM, S-BKI)
    SOFT = "soft"  # the class-probability vector: alpha / S for alpha payloads (EBS, the "Prob." ablations)


class ThresholdScope(str, enum.Enum):
    """Over which points the uncertainty threshold drops its fraction (``mapping.threshold_scope``)."""
    INSERTION = "insertion"  # the most uncertain points of the whole insertion (the paper)
    # the most uncertain points of each class the network predicted, in each insertion: a class the network is
    # unsure of as a whole (small objects, rare ground) keeps its surest points instead of losing most of them
    PREDICTED_CLASS = "predicted-class"


class Compat(_RenamedValues):
    """Which program's map to compute: the paper's algorithm or one of the original C++ programs
    (``mapping.compat``)."""
    CLEAN = "clean"  # the paper's algorithm with a true radius search (default)
    SBKI = "sbki"  # reproduce the original S-BKI / S-CSM C++ (docs/compatibility.md §1)
    RELEASE = "release"  # reproduce the released EvSemMap C++ for ebs / dempster (docs/compatibility.md §4)


# Renamed in this release; the old names go in the next. Values: what config files, map files and
# stores wrote (YAML values); members: the Python names.
RENAMED_VALUES = {
    "Kernel": {"convbki": "compound", "see-csom": "triangular"},
    "Media": {"prob": "soft"},
    "Compat": {"evsemmap": "release"},
}
_RENAMED_MEMBERS = {
    "Kernel": {"CONVBKI": "COMPOUND", "SEE_CSOM": "TRIANGULAR"},
    "Media": {"PROB": "SOFT"},
    "Compat": {"EVSEMMAP": "RELEASE"},
}
# Mapping presets renamed in this release: old name -> new.
RENAMED_PRESETS = {"evsemmap-release": "release"}


def warn_deprecated(old: str, new: str) -> None:
    """Tell the user, in one line on stderr, that ``old`` (a flag, a config key or value, a preset) is
    now ``new``; once per process for each."""
    if (old, new) in _WARNED:
        return
    _WARNED.add((old, new))
    print(f"evsemmap: warning: {old} is deprecated, use {new} (the old name goes in the next release)", file=sys.stderr)


_WARNED: set[tuple[str, str]] = set()


# A kernel that visits more voxels than this per point is a mistake (a length in the wrong unit, say),
# not a map: 50 m at 0.2 m would be 65 million voxels per point, hours for one scan.
MAX_VOXELS_PER_POINT = 50_000


class PayloadType(str, enum.Enum):
    """What a scan's per-point payload holds, and so how ``Mapper.integrate`` reads it (``Media`` says what
    a point then contributes to the map)."""
    ALPHA = "alpha"  # evidential Dirichlet parameters, [N, K], alpha >= 1
    PROB = "prob"  # class probabilities, [N, K], rows sum to 1
    LABEL = "label"  # integer class ids, [N]


class ScatterStrategy(str, enum.Enum):
    """How the radius kernel (clean mode, Bayes fusion) reaches the map (``mapping.clean.scatter_strategy``);
    sorted and gather sum each voxel in a fixed order (docs/kernel_study.md)."""
    ATOMIC = "atomic"  # scatter with atomic adds
    SORTED = "sorted"  # sort-then-reduce
    GATHER = "gather"  # per voxel, through a hash grid of the points


@dataclass(frozen=True)
class SbkiSettings:
    """S-BKI's point preparation and blocks (``mapping.sbki``), which the sbki and release compatibility
    modes and SEE-CSOM share (docs/compatibility.md §1, §3, §4)."""

    block_depth: int = 2  # blocks of 2^(depth - 1) cells a side
    ds_resolution_m: float = 0.1  # VoxelGrid leaf of the hits (m); the release mode's snapping grid
    free_resolution_m: float = 4.0  # spacing of the free-space samples along each ray (m); sbki mode only
    max_range_m: float | None = None  # hits farther from the sensor are dropped (m); null: no range filter


@dataclass(frozen=True)
class ReleaseSettings:
    """The release compatibility mode (``mapping.release``, docs/compatibility.md §4)."""

    # each 0.4 m block keeps its first ds_multiplier + 1 points per scan;
    # null: the release's own value, 10 for ebs (Bayes fusion) and 5 for dempster
    ds_multiplier: int | None = None


@dataclass(frozen=True)
class ConvBkiSettings:
    """ConvBKI's compound kernel (``mapping.convbki``, docs/compatibility.md §2)."""

    # per-class length scales (a .pt state dict with ell_h / ell_z, or .json / .yaml / .npz with the same
    # keys); empty: every class at its authors' initial 0.5 m
    lengths_file: str = ""
    stencil_half: int = 2  # the stencil is (2h + 1)^3 voxels


@dataclass(frozen=True)
class CleanSettings:
    """The clean mode's sparse kernel (``mapping.clean``)."""

    scatter_strategy: ScatterStrategy = ScatterStrategy.ATOMIC  # how the radius kernel with Bayes fusion reaches the map


# The keys MappingConfig had before its mode sections, as map files, stores and config files may still
# hold them: old key -> (section, key). Their -1 / <= 0 sentinels now read None (_old_sentinel).
MOVED_MAPPING_KEYS = {
    "block_depth": ("sbki", "block_depth"),
    "ds_resolution_m": ("sbki", "ds_resolution_m"),
    "free_resolution_m": ("sbki", "free_resolution_m"),
    "max_range_m": ("sbki", "max_range_m"),
    "scatter_strategy": ("clean", "scatter_strategy"),
    "ds_multiplier": ("release", "ds_multiplier"),
    "convbki_lengths_file": ("convbki", "lengths_file"),
    "convbki_stencil_half": ("convbki", "stencil_half"),
}


def _old_sentinel(key: str, value: Any) -> Any:
    """An old flat key's value in the new form: max_range_m <= 0 and ds_multiplier -1 meant "none"."""
    if key == "max_range_m" and isinstance(value, (int, float)) and not isinstance(value, bool) and value <= 0:
        return None
    if key == "ds_multiplier" and isinstance(value, int) and not isinstance(value, bool) and value == -1:
        return None
    return value


def upgrade_mapping_dict(data: dict, source: str = "", *, tell: bool = False) -> dict:
    """A ``mapping`` dict with the flat keys of before the mode sections (MOVED_MAPPING_KEYS) moved into
    their sections, sentinels as None; ``tell``: say so once per key on stderr (config files; map files
    and stores are read silently). A key given both ways raises."""
    if not isinstance(data, dict) or not any(key in data for key in MOVED_MAPPING_KEYS):
        return data
    out = {k: (dict(v) if k in _MAPPING_SECTIONS and isinstance(v, dict) else v) for k, v in data.items() if k not in MOVED_MAPPING_KEYS}
    where = f"{source}: " if source else ""
    for old, value in data.items():
        if old not in MOVED_MAPPING_KEYS:
            continue
        section, key = MOVED_MAPPING_KEYS[old]
        holder = out.setdefault(section, {})
        if not isinstance(holder, dict):
            raise ConfigError(f"{where}mapping.{section} must be a mapping, got {type(holder).__name__}")
        if key in holder:
            raise ConfigError(f"{where}mapping.{old} and mapping.{section}.{key} are the same key; give it once, as mapping.{section}.{key}")
        if tell:
            warn_deprecated(f"{where}mapping.{old}", f"mapping.{section}.{key}")
        holder[key] = _old_sentinel(old, value)
    return out


@dataclass(frozen=True)
class MappingConfig:
    """Everything the mapper needs. Lengths in metres; see docs/algorithm.md §3. The fields of one mode
    only live in its section (sbki, release, convbki, clean)."""

    method: str = "ebs"  # the method's name, recorded in map files (a method file's method.name)
    kernel: Kernel = Kernel.SPARSE  # how a point spreads its evidence over the voxels around it
    fusion: Fusion = Fusion.BAYES  # how evidence in a voxel combines
    media: Media = Media.SOFT  # what a point contributes per class
    adaptive_length: bool = True  # the kernel length shrinks with a point's uncertainty (docs/algorithm.md §3.4)
    uncertainty_threshold: bool = True  # drop each insertion's most uncertain points (docs/algorithm.md §3.2)
    compat: Compat = Compat.CLEAN  # which program's map to compute
    resolution_m: float = 0.2  # voxel edge (m)
    prior: float = 1.0  # every voxel's initial concentration per class (alpha0)
    length_m: float = 0.2  # l; the kernel length is l * beta * exp(1 - gamma u_i) when adaptive
    beta: float = 0.5  # scale of the adaptive length
    gamma: float = 10.0  # how fast the adaptive length shrinks with u
    uncertainty_drop_fraction: float = 0.1  # u~: the most uncertain fraction dropped per insertion
    threshold_scope: ThresholdScope = ThresholdScope.INSERTION  # ... of the whole insertion, or per predicted class
    sigma0: float = 1.0  # kernel amplitude: k'(0) = sigma0 (S-BKI's sf2)
    sbki: SbkiSettings = field(default_factory=SbkiSettings)  # S-BKI's blocks (sbki and release modes, SEE-CSOM)
    release: ReleaseSettings = field(default_factory=ReleaseSettings)  # the release mode
    convbki: ConvBkiSettings = field(default_factory=ConvBkiSettings)  # ConvBKI's compound kernel
    clean: CleanSettings = field(default_factory=CleanSettings)  # the clean mode's sparse kernel

    def __post_init__(self) -> None:
        # every check of the mapping parameters, the sections' included, is here: one place, dotted keys
        def need(ok: bool, name: str, text: str) -> None:
            if not ok:
                value = self
                for part in name.split("."):
                    value = getattr(value, part)
                raise ConfigError(f"mapping.{name} = {value!r}: {text}")

        for section, cls in _MAPPING_SECTIONS.items():
            if not isinstance(getattr(self, section), cls):
                raise ConfigError(f"mapping.{section} = {getattr(self, section)!r}: must be a {cls.__name__}")
        for name, value in _dotted_items(self):
            if isinstance(value, float) and not math.isfinite(value):
                need(False, name, "must be a finite number")
        need(self.resolution_m > 0, "resolution_m", "must be > 0")
        need(self.prior > 0, "prior", "must be > 0 (a Dirichlet concentration)")
        need(self.length_m > 0, "length_m", "must be > 0")
        need(self.beta > 0, "beta", "must be > 0")
        need(self.gamma >= 0, "gamma", "must be >= 0")
        need(0 <= self.uncertainty_drop_fraction < 1, "uncertainty_drop_fraction", "must lie in [0, 1)")
        need(self.sigma0 > 0, "sigma0", "must be > 0")
        need(1 <= self.sbki.block_depth <= 8, "sbki.block_depth", "must lie in 1..8")
        need(self.sbki.ds_resolution_m > 0, "sbki.ds_resolution_m", "must be > 0")
        need(self.sbki.free_resolution_m > 0, "sbki.free_resolution_m", "must be > 0")
        need(self.sbki.max_range_m is None or self.sbki.max_range_m > 0, "sbki.max_range_m", "must be > 0 (or null: no range filter)")
        need(0 <= self.convbki.stencil_half <= 8, "convbki.stencil_half", "must lie in 0..8")
        visits = self.voxels_per_point()
        if visits > MAX_VOXELS_PER_POINT:
            longest = self.longest_length_m()
            raise ConfigError(
                f"mapping.length_m = {self.length_m!r} at resolution_m = {self.resolution_m!r}: each point would visit about "
                f"{visits:,.0f} voxels (kernel reach {longest:.3g} m = {longest / self.resolution_m:.0f} voxels; at most "
                f"{MAX_VOXELS_PER_POINT:,} allowed); is a length in the wrong unit?")
        if self.kernel is Kernel.TRIANGULAR:
            need(self.media is Media.ONEHOT, "media", "SEE-CSOM takes hard labels (its code has no soft-label path)")
        if self.fusion is Fusion.DEMPSTER:
            need(self.kernel is Kernel.SPARSE, "kernel", "the Dempster-Shafer variant discounts beliefs with the sparse kernel")
            need(self.media is Media.SOFT, "media", "the Dempster-Shafer variant fuses belief masses from the Dirichlet (media soft)")
        if self.compat is Compat.SBKI:
            need(self.kernel in (Kernel.SPARSE, Kernel.COUNT) and self.fusion is Fusion.BAYES, "kernel",
                 "the sbki compatibility mode reproduces S-BKI / S-CSM only")
            need(self.media is Media.ONEHOT, "media", "the sbki compatibility mode reproduces S-BKI/S-CSM, which take one-hot labels")
            need(not self.adaptive_length, "adaptive_length", "the original S-BKI has no adaptive length")
            need(not self.uncertainty_threshold, "uncertainty_threshold", "the original S-BKI has no uncertainty threshold")
        need(isinstance(self.clean.scatter_strategy, ScatterStrategy), "clean.scatter_strategy", "must be atomic, sorted or gather")
        if self.clean.scatter_strategy is not ScatterStrategy.ATOMIC:
            need(self.kernel is Kernel.SPARSE and self.fusion is Fusion.BAYES and self.compat is Compat.CLEAN, "clean.scatter_strategy",
                 "the sorted and gather strategies integrate the clean sparse kernel with Bayes fusion (s-bki, ebs, prob*)")
        need(self.release.ds_multiplier is None or self.release.ds_multiplier >= 0, "release.ds_multiplier",
             "must be >= 0 (or null: the release's value for the fusion)")
        if self.compat is Compat.RELEASE:
            need(self.kernel is Kernel.SPARSE, "kernel", "the release mode reproduces the release's ebs and dempster (sparse kernel)")
            need(self.media is Media.SOFT, "media", "the released ebs and dempster read class probabilities (media soft)")
            need(self.adaptive_length and self.beta == 1.0 and self.gamma == 0.0, "adaptive_length",
                 "the release's kernel length is the constant length_m * e: set adaptive_length true, beta 1, gamma 0")
            need(self.uncertainty_threshold, "uncertainty_threshold", "the released ebs and dempster cut the most uncertain points")
        if self.threshold_scope is not ThresholdScope.INSERTION:
            need(self.compat is Compat.CLEAN and self.kernel is Kernel.SPARSE, "threshold_scope",
                 "a threshold per predicted class is an option of the clean sparse-kernel methods (ebs, dempster, prob-*)")

    def longest_length_m(self) -> float:
        """The longest kernel length any point can get (u = 0 with the adaptive length)."""
        if self.kernel is not Kernel.SPARSE:
            return self.resolution_m
        return self.length_m * self.beta * math.e if self.adaptive_length else self.length_m

    def voxels_per_point(self) -> float:
        """About how many voxels one point's kernel visits (the ball of the longest length)."""
        if self.kernel is Kernel.COUNT:
            return 1.0
        if self.kernel is Kernel.COMPOUND:
            return float((2 * self.convbki.stencil_half + 1) ** 3)
        if self.kernel is Kernel.TRIANGULAR:
            return 7.0 * 8.0  # a block and its 6 face neighbours, 2x2x2 cells each
        reach = self.longest_length_m() / self.resolution_m
        ball = 4.0 / 3.0 * math.pi * (reach + 0.5) ** 3
        if self.compat is Compat.SBKI:
            return min(ball, 7.0 * 8.0 ** (self.sbki.block_depth - 1))  # the owner block and its 6 face neighbours
        if self.compat is Compat.RELEASE:
            return 25.0 * 8.0 ** (self.sbki.block_depth - 1)  # the blocks within L1 distance 2 of the point's block
        return ball

    @property
    def release_block_cap(self) -> int:
        """Points each block keeps per scan in the release mode: ds_multiplier + 1."""
        if self.release.ds_multiplier is not None:
            return self.release.ds_multiplier + 1
        return (5 if self.fusion is Fusion.DEMPSTER else 10) + 1

    @property
    def keep_quantile(self) -> float:
        """The share of each insertion's points the uncertainty threshold keeps: 1 -
        ``uncertainty_drop_fraction``."""
        return 1.0 - self.uncertainty_drop_fraction

    def replace(self, **changes) -> "MappingConfig":
        """``dataclasses.replace``; a section may also be given as a dict of the keys to change in it
        (``config.replace(sbki={"block_depth": 3})``)."""
        for name, value in changes.items():
            if name in _MAPPING_SECTIONS and isinstance(value, dict):
                changes[name] = dataclasses.replace(getattr(self, name), **value)
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """Every field by name, sections as dicts, enums as their YAML values (what map files record as
        ``meta.mapping``)."""
        return _as_dict(self)

    @classmethod
    def from_dict(cls, data: Any, source: str = "mapping") -> "MappingConfig":
        """The config a map file or store recorded (``as_dict``), flat keys of before the mode sections
        included (read silently); a ConfigError names ``source`` and the dotted key."""
        return dataclass_from_dict(cls, upgrade_mapping_dict(data, source), source)


_MAPPING_SECTIONS = {"sbki": SbkiSettings, "release": ReleaseSettings, "convbki": ConvBkiSettings, "clean": CleanSettings}


def _as_dict(obj) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        out[f.name] = _as_dict(value) if dataclasses.is_dataclass(value) else value.value if isinstance(value, enum.Enum) else value
    return out


def _dotted_items(obj, prefix: str = ""):
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _dotted_items(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", value


def flat_items(mapping: dict, prefix: str = "") -> dict[str, Any]:
    """A nested ``as_dict`` as one level of dotted keys (``sbki.block_depth``), to name what differs."""
    out = {}
    for key, value in mapping.items():
        if isinstance(value, dict):
            out.update(flat_items(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def legacy_flat_dict(mapping: dict) -> dict[str, Any]:
    """``MappingConfig.as_dict()`` in the flat form of before the mode sections, sentinels included
    (max_range_m -1.0, ds_multiplier -1), for keys that must not change with the refactor (cached maps)."""
    out = {k: v for k, v in mapping.items() if k not in _MAPPING_SECTIONS}
    for old, (section, key) in MOVED_MAPPING_KEYS.items():
        out[old] = mapping[section][key]
    if out["max_range_m"] is None:
        out["max_range_m"] = -1.0
    if out["ds_multiplier"] is None:
        out["ds_multiplier"] = -1
    return out


@dataclass(frozen=True)
class BagConfig:
    """How to read a robot log (``dataset.kind: bag``): topics, frames and the pose source. Empty
    topics are not read; an empty frame is taken from the messages' headers. The built-in preset
    ``rellis3d-bag`` holds RELLIS-3D's topic names."""

    cloud_topic: str = ""  # sensor_msgs/PointCloud2; "": the log's only PointCloud2 topic
    label_field: str = "label"  # per-point labels in this cloud field (as S-BKI's /labeled_pointcloud)
    label_ontology: str = "rellis3d"  # rellis3d (ids remapped to the 9 v3 classes), semantickitti, or none (class ids)
    image_topic: str = ""  # sensor_msgs/Image or CompressedImage
    camera_info_topic: str = ""  # sensor_msgs/CameraInfo of image_topic
    label_image_topic: str = ""  # 2D label ids (mono8/mono16 Image, or a PNG CompressedImage), for ground truth
    image_tolerance_s: float = 0.05  # a cloud pairs with the nearest image at most this far apart in time
    pose_source: str = "tf"  # tf: the TF tree from fixed_frame to the LiDAR; odometry: odometry_topic + extrinsic
    fixed_frame: str = ""  # "": the root of the LiDAR's TF tree (tf) or the odometry's header frame (odometry)
    lidar_frame: str = ""  # "": the clouds' header frame
    camera_frame: str = ""  # "": the images' header frame
    odometry_topic: str = ""  # nav_msgs/Odometry, when pose_source is odometry
    tf_topic: str = "/tf"  # tf2_msgs/TFMessage with the moving transforms
    tf_static_topic: str = "/tf_static"  # tf2_msgs/TFMessage with the fixed transforms
    # x y z qx qy qz qw; empty: from the TF tree. lidar: the LiDAR's pose in the odometry's child frame;
    # camera: the camera's pose in the LiDAR frame (what RELLIS-3D's transforms.yaml stores).
    lidar_extrinsic: tuple[float, ...] = ()
    camera_extrinsic: tuple[float, ...] = ()  # x y z qx qy qz qw, see lidar_extrinsic

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, text: str) -> None:
            if not ok:
                raise ConfigError(f"dataset.bag.{name} = {getattr(self, name)!r}: {text}")

        need(self.pose_source in ("tf", "odometry"), "pose_source", "must be tf or odometry")
        need(self.pose_source != "odometry" or bool(self.odometry_topic), "odometry_topic", "pose_source odometry needs an odometry topic")
        need(self.label_ontology in ("rellis3d", "semantickitti", "none"), "label_ontology", "must be rellis3d, semantickitti or none")
        need(math.isfinite(self.image_tolerance_s) and self.image_tolerance_s >= 0, "image_tolerance_s", "must be a finite number >= 0")
        for name in ("lidar_extrinsic", "camera_extrinsic"):
            value = getattr(self, name)
            need(len(value) in (0, 7), name, "must be empty or 7 numbers x y z qx qy qz qw")
            need(all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value), name, "must be finite numbers")
            need(not value or any(value[3:]), name, "has a zero quaternion")
        need(not self.label_image_topic or bool(self.image_topic), "label_image_topic", "label images pair with camera images: set image_topic too")


@dataclass(frozen=True)
class DatasetConfig:
    """Where scans come from. ``paths`` are candidates, the first existing one is used; a ``bag``
    dataset reads every one of its ``logs`` in order instead (ROS 1 .bag files, ROS 2 bag folders,
    .db3 or .mcap files), as ``bag`` says."""

    kind: str = ""  # rellis3d, semantickitti, bag (robot logs), pcd_sequence (numbered PCD files) or bench_npz (an .npz workload)
    paths: tuple[str, ...] = ()  # candidate locations of the data, relative to the config file; the first that exists is read
    logs: tuple[str, ...] = ()  # a bag dataset's robot logs, read in order as one drive
    bag: BagConfig = field(default_factory=BagConfig)  # how to read the logs (the dataset.bag section)
    pattern: str = ""  # pcd_sequence: the scans' file names, with {index} for the number (e.g. "scan_{index}.pcd")
    first_index: int = 1  # pcd_sequence: the first scan's number
    last_index: int = 1  # pcd_sequence: the last scan's number (inclusive)
    payload: PayloadType = PayloadType.LABEL  # what each point carries
    num_classes: int = 0  # classes of the payload; 0: the sequence's class set (a pcd_sequence must give it)
    class_names: tuple[str, ...] = ()  # names of the classes; empty: the sequence's class set
    # The world frame the map lives in (docs/algorithm.md §6.6). "": the data's own frame (a log's fixed
    # frame; a folder's poses.txt frame, named by its frame.yaml or after the folder; a point file's
    # frame); a name: the name of a folder's or point files' frame (a log's must equal its fixed frame);
    # "first-scan": the paper's convention, coordinates relative to the first scan's LiDAR pose.
    frame: str = ""
    crs: str = ""  # EPSG code of georeferenced coordinates (e.g. EPSG:32617, UTM zone 17N); "": none or the folder's frame.yaml
    config_dir: str = "."  # folder of the file that named the paths (they are relative to it)

    def __post_init__(self) -> None:
        from .frames import FIRST_SCAN, FrameError, check_crs

        try:
            object.__setattr__(self, "crs", check_crs(self.crs, "dataset.crs") or "")
        except FrameError as exc:
            raise ConfigError(str(exc)) from None
        if self.frame.strip() != self.frame:
            raise ConfigError(f"dataset.frame = {self.frame!r}: a frame name has no leading or trailing spaces")
        if self.kind == "bag" and self.frame not in ("", FIRST_SCAN):
            # a log's world frame is its fixed frame: naming the frame chooses it
            if self.bag.fixed_frame and self.bag.fixed_frame != self.frame:
                raise ConfigError(f"dataset.frame = {self.frame!r} but dataset.bag.fixed_frame = {self.bag.fixed_frame!r}: a log is mapped "
                                  f"in its fixed frame; give one of them")
            object.__setattr__(self, "bag", dataclasses.replace(self.bag, fixed_frame=self.frame))

    def resolve_path(self) -> Path:
        """The first of ``paths`` that exists (relative ones are relative to the config file that named
        them); raises ConfigError listing every path tried when none does."""
        tried = []
        for candidate in self.paths:
            path = Path(candidate).expanduser()
            if not path.is_absolute():
                path = (Path(self.config_dir) / path).resolve()
            tried.append(str(path))
            if path.exists():
                return path
        raise ConfigError(f"dataset.paths: none of these exists: {tried}")

    def resolve_logs(self) -> list[Path]:
        """The robot logs of a bag dataset as paths, in order; raises ConfigError when there are none, one
        does not exist or one is named twice."""
        if not self.logs:
            raise ConfigError("dataset.logs: a bag dataset needs at least one log (a .bag, .mcap or .db3 file or a ROS 2 bag folder): "
                              "name them on the command line or in dataset.logs")
        resolved = []
        for candidate in self.logs:
            path = Path(candidate).expanduser()
            path = path if path.is_absolute() else (Path(self.config_dir) / path).resolve()
            if not path.exists():
                raise ConfigError(f"dataset.logs: {path} does not exist")
            if path.resolve() in [p.resolve() for p in resolved]:  # read twice, every cloud would be integrated twice
                raise ConfigError(f"dataset.logs: {candidate} is given twice; name each log once")
            resolved.append(path)
        return resolved


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
_METHOD_KEYS = {"name", "kernel", "fusion", "media", "adaptive_length", "uncertainty_threshold", "threshold_scope", "compat"}


def methods_dir() -> Path:
    """The folder of the method files (``configs/methods/``, installed as ``evsemmap_warp.configs.methods``)."""
    return Path(str(resources.files("evsemmap_warp.configs") / "methods"))


def preset_path(name_or_path: str) -> Path:
    """A mapping preset by name (``configs/presets/NAME.yaml``, e.g. rellis3d, offroad) or path."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") and path.exists():
        return path
    presets = Path(str(resources.files("evsemmap_warp.configs") / "presets"))
    if name_or_path in RENAMED_PRESETS:
        warn_deprecated(f"mapping preset {name_or_path!r}", repr(RENAMED_PRESETS[name_or_path]))
        name_or_path = RENAMED_PRESETS[name_or_path]
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


def read_yaml_file(path, what: str = "config file") -> Any:
    """A YAML (or JSON) file's content, or a ConfigError naming the file when it is missing, not text
    (binary junk) or not YAML."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such {what}") from None
    except (UnicodeDecodeError, IsADirectoryError):
        raise ConfigError(f"{path}: not a text file (a YAML {what} was expected)") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None


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


# an optional field: a value other than null converts as this default would
_OPTIONAL_KINDS = {"float | None": 0.0, "int | None": 0, "str | None": ""}


def _convert(cls, name: str, value: Any, source: str) -> Any:
    ftype = {f.name: f.type for f in dataclasses.fields(cls)}[name]
    default = {f.name: f.default for f in dataclasses.fields(cls)}[name]
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{source}: {name} = {value!r} must be a finite number")
    if str(ftype) in _OPTIONAL_KINDS:
        if value is None:
            return None
        default = _OPTIONAL_KINDS[str(ftype)]
    try:
        if isinstance(default, enum.Enum):
            return type(default)(value)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise TypeError
            return value
        if isinstance(default, int):
            if isinstance(value, bool) or int(value) != value:
                raise TypeError
            return int(value)
        if isinstance(default, float):
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if isinstance(default, tuple):
            items = tuple(value) if isinstance(value, (list, tuple)) else (value,)
            if any(isinstance(item, (dict, list, tuple)) for item in items):
                raise TypeError
            if str(ftype) == "tuple[str, ...]" and not all(isinstance(item, str) for item in items):  # paths, logs, names
                raise TypeError
            return items
        if isinstance(default, str):
            if not isinstance(value, str):
                raise TypeError
            return value
        return value
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: {name} = {value!r} is not a valid {ftype}") from None


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


def load_config(config_paths: list[str | Path], method: str | None = None, *, frame: str | None = None, crs: str | None = None) -> RunConfig:
    """Merge the method file (if any) and the given files, later ones winning; validate. A folder
    among the paths is a sequence to map (``dataset_for_folder``), robot logs are a ``bag`` dataset
    (read in the order given), a bare name a built-in preset. ``frame`` and ``crs`` (the --frame and
    --crs flags) override the files' dataset.frame and dataset.crs."""
    mapping: dict[str, Any] = {}
    dataset: dict[str, Any] = {}
    bag: dict[str, Any] = {}
    bin_frames = 1
    sources = []
    logs = [Path(p) for p in config_paths if is_robot_log(p)]
    if logs:
        dataset.update(kind="bag", logs=tuple(str(p.resolve()) for p in logs))
        sources += [str(p) for p in logs]
    config_paths = [p for p in config_paths if not is_robot_log(p)]
    folders = [Path(p) for p in config_paths if Path(p).is_dir()]
    if folders and logs:
        raise ConfigError(f"map either a sequence folder or robot logs, got both: {str(folders[0])!r} and {str(logs[0])!r}")
    if len(folders) > 1:
        raise ConfigError(f"one sequence folder per run, got {len(folders)}: {[str(f) for f in folders]}")
    if folders:
        dataset.update(dataset_for_folder(folders[0]))
        sources.append(str(folders[0]))
    # a bare name (no .yaml, no such file) is a built-in mapping preset: rellis3d, offroad, ...
    files = ([method_path(method)] if method else []) + [
        preset_path(str(p)) if not Path(p).exists() and Path(p).suffix == "" else Path(p) for p in config_paths if not Path(p).is_dir()]
    for path in files:
        data = _read_yaml(path)
        sources.append(str(path))
        for section, values in data.items():
            if section == "pipeline":
                if not isinstance(values, dict) or set(values) - {"bin_frames"}:
                    raise ConfigError(f"{path}: pipeline takes only bin_frames, got {values!r}")
                if "bin_frames" in values:
                    bins = values["bin_frames"]
                    if isinstance(bins, bool) or not isinstance(bins, int) or bins < 1:
                        raise ConfigError(f"{path}: pipeline.bin_frames = {bins!r} must be a whole number >= 1")
                    bin_frames = bins
                continue
            if not isinstance(values, dict):
                raise ConfigError(f"{path}: section {section!r} must be a mapping")
            cls = _SECTIONS[section]
            if section == "mapping":
                values = upgrade_mapping_dict(values, str(path), tell=True)
            for key, value in values.items():
                if not isinstance(key, str):
                    raise ConfigError(f"{path}: key {key!r} in section {section!r} is not a name (a {type(key).__name__})")
                if section == "method":
                    if key not in _METHOD_KEYS:
                        raise ConfigError(f"{path}: method.{key} is not a method switch; allowed: {sorted(_METHOD_KEYS)}")
                    key = "method" if key == "name" else key
                known = {f.name for f in dataclasses.fields(cls)} - {"config_dir"}
                if key not in known:
                    raise ConfigError(f"{path}: unknown key {section}.{key}; known: {sorted(known)}")
                renamed = RENAMED_VALUES.get(type(getattr(cls, key, None)).__name__, {})
                if isinstance(value, str) and value in renamed:
                    warn_deprecated(f"{path}: {section}.{key}: {value}", f"{section}.{key}: {renamed[value]}")
                if section == "dataset" and key == "bag":
                    # key by key, so a user's file can change one topic of a preset
                    if not isinstance(value, dict):
                        raise ConfigError(f"{path}: dataset.bag must be a mapping, got {type(value).__name__}")
                    known = {f.name for f in dataclasses.fields(BagConfig)}
                    unknown = sorted(str(k) for k in value if k not in known)
                    if unknown:  # named now, with its file; values are checked once all files are merged
                        raise ConfigError(f"{path}: unknown key(s) dataset.bag.{unknown[0]}; known: {sorted(known)}")
                    bag.update(value)
                    continue
                if section == "mapping" and key in _MAPPING_SECTIONS:
                    # key by key, so a dataset file can change one of a preset's mode settings
                    if not isinstance(value, dict):
                        raise ConfigError(f"{path}: mapping.{key} must be a mapping, got {type(value).__name__}")
                    sub = _MAPPING_SECTIONS[key]
                    known = {f.name for f in dataclasses.fields(sub)}
                    for subkey, subvalue in value.items():
                        if subkey not in known:
                            raise ConfigError(f"{path}: unknown key mapping.{key}.{subkey}; known: {sorted(known)}")
                        mapping.setdefault(key, {})[subkey] = _convert(sub, subkey, subvalue, f"{path}: mapping.{key}")
                    continue
                if section == "dataset" and key == "logs" and "logs" in dataset and logs:
                    continue  # logs named on the command line win over a config's
                converted = _convert(cls, key, value, f"{path}: {section}")
                if section == "dataset":
                    dataset[key] = converted
                    if key in ("paths", "logs"):  # relative paths belong to the file that names them
                        dataset["config_dir"] = str(path.resolve().parent)
                else:
                    mapping[key] = converted
    try:
        mapping_cfg = MappingConfig(**{k: _MAPPING_SECTIONS[k](**v) if k in _MAPPING_SECTIONS else v for k, v in mapping.items()})
    except ConfigError as exc:
        raise ConfigError(f"{' + '.join(sources)}: {exc}") from None
    if bag:
        dataset["bag"] = dataclass_from_dict(BagConfig, bag, " + ".join(sources) + ": dataset.bag")
    if (frame is not None or crs is not None) and not dataset:
        raise ConfigError(f"{' + '.join(sources) or 'no config'}: --frame / --crs place a dataset's scans, and none is named")
    if crs is not None:  # a bad flag named as the flag, not as the dataset.crs key it stands for
        from .frames import FrameError, check_crs

        try:
            check_crs(crs, "--crs")
        except FrameError as exc:
            raise ConfigError(str(exc)) from None
    if dataset:
        # --frame / --crs win over the files' dataset.frame / dataset.crs
        dataset.update({k: v for k, v in (("frame", frame), ("crs", crs)) if v is not None})
    try:
        dataset_cfg = DatasetConfig(**dataset) if dataset else None
    except ConfigError as exc:
        raise ConfigError(f"{' + '.join(sources) or '--frame/--crs'}: {exc}") from None
    return RunConfig(mapping=mapping_cfg, dataset=dataset_cfg, sources=tuple(sources), bin_frames=bin_frames)


def dataclass_from_dict(cls, data: Any, source: str):
    """Build a (possibly nested) frozen dataclass from a YAML mapping: unknown keys and wrongly typed
    values raise a ConfigError naming ``source`` and the dotted key; missing keys keep the defaults."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    not_names = [k for k in data if not isinstance(k, str)]
    if not_names:
        raise ConfigError(f"{source}: key {not_names[0]!r} is not a name (a {type(not_names[0]).__name__})")
    unknown = set(data) - set(fields)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; known: {sorted(fields)}")
    values = {}
    for name, value in data.items():
        default = fields[name].default
        if default is dataclasses.MISSING and fields[name].default_factory is not dataclasses.MISSING:
            default = fields[name].default_factory()
        if dataclasses.is_dataclass(default):
            values[name] = dataclass_from_dict(type(default), value, f"{source}.{name}")
        elif isinstance(default, dict):  # already-parsed sub-mappings (e.g. named entries)
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {name} must be a mapping, got {type(value).__name__}")
            values[name] = dict(value)
        else:
            values[name] = _convert(cls, name, value, source)
    try:
        return cls(**values)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None

"""The ``mapping`` section: ``MappingConfig``, every parameter the mapper takes, and its mode sections
(``sbki``, ``release``, ``convbki``, ``clean``), each checked where it is built."""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field
from typing import Any

from .convert import dataclass_from_dict
from .enums import Compat, Fusion, Kernel, Media, ScatterStrategy, ThresholdScope
from .errors import ConfigError


# A kernel that visits more voxels than this per point is a mistake (a length in the wrong unit, say),
# not a map: 50 m at 0.2 m would be 65 million voxels per point, hours for one scan.
MAX_VOXELS_PER_POINT = 50_000


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
    # each class's media times its gain: the mass of ConvBKI's kernel with that class's learned lengths
    # (convbki.lengths_file), over the classes' mean (ebs-learned, docs/unseen.md)
    class_gains: bool = False
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

        for section, cls in MAPPING_SECTIONS.items():
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
        if self.class_gains:
            need(self.compat is Compat.CLEAN and self.kernel is Kernel.SPARSE and self.fusion is Fusion.BAYES and self.media is Media.SOFT,
                 "class_gains", "class gains scale the class probabilities of the clean sparse kernel with Bayes fusion (ebs, prob-*)")

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
            if name in MAPPING_SECTIONS and isinstance(value, dict):
                changes[name] = dataclasses.replace(getattr(self, name), **value)
        return dataclasses.replace(self, **changes)

    def as_dict(self, *, every_key: bool = False) -> dict[str, Any]:
        """Every field by name, sections as dicts, enums as their YAML values (what map files record as
        ``meta.mapping``). class_gains only when true or ``every_key`` (dump-config): every other method's maps
        and stores keep their bytes and identity, and a file without it reads back as false."""
        out = _as_dict(self)
        if not (self.class_gains or every_key):
            del out["class_gains"]
        return out

    @classmethod
    def from_dict(cls, data: Any, source: str = "mapping") -> "MappingConfig":
        """The config a map file or store recorded (``as_dict``); a ConfigError names ``source`` and the
        dotted key."""
        return dataclass_from_dict(cls, data, source)


# The mode sections of ``mapping``, by key: what reads each one.
MAPPING_SECTIONS = {"sbki": SbkiSettings, "release": ReleaseSettings, "convbki": ConvBkiSettings, "clean": CleanSettings}


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

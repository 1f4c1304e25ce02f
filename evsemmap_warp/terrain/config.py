"""The terrain layers' settings: which classes support a robot, the filter windows, and the cost table
(docs/terrain.md). One YAML file holds both sections; ``configs/terrain/costs_v3.yaml`` is the
default for the remap-v3 / RELLIS-3D classes, and ``evsemmap layers --costs FILE`` names another.

    layers:  {surface_classes: [...], clearance_m: 1.5, plane_window_cells: 5, step_window_cells: 3, min_plane_cells: 6}
    costs:   {classes: {name: cost, ...}, lethal_classes: [...], lethal_probability: 0.5,
              uncertainty_weight: 1.0, max_slope_deg: 25, slope_weight: 0.3, max_step_m: 0.3, free_step_m: 0.2,
              step_weight: 0.3}

A file's class names are checked against the map's when the layers are computed (``check_classes``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import yaml

from ..config import ConfigError, dataclass_from_dict

DEFAULT_COSTS_NAME = "costs_v3.yaml"


def default_costs_path() -> Path:
    """The default cost table, ``configs/terrain/costs_v3.yaml`` (the 9 remap-v3 / RELLIS-3D classes)."""
    return Path(str(resources.files("evsemmap_warp.configs") / "terrain" / DEFAULT_COSTS_NAME))


@dataclass(frozen=True)
class LayerSettings:
    """What the column reduction and the filters use.

    ``surface_classes``: classes whose occupied voxels support a robot (the ground); the highest one in
    a cell is its ``elevation``. ``clearance_m``: how far above the support an occupied voxel still meets
    a robot (higher ones, a canopy, are overhangs). ``plane_window_cells``, ``step_window_cells``: odd
    window edges (cells) of the plane fit (slope, roughness) and of the step. ``min_plane_cells``: known
    cells a plane fit needs. ``min_evidence``: evidence (summed over classes) an OCCUPIED voxel needs to
    count; below it a voxel holds only the tails of kernels centered elsewhere."""

    surface_classes: tuple = ("water", "paved", "unpaved", "dirt", "grass")  # classes whose occupied voxels support a robot
    clearance_m: float = 1.5  # occupied voxels up to this far above the support meet a robot; higher ones are overhangs
    min_evidence: float = 0.0  # evidence (summed over classes) an OCCUPIED voxel needs to count
    plane_window_cells: int = 5  # odd window edge of the plane fit (slope, roughness), cells
    step_window_cells: int = 3  # odd window edge of the step, cells
    min_plane_cells: int = 6  # known cells a plane fit needs

    def __post_init__(self):
        for key in ("plane_window_cells", "step_window_cells"):
            value = getattr(self, key)
            if value < 1 or value % 2 == 0:
                raise ConfigError(f"layers.{key} = {value} must be an odd number of cells >= 1")
        if self.min_plane_cells < 3:
            raise ConfigError(f"layers.min_plane_cells = {self.min_plane_cells}: a plane needs at least 3 cells")
        if self.min_plane_cells > self.plane_window_cells ** 2:
            raise ConfigError(f"layers.min_plane_cells = {self.min_plane_cells} exceeds the {self.plane_window_cells}^2 cells of the window")
        if not self.min_evidence >= 0:
            raise ConfigError(f"layers.min_evidence = {self.min_evidence} must be >= 0")
        if not self.clearance_m >= 0:
            raise ConfigError(f"layers.clearance_m = {self.clearance_m} must be >= 0")
        if not all(isinstance(name, str) for name in self.surface_classes) or not self.surface_classes:
            raise ConfigError(f"layers.surface_classes = {list(self.surface_classes)} must be a non-empty list of class names")


@dataclass(frozen=True)
class CostSettings:
    """The cost model (docs/terrain.md): per-class costs (>= 0) under the Dirichlet of the voxel a robot
    meets, ``uncertainty_weight`` standard deviations above their mean, plus slope and step terms; a
    cell is lethal when that voxel's class is a lethal class, or the lethal classes' expected
    probability reaches ``lethal_probability`` (two lethal classes sharing a voxel), or its slope or
    step passes its limit."""

    classes: dict = field(default_factory=dict)  # class name -> cost >= 0; every class of the map needs one
    lethal_classes: tuple = ()  # classes a robot must not meet
    lethal_probability: float = 0.5  # lethal when the lethal classes' expected probability reaches this
    uncertainty_weight: float = 1.0  # standard deviations of the class cost added to its mean
    max_slope_deg: float = 25.0  # steeper is lethal; below it the slope adds slope_weight * slope / max_slope_deg
    slope_weight: float = 0.3  # cost of a slope just below max_slope_deg
    max_step_m: float = 0.3  # a larger step is lethal
    free_step_m: float = 0.2  # steps up to this cost nothing; then the cost rises linearly to step_weight at max_step_m
    step_weight: float = 0.3  # cost of a step just below max_step_m

    def __post_init__(self):
        for name, cost in self.classes.items():
            if not isinstance(name, str):
                raise ConfigError(f"costs.classes: key {name!r} is not a class name")
            if isinstance(cost, bool) or not isinstance(cost, (int, float)) or not math.isfinite(cost) or cost < 0:
                raise ConfigError(f"costs.classes.{name} = {cost!r} must be a finite cost >= 0")
        for key in ("uncertainty_weight", "slope_weight", "step_weight"):
            if getattr(self, key) < 0:
                raise ConfigError(f"costs.{key} = {getattr(self, key)} must be >= 0")
        for key in ("max_slope_deg", "max_step_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"costs.{key} = {getattr(self, key)} must be > 0")
        if not 0 <= self.free_step_m < self.max_step_m:
            raise ConfigError(f"costs.free_step_m = {self.free_step_m} must lie in [0, max_step_m = {self.max_step_m})")
        if not 0 < self.lethal_probability <= 1:
            raise ConfigError(f"costs.lethal_probability = {self.lethal_probability} must lie in (0, 1]")


@dataclass(frozen=True)
class TerrainConfig:
    """The terrain settings of one file: the column reduction's and filters' ``layers``, the cost model's
    ``costs``, and the file they came from (for messages)."""

    layers: LayerSettings = field(default_factory=LayerSettings)
    costs: CostSettings = field(default_factory=CostSettings)
    source: str = "defaults"  # the file it was read from

    def check_classes(self, class_names) -> None:
        """Raise a ConfigError naming the file, the key and the names when the file names classes the
        map lacks, or leaves a map class without a cost."""
        names = list(class_names)
        for key, given in (("layers.surface_classes", self.layers.surface_classes), ("costs.classes", list(self.costs.classes)),
                           ("costs.lethal_classes", self.costs.lethal_classes)):
            unknown = [n for n in given if n not in names]
            if unknown:
                raise ConfigError(f"{self.source}: {key} names classes the map does not have: {unknown}; the map's classes: {names}")
        missing = [n for n in names if n not in self.costs.classes]
        if missing:
            raise ConfigError(f"{self.source}: costs.classes gives no cost for the map's classes {missing}")


def load_terrain_config(path=None) -> TerrainConfig:
    """The terrain settings of a YAML file (the default cost table without one); errors name the file and key."""
    path = Path(path) if path is not None else default_costs_path()
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (a YAML cost table was expected)") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with 'layers' and 'costs' sections, got {type(data).__name__}")
    unknown = sorted(set(map(str, data)) - {"layers", "costs"})
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; known: ['costs', 'layers']")
    try:
        layers = dataclass_from_dict(LayerSettings, data.get("layers"), f"{path}: layers")
        costs = dataclass_from_dict(CostSettings, data.get("costs"), f"{path}: costs")
    except ConfigError as exc:
        message = str(exc)
        raise ConfigError(message if message.startswith(str(path)) else f"{path}: {message}") from None
    return TerrainConfig(layers, costs, str(path))

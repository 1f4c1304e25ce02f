"""The terrain layers' settings: which classes support a robot, the filter windows, and the cost table
(docs/terrain.md). One YAML file holds both sections; ``configs/terrain/costs_v3.yaml`` is the
default for the remap-v3 / RELLIS-3D classes, and ``evsemmap layers --costs FILE`` lays another over it:
a file overrides exactly the keys it names (``costs.classes`` class by class), the rest keep the defaults.

    layers:  {surface_classes: [...], clearance_m: 1.5, min_evidence: 0.2, plane_window_cells: 9,
              step_window_cells: 3, min_plane_cells: 20}
    costs:   {rule: evidential, classes: {name: cost, ...}, unknown_cost: 0.5, lethal_classes: [...],
              lethal_probability: 0.5, uncertainty_weight: 1.0, max_slope_deg: 25, slope_weight: 0.3,
              max_step_m: 0.3, free_step_m: 0.2, step_weight: 0.3}

The class names a file gives are checked against the map's when the layers are computed
(``check_classes``); the default table's names that a map lacks are left out silently.
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

    # the defaults are configs/terrain/costs_v3.yaml's layers section (tests/test_terrain_costs.py holds them equal)
    surface_classes: tuple = ("water", "paved", "unpaved", "dirt", "grass")  # classes whose occupied voxels support a robot
    clearance_m: float = 1.5  # occupied voxels up to this far above the support meet a robot; higher ones are overhangs
    min_evidence: float = 0.2  # evidence (summed over classes) an OCCUPIED voxel needs to count
    plane_window_cells: int = 9  # odd window edge of the plane fit (slope, roughness), cells
    step_window_cells: int = 3  # odd window edge of the step, cells
    min_plane_cells: int = 20  # known cells a plane fit needs

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


COST_RULES = ("evidential", "expected")


@dataclass(frozen=True)
class CostSettings:
    """The cost model (docs/terrain.md), read on the voxel a robot meets. The ``evidential`` rule (the
    default) splits its Dirichlet as subjective logic does, into a belief per class b_c = e_c / S and an
    uncommitted mass u = W / S (W the prior's total weight), and costs them apart: the class cost is that
    of the committed belief, sum_c b_c cost_c / (1 - u) = sum_c e_c cost_c / sum_c e_c, so a cell costs
    what the table says for the class its evidence shows, however much there is; how much there is stays
    its own band (``surface_uncommitted``), and a cell with no voxel of at least the layers'
    ``min_evidence`` (``terrain.known``) is unknown rather than costed. The ``expected`` rule takes the
    costs' mean under the Dirichlet plus ``uncertainty_weight`` standard deviations, which pulls a weakly
    observed cell towards the table's mean. Slope and step terms are added; a cell is lethal when that
    voxel's class is a lethal class, or the lethal classes' share of the committed belief (``expected``:
    their expected probability) reaches ``lethal_probability`` (two lethal classes sharing a voxel), or its
    slope or step passes its limit."""

    classes: dict = field(default_factory=dict)  # class name -> cost >= 0; every class of the map needs one
    rule: str = "evidential"  # evidential: the committed belief's class mix, sum e_c cost_c / sum e; expected: mean + k std
    unknown_cost: float = 0.5  # evidential rule: the cost of a voxel that holds no evidence at all (reached with min_evidence 0)
    lethal_classes: tuple = ()  # classes a robot must not meet
    lethal_probability: float = 0.5  # lethal when the lethal classes' share of the belief (expected rule: expected probability) reaches this
    uncertainty_weight: float = 1.0  # expected rule: standard deviations of the class cost added to its mean
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
        if self.rule not in COST_RULES:
            raise ConfigError(f"costs.rule = {self.rule!r} is not a cost rule; known: {list(COST_RULES)}")
        if not (math.isfinite(self.unknown_cost) and self.unknown_cost >= 0):
            raise ConfigError(f"costs.unknown_cost = {self.unknown_cost} must be a finite cost >= 0")
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
    # the keys the file named (``layers.min_evidence``, ``costs.classes.grass``), as laid over the default table:
    # class names the file gives must be the map's; those the defaults give may be missing from it
    named: frozenset = frozenset()

    def check_classes(self, class_names) -> None:
        """Raise a ConfigError naming the file, the key and the names when the file names classes the
        map lacks, leaves a map class without a cost, or leaves the map no surface class."""
        names = list(class_names)
        named_costs = [n for n in self.costs.classes if f"costs.classes.{n}" in self.named]
        for key, given in (("layers.surface_classes", self.layers.surface_classes if key_named(self, "layers.surface_classes") else ()),
                           ("costs.classes", named_costs),
                           ("costs.lethal_classes", self.costs.lethal_classes if key_named(self, "costs.lethal_classes") else ())):
            unknown = [n for n in given if n not in names]
            if unknown:
                raise ConfigError(f"{self.source}: {key} names classes the map does not have: {unknown}; the map's classes: {names}")
        missing = [n for n in names if n not in self.costs.classes]
        if missing:
            raise ConfigError(f"{self.source}: costs.classes gives no cost for the map's classes {missing}")
        if not any(n in names for n in self.layers.surface_classes):
            raise ConfigError(f"{self.source}: layers.surface_classes {list(self.layers.surface_classes)} holds none of the map's "
                              f"classes {names}: name the classes a robot stands on")


def key_named(config: TerrainConfig, key: str) -> bool:
    """Whether ``key`` came from the config's own file, not from the defaults it is laid over. A config built
    in Python (``named`` empty, ``source`` "defaults") names every key."""
    return key in config.named or (not config.named and config.source == "defaults")


def _read_sections(path: Path) -> dict:
    """A cost file's ``layers`` and ``costs`` sections as dicts (absent ones empty); errors name the file."""
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
    sections = {}
    for section in ("layers", "costs"):
        values = data.get(section) or {}
        if not isinstance(values, dict):
            raise ConfigError(f"{path}: {section} must be a mapping, got {type(values).__name__}")
        sections[section] = dict(values)
    if "classes" in sections["costs"] and not isinstance(sections["costs"]["classes"], dict):
        raise ConfigError(f"{path}: costs.classes must be a mapping of class name to cost, got {type(sections['costs']['classes']).__name__}")
    return sections


def load_terrain_config(path=None) -> TerrainConfig:
    """The terrain settings: the default table (configs/terrain/costs_v3.yaml), with the keys the YAML file
    ``path`` names laid over it (``costs.classes`` class by class); errors name the file and key."""
    default = default_costs_path()
    merged = _read_sections(default)
    named: set[str] = set()
    path = Path(path) if path is not None else default
    if path.resolve() != default.resolve():
        for section, values in _read_sections(path).items():
            for key, value in values.items():
                if section == "costs" and key == "classes":
                    merged["costs"]["classes"] = {**merged["costs"]["classes"], **value}
                    named |= {f"costs.classes.{name}" for name in value}
                else:
                    merged[section][key] = value
                named.add(f"{section}.{key}")
    try:
        layers = dataclass_from_dict(LayerSettings, merged["layers"], f"{path}: layers")
        costs = dataclass_from_dict(CostSettings, merged["costs"], f"{path}: costs")
    except ConfigError as exc:
        message = str(exc)
        raise ConfigError(message if message.startswith(str(path)) else f"{path}: {message}") from None
    return TerrainConfig(layers, costs, str(path), frozenset(named))

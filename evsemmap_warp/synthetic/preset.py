"""Synthetic-world presets: plain dataclasses read from ``configs/synthetic/NAME.yaml`` (or a path)."""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from ..config import ConfigError, dataclass_from_dict, read_yaml_file


@dataclass(frozen=True)
class WorldParams:
    size_m: float = 100.0  # square world, centred on the origin
    terrain_cell_m: float = 0.5
    hill_amplitude_m: float = 2.0
    road_half_width_m: float = 3.0
    trail_half_width_m: float = 1.4
    gravel_road_fraction: float = 0.35  # share of the road's length that is unpaved (gravel), not asphalt
    dirt_fraction: float = 0.08  # share of the open ground covered by dirt patches
    puddles: int = 12
    trees_per_hectare: float = 50.0
    bushes_per_hectare: float = 120.0
    rocks_per_hectare: float = 30.0
    vehicles: int = 3
    poles: int = 10
    barrels: int = 8
    barriers: int = 4  # void obstacles (RELLIS "barrier")
    # > 0: a corridor of this many size_m squares along x, generated tile by tile as the drive reaches
    # them (only the tiles in sensor range are held), for drives of any length
    corridor_tiles: int = 0

    def __post_init__(self):
        if self.corridor_tiles < 0:
            raise ConfigError(f"world: corridor_tiles must be >= 0, got {self.corridor_tiles}")
        if not 0 <= self.gravel_road_fraction <= 1:
            raise ConfigError(f"world: gravel_road_fraction must lie in [0, 1], got {self.gravel_road_fraction}")
        if self.size_m <= 0 or self.terrain_cell_m <= 0 or self.size_m / self.terrain_cell_m > 4000:
            raise ConfigError(f"world: size_m {self.size_m} / terrain_cell_m {self.terrain_cell_m} must be positive and give <= 4000 cells a side")


@dataclass(frozen=True)
class TrajectoryParams:
    frames: int = 60
    spacing_m: float = 1.0
    sensor_height_m: float = 1.9
    margin_m: float = 12.0  # distance kept from the world's edge

    def __post_init__(self):
        if self.frames < 1 or self.spacing_m <= 0:
            raise ConfigError(f"trajectory: frames ({self.frames}) must be >= 1 and spacing_m ({self.spacing_m}) > 0")


@dataclass(frozen=True)
class LidarParams:
    beams: int = 64
    azimuth_steps: int = 1024
    fov_up_deg: float = 16.6
    fov_down_deg: float = -16.6
    max_range_m: float = 80.0
    range_noise_m: float = 0.015
    dropout: float = 0.02
    water_dropout: float = 0.6  # puddles are specular: most beams do not come back

    def __post_init__(self):
        if self.beams < 1 or self.azimuth_steps < 1 or not self.fov_down_deg < self.fov_up_deg:
            raise ConfigError(f"lidar: need beams >= 1, azimuth_steps >= 1 and fov_down_deg < fov_up_deg, got {self}")
        if not (self.max_range_m > 0 and self.range_noise_m >= 0):
            raise ConfigError(f"lidar: max_range_m must be > 0 and range_noise_m >= 0, got {self.max_range_m}, {self.range_noise_m}")
        if not (0 <= self.dropout < 1 and 0 <= self.water_dropout <= 1):
            raise ConfigError(f"lidar: dropout probabilities must lie in [0, 1), got {self.dropout}, {self.water_dropout}")


@dataclass(frozen=True)
class CameraParams:
    width: int = 640
    height: int = 400
    hfov_deg: float = 70.0
    pitch_deg: float = -6.0  # downward tilt
    offset_m: tuple = (0.15, 0.0, -0.25)  # camera centre in the LiDAR frame (x forward, y left, z up)
    distortion: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)  # OpenCV k1 k2 p1 p2 k3
    jpeg_quality: int = 95

    def __post_init__(self):
        if self.width < 8 or self.height < 8 or not 10 <= self.hfov_deg <= 150:
            raise ConfigError(f"camera: need width, height >= 8 and 10 <= hfov_deg <= 150, got {self.width}x{self.height}, {self.hfov_deg}")
        if len(self.offset_m) != 3 or len(self.distortion) != 5:
            raise ConfigError(f"camera: offset_m needs 3 values and distortion 5 (k1 k2 p1 p2 k3), got {self.offset_m}, {self.distortion}")


@dataclass(frozen=True)
class AppearanceParams:
    domain: str = "summer"
    noise_sigma: float = 3.0  # sensor noise, 8-bit grey levels

    def __post_init__(self):
        from .appearance import DOMAINS

        if self.domain not in DOMAINS:
            raise ConfigError(f"appearance.domain must be one of {sorted(DOMAINS)}, got {self.domain!r}")


@dataclass(frozen=True)
class SynthPreset:
    name: str = "custom"
    seed: int = 0
    world: WorldParams = field(default_factory=WorldParams)
    trajectory: TrajectoryParams = field(default_factory=TrajectoryParams)
    lidar: LidarParams = field(default_factory=LidarParams)
    camera: CameraParams = field(default_factory=CameraParams)
    appearance: AppearanceParams = field(default_factory=AppearanceParams)


def presets_dir() -> Path:
    return Path(str(resources.files("evsemmap_warp.configs") / "synthetic"))


def available_presets() -> list[str]:
    return sorted(p.stem for p in presets_dir().glob("*.yaml"))


def load_preset(name_or_path: str, **overrides) -> SynthPreset:
    """A preset by name (``configs/synthetic/NAME.yaml``) or path; ``overrides`` replace top-level
    keys or nested ones given as ``section__key`` (``appearance__domain="dusk"``)."""
    path = Path(name_or_path)
    if not (path.suffix in (".yaml", ".yml") and path.exists()):
        path = presets_dir() / f"{name_or_path}.yaml"
        if not path.exists():
            raise ConfigError(f"unknown synthetic preset {name_or_path!r}; available: {', '.join(available_presets())}")
    data = read_yaml_file(path, "synthetic preset") or {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level, got {type(data).__name__}")
    data.setdefault("name", path.stem)
    for key, value in overrides.items():
        if value is None:
            continue
        section, _, sub = key.partition("__")
        if sub:
            data.setdefault(section, {})[sub] = value
        else:
            data[section] = value
    return dataclass_from_dict(SynthPreset, data, str(path))

"""Synthetic-world presets: plain dataclasses read from ``configs/synthetic/NAME.yaml`` (or a path)."""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from ..config import ConfigError, dataclass_from_dict, read_yaml_file


@dataclass(frozen=True)
class WorldParams:
    """The procedural world: its size, terrain, road and trail, and how many of each object it holds (lengths
    in m)."""

    size_m: float = 100.0  # square world, centered on the origin
    terrain_cell_m: float = 0.5  # edge of the terrain mesh's cells
    hill_amplitude_m: float = 2.0  # peak-to-trough height of the rolling terrain
    road_half_width_m: float = 3.0  # the road the drive follows
    trail_half_width_m: float = 1.4  # the unpaved trail beside it
    gravel_road_fraction: float = 0.35  # share of the road's length that is unpaved (gravel), not asphalt
    dirt_fraction: float = 0.08  # share of the open ground covered by dirt patches
    puddles: int = 12  # water patches on the ground
    trees_per_hectare: float = 50.0  # density off the road
    bushes_per_hectare: float = 120.0  # density off the road
    rocks_per_hectare: float = 30.0  # density off the road
    vehicles: int = 3  # objects placed by the road
    poles: int = 10  # objects placed by the road
    barrels: int = 8  # objects placed by the road
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
    """The drive: LiDAR frames every ``spacing_m`` along the road, the sensor ``sensor_height_m`` above it."""

    frames: int = 60  # LiDAR frames (fewer when the road is too short)
    spacing_m: float = 1.0  # distance between frames along the road
    sensor_height_m: float = 1.9  # the LiDAR above the road
    margin_m: float = 12.0  # distance kept from the world's edge

    def __post_init__(self):
        if self.frames < 1 or self.spacing_m <= 0:
            raise ConfigError(f"trajectory: frames ({self.frames}) must be >= 1 and spacing_m ({self.spacing_m}) > 0")


@dataclass(frozen=True)
class LidarParams:
    """The spinning LiDAR: beams and columns, vertical field of view (degrees), range, range noise (m) and
    dropouts."""

    beams: int = 64  # rows of the spinning LiDAR
    azimuth_steps: int = 1024  # columns per revolution
    fov_up_deg: float = 16.6  # vertical field of view, upper edge
    fov_down_deg: float = -16.6  # vertical field of view, lower edge
    max_range_m: float = 80.0  # beams hitting nothing nearer return nothing
    range_noise_m: float = 0.015  # standard deviation of the measured range
    dropout: float = 0.02  # probability that a return is lost
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
    """The pinhole camera on its LiDAR mount: image size (px), field of view and tilt (degrees), offset (m,
    LiDAR frame), OpenCV distortion and JPEG quality."""

    width: int = 640  # image size (px)
    height: int = 400  # image size (px)
    hfov_deg: float = 70.0  # horizontal field of view
    pitch_deg: float = -6.0  # downward tilt
    offset_m: tuple = (0.15, 0.0, -0.25)  # camera center in the LiDAR frame (x forward, y left, z up)
    distortion: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)  # OpenCV k1 k2 p1 p2 k3
    jpeg_quality: int = 95  # of the written camera images

    def __post_init__(self):
        if self.width < 8 or self.height < 8 or not 10 <= self.hfov_deg <= 150:
            raise ConfigError(f"camera: need width, height >= 8 and 10 <= hfov_deg <= 150, got {self.width}x{self.height}, {self.hfov_deg}")
        if len(self.offset_m) != 3 or len(self.distortion) != 5:
            raise ConfigError(f"camera: offset_m needs 3 values and distortion 5 (k1 k2 p1 p2 k3), got {self.offset_m}, {self.distortion}")


@dataclass(frozen=True)
class AppearanceParams:
    """How the camera sees the world: the appearance domain (colors and light) and the sensor noise."""

    domain: str = "summer"  # appearance: summer, autumn or dusk (colors and light; geometry and labels unchanged)
    noise_sigma: float = 3.0  # sensor noise, 8-bit grey levels

    def __post_init__(self):
        from .appearance import DOMAINS

        if self.domain not in DOMAINS:
            raise ConfigError(f"appearance.domain must be one of {sorted(DOMAINS)}, got {self.domain!r}")


@dataclass(frozen=True)
class SynthPreset:
    """A synthetic preset (``configs/synthetic/NAME.yaml``): its name, seed and the sections world,
    trajectory, lidar, camera and appearance."""

    name: str = "custom"  # recorded in the sequence's synth.yaml; a built-in preset's file name
    seed: int = 0  # the world, the drive and the sensor noise follow from it
    world: WorldParams = field(default_factory=WorldParams)
    trajectory: TrajectoryParams = field(default_factory=TrajectoryParams)
    lidar: LidarParams = field(default_factory=LidarParams)
    camera: CameraParams = field(default_factory=CameraParams)
    appearance: AppearanceParams = field(default_factory=AppearanceParams)


def presets_dir() -> Path:
    """The folder of the built-in synthetic presets (``configs/synthetic/``, installed as
    ``evsemmap_warp.configs.synthetic``)."""
    return Path(str(resources.files("evsemmap_warp.configs") / "synthetic"))


def available_presets() -> list[str]:
    """The built-in synthetic preset names, sorted."""
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

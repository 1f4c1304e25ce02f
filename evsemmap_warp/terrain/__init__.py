"""Terrain layers: the stage after mapping that turns a voxel map into the 2.5-D grids a planner or a
GIS reads (elevation, slope, roughness, step, surface class and its uncertainty, traversability cost,
lethal mask), and writes them as a GeoTIFF, an .npz, PNG previews and a ROS bag (docs/terrain.md)."""

from .config import CostSettings, LayerSettings, TerrainConfig, default_costs_path, load_terrain_config
from .known import evidence_sums, is_known
from .api import compute_layers
from .layers import LayerGrid, TerrainLayers, band_names
from .pipeline import write_layers

__all__ = [
    "CostSettings", "LayerGrid", "LayerSettings", "TerrainConfig", "TerrainLayers", "band_names", "compute_layers",
    "default_costs_path", "evidence_sums", "is_known", "load_terrain_config", "write_layers",
]

"""``compute_layers``: the terrain layers of a map or of a store (docs/terrain.md)."""

from __future__ import annotations

from ..core.map_store import MapStore
from ..core.mapper import Mapper
from .config import TerrainConfig, load_terrain_config
from .layers import TerrainLayers, map_layers
from .stores import store_layers_in_memory


def compute_layers(source, *, resolution_m=None, bounds=None, config: TerrainConfig | None = None, device: str = "cpu") -> TerrainLayers:
    """The terrain layers of a Mapper, or the mosaic of a MapStore's tiles (in memory: ``write_layers``
    streams a store to files instead).

    ``resolution_m``: cell edge (m), default the map's voxel size (a store's must divide its tiles).
    ``bounds``: [x0, y0, x1, y1] or [x0, y0, z0, x1, y1, z1] (m, the map's world frame): the grid covers
    the cells meeting it, and only voxels whose centers lie in its z range count. ``config``: surface
    classes, windows and cost table (``load_terrain_config``; default: configs/terrain/costs_v3.yaml)."""
    config = config if config is not None else load_terrain_config()
    if isinstance(source, MapStore):
        return store_layers_in_memory(source, resolution_m=resolution_m, bounds=bounds, config=config, device=device)
    if not isinstance(source, Mapper):
        raise ValueError(f"compute_layers takes a Mapper or a MapStore, got {type(source).__name__}")
    return map_layers(source, resolution_m=resolution_m, bounds=bounds, config=config, device=device)

"""Terrain layers of a map store, tile by tile, with the memory of a few tiles (docs/terrain.md).

A store's tiles are cubes of ``tile_voxels`` voxels; the layers of a tile column (the tiles of one
x-y square, all z) need its voxels only, and its filters need the cells within ``halo_cells`` of its
edges, which the neighbouring columns' own bands give. The columns are swept along the longer side
of the store, so the own bands held at any time are those of three rows of tile columns across the
shorter side (each column's are computed once), and every finished column's layers go to the outputs
at once. The mosaic of the tiles' layers is the layers ``compute_layers`` gives for the whole map.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..core.map_store import MapStore, StoreError, parse_tile_name
from .config import TerrainConfig
from .layers import (LayerGrid, TerrainLayers, VoxelColumns, band_names, check_bounds, check_resolution, finish_layers, grid_covering,
                     halo_cells, neighbourhood_filters, own_bands, to_north_up)


@dataclass
class StorePlan:
    """What a store's layers are computed over: the mosaic grid, and the tile columns (x, y) -> tile names."""

    store: MapStore
    grid: LayerGrid
    cells_per_tile: int
    columns: dict[tuple[int, int], list[str]]
    bounds: np.ndarray | None


def plan_store_layers(store: MapStore, *, resolution_m=None, bounds=None, config: TerrainConfig) -> StorePlan:
    """Check the inputs against the store (classes, cell size, bounds, tile files) and pick the grid."""
    config.check_classes(store.class_names)
    voxel_m = store.config.resolution_m
    cell_m = check_resolution(resolution_m, voxel_m)
    bounds = check_bounds(bounds)
    tile_m = store.tile_voxels * voxel_m
    cells_per_tile = round(tile_m / cell_m)
    if cells_per_tile < 1 or abs(cells_per_tile * cell_m - tile_m) > 1e-9 * tile_m:
        raise ValueError(f"resolution_m = {cell_m}: a store's cells must divide its {tile_m} m tiles ({store.tile_voxels} voxels of "
                         f"{voxel_m} m) into whole cells, e.g. {voxel_m} or {2 * voxel_m} m")
    if halo_cells(config) > cells_per_tile:
        raise ValueError(f"{config.source}: the filters reach {halo_cells(config)} cells beyond a cell, more than a tile of the store "
                         f"({cells_per_tile} cells of {cell_m} m); use smaller windows or smaller cells")
    if not store.tiles:
        raise ValueError(f"{store.path}: the store holds no tiles: there is nothing to compute layers from")
    boxes = np.array([store.tiles[name]["bounds_m"] for name in sorted(store.tiles)], np.float64)  # [T, 2, 3]
    extent = np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)])
    names = store.tiles_in(bounds) if bounds is not None else sorted(store.tiles)
    if bounds is not None and not names:
        box = ", ".join(f"{a} {lo:.2f}..{hi:.2f}" for a, lo, hi in zip("xyz", extent[0], extent[1]))
        raise ValueError(f"bounds {bounds.reshape(-1).tolist()} lie outside the store {store.path} (its tiles span {box})")
    missing = [name for name in names if not store.tile_path(name).is_file()]
    if missing:
        shown = ", ".join(str(store.tile_path(n).relative_to(store.path)) for n in missing[:5])
        raise StoreError(f"{store.path}: {len(missing)} of the {len(names)} tiles it lists are missing ({shown}"
                         f"{', ...' if len(missing) > 5 else ''}); re-run the batch that wrote it, or export the tiles that are there")
    offset_m = store.template.grid_offset_m
    if bounds is None:
        used = np.array([store.tiles[name]["bounds_m"] for name in names], np.float64)
        # voxel boxes: the cells holding their centers
        half = voxel_m / 2
        grid = grid_covering((used[:, 0, 0].min() + half, used[:, 1, 0].max() - half), (used[:, 0, 1].min() + half, used[:, 1, 1].max() - half),
                             cell_m, offset_m)
    else:
        grid = grid_covering(bounds[:, 0], bounds[:, 1], cell_m, offset_m)
    columns: dict[tuple[int, int], list[str]] = {}
    for name in names:
        x, y, _ = parse_tile_name(name)
        columns.setdefault((x, y), []).append(name)
    return StorePlan(store, grid, cells_per_tile, columns, bounds)


def tile_voxels(store: MapStore, name: str):
    """A tile's voxels (read and checked by the store: format, identity and checksums are its business)
    and their read-out."""
    voxels = store.tile_arrays(name)
    return voxels, store.template.summarize(voxels.evidence, voxels.touched)


def _column_grid(plan: StorePlan, column: tuple[int, int]) -> LayerGrid | None:
    """The part of the mosaic grid over one tile column (None when they do not meet)."""
    n, grid = plan.cells_per_tile, plan.grid
    i0, j0 = max(column[0] * n, grid.first_cell[0]), max(column[1] * n, grid.first_cell[1])
    i1 = min((column[0] + 1) * n, grid.first_cell[0] + grid.width)
    j1 = min((column[1] + 1) * n, grid.first_cell[1] + grid.height)
    if i1 <= i0 or j1 <= j0:
        return None
    return LayerGrid(grid.cell_m, grid.offset_m, (i0, j0), i1 - i0, j1 - j0)


def _paste(source_grid: LayerGrid, source: np.ndarray, target_grid: LayerGrid, target: np.ndarray) -> None:
    """Copy the overlap of two grids of one lattice (arrays [height, width], row j northward)."""
    i0 = max(source_grid.first_cell[0], target_grid.first_cell[0])
    j0 = max(source_grid.first_cell[1], target_grid.first_cell[1])
    i1 = min(source_grid.first_cell[0] + source_grid.width, target_grid.first_cell[0] + target_grid.width)
    j1 = min(source_grid.first_cell[1] + source_grid.height, target_grid.first_cell[1] + target_grid.height)
    if i1 <= i0 or j1 <= j0:
        return
    si, sj = i0 - source_grid.first_cell[0], j0 - source_grid.first_cell[1]
    ti, tj = i0 - target_grid.first_cell[0], j0 - target_grid.first_cell[1]
    target[tj:tj + j1 - j0, ti:ti + i1 - i0] = source[sj:sj + j1 - j0, si:si + i1 - i0]


def iterate_store_layers(plan: StorePlan, *, config: TerrainConfig, device: str = "cpu", progress=None) -> Iterator[TerrainLayers]:
    """The layers of each tile column that meets the grid, in sweep order (see the module docstring)."""
    store = plan.store
    mapper = store.template
    # sweep along the longer side: the columns held are three lines across the shorter one
    xs = {c[0] for c in plan.columns}
    ys = {c[1] for c in plan.columns}
    major = 0 if len(xs) >= len(ys) else 1
    order = sorted((c for c in plan.columns if _column_grid(plan, c) is not None), key=lambda c: (c[major], c[1 - major]))
    own: dict[tuple[int, int], tuple[LayerGrid, dict]] = {}
    halo = halo_cells(config)
    z_bounds = plan.bounds

    def own_of(column):
        if column not in own:
            grid = _column_grid(plan, column)
            parts = [tile_voxels(store, name) for name in sorted(plan.columns[column])]
            voxels = VoxelColumns.of_parts(parts, min_evidence=config.layers.min_evidence)
            del parts
            own[column] = (grid, own_bands(voxels, grid, mapper=mapper, config=config, bounds=z_bounds, device=device))
        return own[column]

    for done, column in enumerate(order):
        for key in [k for k in own if k[major] < column[major] - 1]:  # no later column needs them
            del own[key]
        grid, bands = own_of(column)
        padded = LayerGrid(grid.cell_m, grid.offset_m, (grid.first_cell[0] - halo, grid.first_cell[1] - halo),
                           grid.width + 2 * halo, grid.height + 2 * halo)
        heights = {name: np.full((padded.height, padded.width), np.nan) for name in ("elevation", "cover_height")}
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                neighbour = (column[0] + dx, column[1] + dy)
                if halo == 0 and neighbour != column:
                    continue
                if neighbour in plan.columns and _column_grid(plan, neighbour) is not None:
                    neighbour_grid, neighbour_bands = own_of(neighbour)
                    for name, target in heights.items():
                        _paste(neighbour_grid, neighbour_bands[name], padded, target)
        filtered = neighbourhood_filters(heights["elevation"], heights["cover_height"], cell_m=grid.cell_m, config=config, device=device)
        tile_bands = dict(bands)
        for name, values in filtered.items():
            tile_bands[name] = values[halo:halo + grid.height, halo:halo + grid.width]
        finish_layers(tile_bands, config, store.class_names)
        yield TerrainLayers(grid, store.frame, store.class_names, to_north_up(tile_bands, store.class_names), config)
        if progress:
            progress(done + 1, len(order))


def tile_name_of(layers: TerrainLayers, plan: StorePlan) -> str:
    """The tile column a grid of ``iterate_store_layers`` belongs to, as X_Y."""
    n = plan.cells_per_tile
    return f"{math.floor(layers.grid.first_cell[0] / n)}_{math.floor(layers.grid.first_cell[1] / n)}"


def store_layers_in_memory(store: MapStore, *, resolution_m=None, bounds=None, config: TerrainConfig, device: str = "cpu") -> TerrainLayers:
    """The mosaic of a store's layers as one TerrainLayers (memory: the whole grid; ``write_layers``
    streams instead)."""
    plan = plan_store_layers(store, resolution_m=resolution_m, bounds=bounds, config=config)
    grid = plan.grid
    names = band_names(store.class_names)
    bands = {name: np.full((grid.height, grid.width), np.nan, np.float32) for name in names}
    for name in ("observations", "known", "lethal"):
        bands[name][:] = 0
    for tile in iterate_store_layers(plan, config=config, device=device):
        row, column = tile.grid.window_in(grid)
        for name in names:
            bands[name][row:row + tile.grid.height, column:column + tile.grid.width] = tile.bands[name]
    return TerrainLayers(grid, store.frame, store.class_names, bands, config)

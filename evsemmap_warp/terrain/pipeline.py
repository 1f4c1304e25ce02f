"""``evsemmap layers``: a map file or a map store in, the terrain layers' files out (docs/terrain.md).

    OUT/layers.tif            every band, float32, NaN nodata, in the map's world frame (CRS when it has one)
    OUT/layers.npz            every band (a map file's grid; a store writes OUT/tiles/X_Y.npz per tile column)
    OUT/layers.bag            ROS 1: /terrain/grid_map (grid_map_msgs/GridMap, one per grid) and
                              /terrain/costmap (nav_msgs/OccupancyGrid of the whole grid)
    OUT/previews/*.png        one image per band with its color bar or legend
    OUT/layers.json           what was computed: grid, frame, bands and units, cost file, counts, timings

A store is computed and written tile column by tile column (``terrain.stores``): memory holds a few
tiles' voxels and bands, the OccupancyGrid's one byte per cell, and previews of at most
MAX_PREVIEW_PIXELS a side.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..classes import named_colors
from ..core.map_store import MapStore, is_store
from ..core.mapper import Mapper, load_map
from ..files import check_not_inside
from .config import TerrainConfig, load_terrain_config
from .api import compute_layers
from .layers import TerrainLayers, band_names
from .outputs import (BAG_NAME, GEOTIFF_NAME, NPZ_NAME, PREVIEW_DIR, BagWriter, GeoTiffWriter, check_output_folder, occupancy_values,
                      preview_stride, write_npz, write_previews, write_summary)
from .stores import iterate_store_layers, plan_store_layers, tile_name_of

SUMMARY_NAME = "layers.json"


def class_colors(class_names) -> np.ndarray:
    """[K, 3] uint8 display colors of the classes (configs/classes), grey for names without one."""
    known = named_colors()
    return np.array([known.get(name.lower(), (128, 128, 128)) for name in class_names], np.uint8)


class _TiffPreviewBands(Mapping):
    """Bands read back from a written GeoTIFF, decimated to preview size, one at a time."""

    def __init__(self, path: Path, names: list[str], stride: int):
        import rasterio

        self.dataset = rasterio.open(path)
        self.names, self.stride = names, stride

    def __getitem__(self, name):
        from rasterio.enums import Resampling

        if name not in self.names:
            raise KeyError(name)
        shape = (max(1, self.dataset.height // self.stride), max(1, self.dataset.width // self.stride))
        return self.dataset.read(self.names.index(name) + 1, out_shape=shape, resampling=Resampling.nearest)

    def __iter__(self):
        return iter(self.names)

    def __len__(self):
        return len(self.names)

    def close(self):
        self.dataset.close()


def _counts(bands) -> dict:
    known = bands["known"] > 0
    return {"cells": int(known.size), "known_cells": int(known.sum()), "lethal_cells": int((bands["lethal"] > 0).sum())}


def write_layers(source, out, *, resolution_m=None, bounds=None, costs=None, device: str = "cpu", previews: bool = True,
                 bag: bool = True, log=None) -> dict:
    """Compute the layers of a map file or store (a path, a Mapper or a MapStore) and write them into
    the folder ``out``; returns the summary also written to ``OUT/layers.json``. ``costs``: a cost
    table YAML (default configs/terrain/costs_v3.yaml) or a TerrainConfig."""
    started = time.perf_counter()
    out = check_output_folder(out)
    config = costs if isinstance(costs, TerrainConfig) else load_terrain_config(costs)
    if isinstance(source, (str, Path)):
        check_not_inside(out, [source], "layers --out")
        source = MapStore(source, cache_tiles=4) if is_store(source) else load_map(source)
    if isinstance(source, MapStore):
        summary = _write_store(source, out, resolution_m=resolution_m, bounds=bounds, config=config, device=device, previews=previews,
                               bag=bag, log=log)
    elif isinstance(source, Mapper):
        summary = _write_map(source, out, resolution_m=resolution_m, bounds=bounds, config=config, device=device, previews=previews, bag=bag)
    else:
        raise ValueError(f"write_layers takes a map file, a store, a Mapper or a MapStore, got {type(source).__name__}")
    summary["seconds"] = round(time.perf_counter() - started, 3)
    write_summary(out / SUMMARY_NAME, summary)
    return summary


def _summary(layers_meta: dict, out: Path, files: list[Path], **extra) -> dict:
    return {"out": str(out), "files": sorted(str(p.relative_to(out)) for p in files), **layers_meta, **extra}


def _write_map(mapper: Mapper, out: Path, *, resolution_m, bounds, config, device, previews, bag) -> dict:
    started = time.perf_counter()
    layers = compute_layers(mapper, resolution_m=resolution_m, bounds=bounds, config=config, device=device)
    seconds = time.perf_counter() - started
    out.mkdir(parents=True, exist_ok=True)
    files = []
    tiff = GeoTiffWriter(out / GEOTIFF_NAME, layers.grid, layers.frame, layers.class_names, costs_file=config.source)
    try:
        tiff.write(layers)
    except BaseException:
        tiff.abort()
        raise
    files.append(tiff.close())
    files.append(write_npz(out / NPZ_NAME, layers))
    if bag:
        writer = BagWriter(out / BAG_NAME, layers.frame)
        try:
            writer.write_grid_map(layers)
            writer.write_occupancy_grid(occupancy_values(layers.bands["traversability_cost"], layers.bands["lethal"]), layers.grid)
        except BaseException:
            writer.abort()
            raise
        files.append(writer.close())
    if previews:
        stride = preview_stride(layers.grid)
        decimated = {name: values[::stride, ::stride] for name, values in layers.bands.items()}
        files += write_previews(out / PREVIEW_DIR, decimated, layers.grid, layers.class_names, class_colors(layers.class_names),
                                frame=layers.frame, stride=stride)
    return _summary(layers.metadata(), out, files, source="map", voxels=mapper.voxel_count, **_counts(layers.bands),
                    layer_seconds=round(seconds, 3), cells_per_second=round(layers.grid.width * layers.grid.height / max(seconds, 1e-9)))


def _write_store(store: MapStore, out: Path, *, resolution_m, bounds, config: TerrainConfig, device, previews, bag, log) -> dict:
    plan = plan_store_layers(store, resolution_m=resolution_m, bounds=bounds, config=config)
    grid = plan.grid
    out.mkdir(parents=True, exist_ok=True)
    files = []
    tiff = GeoTiffWriter(out / GEOTIFF_NAME, grid, store.frame, store.class_names, costs_file=config.source)
    writer = BagWriter(out / BAG_NAME, store.frame) if bag else None
    occupancy = np.full((grid.height, grid.width), -1, np.int8) if bag else None
    counts = {"cells": grid.width * grid.height, "known_cells": 0, "lethal_cells": 0}
    tiles = []
    started = time.perf_counter()
    try:
        def progress(done, total):
            if log and (done == total or done % max(1, total // 10) == 0):
                log(f"layers: {done}/{total} tile columns")

        def write(layers):
            tiff.write(layers)
            name = tile_name_of(layers, plan)
            files.append(write_npz(out / "tiles" / f"{name}.npz", layers))
            tiles.append(name)
            counts["known_cells"] += int((layers.bands["known"] > 0).sum())
            counts["lethal_cells"] += int((layers.bands["lethal"] > 0).sum())
            if writer is not None:
                writer.write_grid_map(layers)
                row, column = layers.grid.window_in(grid)
                occupancy[row:row + layers.grid.height, column:column + layers.grid.width] = occupancy_values(
                    layers.bands["traversability_cost"], layers.bands["lethal"])

        # A column's files are compressed and written on a second thread (zlib and GDAL release the GIL) while the
        # next column is computed; one column in flight, in order, so memory holds two columns' layers at most.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="evsemmap-layers-write") as pool:
            pending = None
            for layers in iterate_store_layers(plan, config=config, device=device, progress=progress):
                if pending is not None:
                    pending.result()
                pending = pool.submit(write, layers)
            if pending is not None:
                pending.result()
        seconds = time.perf_counter() - started
        files.append(tiff.close())
        if writer is not None:
            writer.write_occupancy_grid(occupancy, grid)
            files.append(writer.close())
    except BaseException:
        tiff.abort()
        if writer is not None:
            writer.abort()
        raise
    if previews:
        stride = preview_stride(grid)
        bands = _TiffPreviewBands(out / GEOTIFF_NAME, band_names(store.class_names), stride)
        try:
            files += write_previews(out / PREVIEW_DIR, bands, grid, store.class_names, class_colors(store.class_names), frame=store.frame,
                                    stride=stride)
        finally:
            bands.close()
    meta = TerrainLayers(grid, store.frame, store.class_names, {}, config).metadata()
    voxels = sum(store.tiles[n]["voxels"] for names in plan.columns.values() for n in names)
    return _summary(meta, out, files, source="store", tiles_read=store.tiles_loaded, tile_columns=sorted(tiles), voxels=voxels,
                    **counts, layer_seconds=round(seconds, 3), cells_per_second=round(counts["cells"] / max(seconds, 1e-9)))

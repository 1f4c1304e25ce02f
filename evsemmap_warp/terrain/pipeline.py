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

import collections
import time
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
from .outputs import (BAG_NAME, GEOTIFF_NAME, NPZ_NAME, PREVIEW_DIR, UNREACHED_ZERO_BANDS, BagWriter, GeoTiffWriter, staged_output_folder,
                      occupancy_values, preview_stride, write_npz, write_previews, write_summary)
from .stores import iterate_store_layers, plan_store_layers, tile_name_of

SUMMARY_NAME = "layers.json"
WRITES_IN_FLIGHT = 3  # tile columns computed but not yet written (each a few MB of bands)


def class_colors(class_names) -> np.ndarray:
    """[K, 3] uint8 display colors of the classes (configs/classes), grey for names without one."""
    known = named_colors()
    return np.array([known.get(name.lower(), (128, 128, 128)) for name in class_names], np.uint8)


class _PreviewMosaic:
    """Every band of a store's layers at preview size (one cell in ``stride`` along each axis, as a map file's
    previews are decimated), filled tile column by tile column as they are computed, so that the previews are
    drawn from memory, on a second thread while the GeoTIFF and the bag are finished, instead of reading the
    GeoTIFF back (docs/terrain.md §8 says what that cost). At most MAX_PREVIEW_PIXELS a side: 10 MB a band
    (float32) for the squarest store."""

    def __init__(self, grid, names: list[str], stride: int):
        shape = (-(-grid.height // stride), -(-grid.width // stride))
        self.grid, self.stride = grid, stride
        self.bands = {name: np.full(shape, 0.0 if name in UNREACHED_ZERO_BANDS else np.nan, np.float32) for name in names}

    def add(self, layers: TerrainLayers) -> None:
        """The cells of ``layers`` (a part of the mosaic's grid) that fall on the preview's lattice."""
        row, column = layers.grid.window_in(self.grid)
        s = self.stride
        first_row, first_column = -row % s, -column % s  # the part's first cells on the lattice
        at_row, at_column = (row + first_row) // s, (column + first_column) // s
        for name, band in self.bands.items():
            part = layers.bands[name][first_row::s, first_column::s]
            band[at_row:at_row + part.shape[0], at_column:at_column + part.shape[1]] = part


def _counts(bands) -> dict:
    known = bands["known"] > 0
    return {"cells": int(known.size), "known_cells": int(known.sum()), "lethal_cells": int((bands["lethal"] > 0).sum())}


def write_layers(source, out, *, resolution_m=None, bounds=None, costs=None, device: str = "cpu", previews: bool = True,
                 bag: bool = True, log=None) -> dict:
    """Compute the layers of a map file or store (a path, a Mapper or a MapStore) and write them into
    the folder ``out``; returns the summary also written to ``OUT/layers.json``. ``costs``: a cost
    table YAML (default configs/terrain/costs_v3.yaml) or a TerrainConfig. The folder is replaced
    whole when all is written (``outputs.staged_output_folder``): nothing of an earlier run stays."""
    started = time.perf_counter()
    out = Path(out)
    config = costs if isinstance(costs, TerrainConfig) else load_terrain_config(costs)
    if isinstance(source, (str, Path)):
        check_not_inside(out, [source], "layers --out")
        if out.resolve() in Path(source).resolve().parents:  # replacing the folder would delete the map inside it
            raise ValueError(f"layers --out {out}: holds the map {source}, and the layers replace the folder whole; give another --out")
        # a folder is a store, or one not written yet (MapStore names why it is not one)
        source = MapStore(source, cache_tiles=4) if is_store(source) or Path(source).is_dir() else load_map(source)
    if not isinstance(source, (MapStore, Mapper)):
        raise ValueError(f"write_layers takes a map file, a store, a Mapper or a MapStore, got {type(source).__name__}")
    with staged_output_folder(out, SUMMARY_NAME) as staging:
        if isinstance(source, MapStore):
            summary = _write_store(source, staging, resolution_m=resolution_m, bounds=bounds, config=config, device=device,
                                   previews=previews, bag=bag, log=log)
        else:
            summary = _write_map(source, staging, resolution_m=resolution_m, bounds=bounds, config=config, device=device,
                                 previews=previews, bag=bag)
        summary["out"] = str(out)
        summary["seconds"] = round(time.perf_counter() - started, 3)
        write_summary(staging / SUMMARY_NAME, summary)
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
    mosaic = _PreviewMosaic(grid, band_names(store.class_names), preview_stride(grid)) if previews else None
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
            if mosaic is not None:
                mosaic.add(layers)
            if writer is not None:
                writer.write_grid_map(layers)
                row, column = layers.grid.window_in(grid)
                occupancy[row:row + layers.grid.height, column:column + layers.grid.width] = occupancy_values(
                    layers.bands["traversability_cost"], layers.bands["lethal"])

        # A column's files are compressed and written on a second thread (zlib and GDAL release the GIL) while the
        # next columns are computed, in order, at most WRITES_IN_FLIGHT columns queued: computing and writing a
        # column take about as long, but not column by column, so with one in flight each side waits for the other.
        # After the last one, that thread draws the previews while this one finishes the GeoTIFF and the bag.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="evsemmap-layers-write") as pool:
            pending = collections.deque()
            for layers in iterate_store_layers(plan, config=config, device=device, progress=progress):
                while len(pending) >= WRITES_IN_FLIGHT:
                    pending.popleft().result()
                pending.append(pool.submit(write, layers))
            while pending:
                pending.popleft().result()
            seconds = time.perf_counter() - started
            drawn = None if mosaic is None else pool.submit(write_previews, out / PREVIEW_DIR, mosaic.bands, grid, store.class_names,
                                                               class_colors(store.class_names), frame=store.frame, stride=mosaic.stride)
            files.append(tiff.close())
            if writer is not None:
                writer.write_occupancy_grid(occupancy, grid)
                files.append(writer.close())
            if drawn is not None:
                files += drawn.result()
    except BaseException:
        tiff.abort()
        if writer is not None:
            writer.abort()
        raise
    meta = TerrainLayers(grid, store.frame, store.class_names, {}, config).metadata()
    voxels = sum(store.tiles[n]["voxels"] for names in plan.columns.values() for n in names)
    return _summary(meta, out, files, source="store", tiles_read=store.tiles_loaded, tile_columns=sorted(tiles), voxels=voxels,
                    **counts, layer_seconds=round(seconds, 3), cells_per_second=round(counts["cells"] / max(seconds, 1e-9)))

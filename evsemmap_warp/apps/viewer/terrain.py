"""Terrain layers in the viewer: a map's (or a store's) ``terrain.compute_layers`` drawn as a colored height
surface (``TerrainSurface``), picked cell by cell; ``TerrainView`` is the part of ``MapViewer`` that
computes, draws and picks them."""

from __future__ import annotations

import math
import time

import numpy as np

from .colors import NO_DATA, color_bar_image, colormap, swatch_image
from .lighting import mesh_colors

TERRAIN_MODES = ("surface under the voxels", "surface instead of the voxels")
BINARY_BANDS = {"known": ((200, 200, 200), (40, 40, 40)), "lethal": ((230, 230, 230), (200, 0, 0))}


def terrain_band_order(names: list[str]) -> list[str]:
    """Bands as the layer selector offers them: the cost first, then the rest in output order."""
    first = [n for n in ("traversability_cost", "elevation", "slope", "surface_class", "semantic_variance") if n in names]
    return first + [n for n in names if n not in first]


class TerrainSurface:
    """A grid of terrain layers (``terrain.TerrainLayers``) drawn as a height surface: one flat tile per
    cell with a height (the ``elevation`` layer: the top of the supporting surface; ``cover_height``
    where a cell has no supporting class), colored by the selected layer. More than ``max_cells``
    cells are drawn every ``stride``-th row and column with tiles ``stride`` cells wide (picking still
    reads every cell)."""

    def __init__(self, layers, *, voxel_m: float, max_cells: int = 250_000):
        self.layers = layers
        self.grid = layers.grid
        self.voxel_m = float(voxel_m)
        bands = layers.bands
        height = np.where(np.isfinite(bands["elevation"]), bands["elevation"], bands["cover_height"]).astype(np.float64)
        self.height = height  # [rows, columns], north-up, NaN where nothing is drawn
        rows, cols = np.nonzero(np.isfinite(height))
        self.stride = max(1, int(math.ceil(math.sqrt(len(rows) / max(int(max_cells), 1))))) if len(rows) else 1
        if self.stride > 1:
            keep = (rows % self.stride == 0) & (cols % self.stride == 0)
            rows, cols = rows[keep], cols[keep]
        self.rows, self.cols = rows, cols
        xs, ys = self.grid.cell_centers()
        # a tile of stride cells covers its cell and the next ones east and south: center it on them
        half = (self.stride - 1) * 0.5 * self.grid.cell_m
        self.centers = np.c_[xs[cols] + half, ys[rows] - half, height[rows, cols]]  # world coordinates, m

    @property
    def band_names(self) -> list[str]:
        """The layers' bands in the order the selector lists them."""
        return terrain_band_order(list(self.layers.bands))

    def class_band(self, band: str) -> bool:
        """Whether ``band`` holds class indices (drawn with the class palette) rather than values."""
        from ...terrain.layers import CLASS_BANDS

        return band in CLASS_BANDS

    def values(self, band: str) -> np.ndarray:
        """``band``'s value at each drawn cell (float64, NaN where unknown)."""
        return np.asarray(self.layers.bands[band], np.float64)[self.rows, self.cols]

    def value_range(self, band: str) -> tuple[float, float]:
        """The (low, high) of ``band``'s finite values that its color bar spans."""
        finite = self.values(band)
        finite = finite[np.isfinite(finite)]
        return (float(finite.min()), float(finite.max())) if len(finite) else (0.0, 1.0)

    def colors(self, band: str, palette: np.ndarray) -> np.ndarray:
        """[tiles, 3] uint8 sRGB colors of the drawn tiles by ``band`` (``palette``: [K, 3] class colors)."""
        values = self.values(band)
        if self.class_band(band):
            out = np.tile(NO_DATA, (len(values), 1))
            ok = np.isfinite(values)
            out[ok] = palette[values[ok].astype(np.int64)]
            return out
        if band in BINARY_BANDS:
            off, on = (np.array(c, np.uint8) for c in BINARY_BANDS[band])
            return np.where((values > 0)[:, None], on, off).astype(np.uint8)
        lo, hi = self.value_range(band)
        return colormap(values, lo, hi)

    def legend(self, band: str, classes: list[str], palette: np.ndarray) -> np.ndarray:
        """An RGB image of ``band``'s color bar (values with their unit) or class legend, for the side panel."""
        from ...terrain.layers import band_units

        if self.class_band(band):
            present = np.unique(self.values(band)[np.isfinite(self.values(band))]).astype(int)
            return swatch_image([(classes[k], tuple(palette[k])) for k in present] or [("no cells", tuple(NO_DATA))])
        if band in BINARY_BANDS:
            off, on = BINARY_BANDS[band]
            return swatch_image([(f"{band}: no", off), (f"{band}: yes", on)])
        lo, hi = self.value_range(band)
        return color_bar_image(lo, hi, f"terrain {band} ({band_units(band)})")

    def tile_tops(self, mode: str) -> np.ndarray:
        """z of the drawn tiles' tops: the layer's height, or half a voxel lower (the support voxel's
        bottom face) when the voxels are drawn on it."""
        return self.centers[:, 2] - (0.5 * self.voxel_m if mode == TERRAIN_MODES[0] else 0.0)

    # ------------------------------------------------------------------ picking
    def cell_at(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) of the cell under each point, -1 outside the grid."""
        g = self.grid
        p = np.asarray(points_world, np.float64).reshape(-1, 3)
        col = np.floor((p[:, 0] - g.x0_m) / g.cell_m).astype(np.int64)
        row = np.floor((g.y1_m - p[:, 1]) / g.cell_m).astype(np.int64)
        inside = (col >= 0) & (col < g.width) & (row >= 0) & (row < g.height)
        return np.where(inside, row, -1), np.where(inside, col, -1)

    def pick(self, origin_world: np.ndarray, direction: np.ndarray, mode: str) -> tuple[float, int, int] | None:
        """(distance along the ray, row, column) of the first drawn cell whose top the ray passes
        below (the ray enters the surface there), None if it meets none."""
        if len(self.rows) == 0:
            return None
        o = np.asarray(origin_world, np.float64)
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        g = self.grid
        drop = 0.5 * self.voxel_m if mode == TERRAIN_MODES[0] else 0.0
        top = self.height - drop
        lo = np.array([g.x0_m, g.y0_m, np.nanmin(top) - 1.0])
        hi = np.array([g.x1_m, g.y1_m, np.nanmax(top)])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        t_near = np.nanmax(np.minimum(t1, t2))
        t_far = np.nanmin(np.maximum(t1, t2))
        if not t_far >= max(t_near, 0.0):
            return None
        ts = np.arange(max(t_near, 0.0), t_far + g.cell_m, g.cell_m / 4.0)[:400_000]
        points = o + ts[:, None] * d
        row, col = self.cell_at(points)
        inside = row >= 0
        z_top = np.full(len(ts), np.nan)
        z_top[inside] = top[row[inside], col[inside]]
        with np.errstate(invalid="ignore"):
            below = np.isfinite(z_top) & (points[:, 2] <= z_top)
        hits = np.flatnonzero(below)
        if len(hits) == 0:
            return None
        k = int(hits[0])
        return float(ts[k]), int(row[k]), int(col[k])

    def describe(self, row: int, col: int, classes: list[str], frame_text: str) -> str:
        """Markdown: a cell's center in world coordinates and every layer's value there."""
        from ...terrain.layers import band_units

        xs, ys = self.grid.cell_centers()
        bands = self.layers.bands
        lines = [f"**terrain cell** (column {col}, row {row}) of {self.grid.cell_m:g} m",
                 f"center in {frame_text}: x={xs[col]:.3f}, y={ys[row]:.3f} m", "", "| layer | value | unit |", "|---|---|---|"]
        probabilities = []
        for name, values in bands.items():
            value = float(values[row, col])
            if name.startswith("probability_"):
                probabilities.append((value, name[len("probability_"):]))
                continue
            if self.class_band(name) and np.isfinite(value):
                shown = f"{classes[int(value)]} ({int(value)})"
            else:
                shown = "unknown" if not np.isfinite(value) else f"{value:.4g}"
            lines.append(f"| {name} | {shown} | {band_units(name)} |")
        probabilities = sorted((p for p in probabilities if np.isfinite(p[0])), reverse=True)[:3]
        if probabilities:
            lines.append("| most probable surface classes | " + ", ".join(f"{n} {p:.2f}" for p, n in probabilities) + " | 1 |")
        return "\n".join(lines)


def compute_terrain(path, *, resolution_m=None, costs=None, bounds=None):
    """Terrain layers (``terrain.compute_layers``) of a map file or a store at ``path``; for a store, the
    mosaic of its tiles' layers. ``costs``: a cost table YAML (default configs/terrain/costs_v3.yaml)."""
    from ...core.map_store import MapStore, is_store
    from ...core.mapper import load_map
    from ...terrain import compute_layers, load_terrain_config

    source = MapStore(path, cache_tiles=4) if is_store(path) else load_map(path)
    voxel_m = source.config.resolution_m
    return compute_layers(source, resolution_m=resolution_m, bounds=bounds, config=load_terrain_config(costs)), voxel_m


class TerrainView:
    """The part of a ``MapViewer`` that shows terrain layers: ``compute`` makes each map's ``surfaces``
    (``resolution_m`` cells, the cost table ``costs``), ``draw`` puts the shown maps' surfaces in the scene
    (``handles``), colored by the *Layer* band; ``hits`` finds where a ray meets them."""

    def __init__(self, viewer, *, resolution_m=None, costs=None):
        self.viewer = viewer
        self.resolution_m, self.costs = resolution_m, costs
        self.surfaces: dict[int, TerrainSurface] = {}
        self.handles: dict[int, object] = {}
        self._drawn: dict[int, tuple] = {}  # what each surface was last drawn as (band, mode, shift, surface)

    def shown(self) -> bool:
        """Whether a surface is computed and *Show surface* is ticked."""
        return bool(self.surfaces) and self.viewer.gui_terrain_show.value

    def voxels_hidden(self) -> bool:
        """The surface is drawn instead of the voxels."""
        return self.shown() and self.viewer.gui_terrain_mode.value == TERRAIN_MODES[1]

    def compute(self) -> None:
        """Compute the terrain layers of every map (a store's: the mosaic of its tiles) and show them."""
        viewer = self.viewer
        started = time.perf_counter()
        viewer.gui_terrain_status.content = "computing terrain layers ..."
        try:
            for i, layer in enumerate(viewer.layers):
                layers, voxel_m = compute_terrain(layer.path, resolution_m=self.resolution_m, costs=self.costs)
                self.surfaces[i] = TerrainSurface(layers, voxel_m=voxel_m, max_cells=viewer.max_voxels)
        except (ValueError, OSError) as exc:  # ConfigError included: a cost table that does not fit the map's classes
            viewer.gui_terrain_status.content = f"**Cannot compute terrain layers:** {exc}"
            raise
        bands = self.surfaces[0].band_names
        viewer.gui_terrain_band.options = tuple(bands)
        if viewer.gui_terrain_band.value not in bands:
            viewer.gui_terrain_band.value = bands[0]
        viewer.gui_terrain_compute.visible = False
        viewer.gui_terrain_mode.visible = True
        first = self.surfaces[0]
        viewer.gui_terrain_status.content = (
            f"{len(self.surfaces)} map(s): cells of {first.grid.cell_m:g} m, {time.perf_counter() - started:.1f} s; click the surface for "
            "a cell's values" + ("" if first.stride == 1 else f" (drawn every {first.stride} cells)"))
        viewer.refresh()

    def compute_from_gui(self) -> None:
        """The *Compute terrain layers* button: a failure is shown in the folder's status line, not raised."""
        try:
            self.compute()
        except (ValueError, OSError):
            pass

    def draw(self, shown: list[int]) -> None:
        """Show the surfaces of the maps ``shown`` (drawn again only where the band, mode or place changed)."""
        viewer = self.viewer
        band, mode = viewer.gui_terrain_band.value, viewer.gui_terrain_mode.value
        for i, surface in self.surfaces.items():
            if not (viewer.gui_terrain_show.value and i in shown and len(surface.rows) > 0):
                if i in self.handles:
                    self.handles[i].visible = False
                continue
            key = (band, mode, float(viewer.comparison.shift(i)[0]), id(surface))
            if self._drawn.get(i) == key and i in self.handles:
                self.handles[i].visible = True  # drawn as asked already: only shown again
                continue
            self._drawn[i] = key
            self.handles[i] = self._add_surface(i, surface, band, mode)
        if self.surfaces:
            first = next((i for i in shown if i in self.surfaces), next(iter(self.surfaces)))
            viewer.gui_terrain_legend.image = self.surfaces[first].legend(band, viewer.layers[first].classes, self._palette(first))

    def _palette(self, i: int) -> np.ndarray:
        return np.array([self.viewer.palette[name] for name in self.viewer.layers[i].classes], np.uint8)

    def _add_surface(self, i: int, surface: TerrainSurface, band: str, mode: str):
        import trimesh

        viewer = self.viewer
        tile = surface.grid.cell_m * surface.stride
        thickness = 0.25 * surface.voxel_m
        positions = np.c_[surface.centers[:, :2], surface.tile_tops(mode) - thickness / 2] - viewer.origin + viewer.comparison.shift(i)
        box = trimesh.creation.box(extents=[tile * 0.98, tile * 0.98, thickness])
        return viewer.server.scene.add_batched_meshes_simple(
            f"/terrain/{i}", box.vertices.astype(np.float32), box.faces.astype(np.uint32),
            batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(positions), 1)),
            batched_positions=positions.astype(np.float32), batched_colors=mesh_colors(surface.colors(band, self._palette(i))),
            cast_shadow=False, receive_shadow=False)

    def hits(self, ray_origin, direction: np.ndarray, shown: list[int]) -> list[tuple[float, dict]]:
        """(distance, hit) where a ray (display coordinates, unit ``direction``) meets a shown surface: a hit
        has ``kind`` "cell", ``layer``, ``row``, ``column`` and ``point`` (world coordinates, m)."""
        if not self.viewer.gui_terrain_show.value:
            return []
        found = []
        for i, surface in self.surfaces.items():
            if i not in shown:
                continue
            world = np.asarray(ray_origin, np.float64) + self.viewer.origin - self.viewer.comparison.shift(i)
            cell = surface.pick(world, direction, self.viewer.gui_terrain_mode.value)
            if cell is not None:
                t, row, column = cell
                found.append((t, {"kind": "cell", "layer": i, "row": row, "column": column, "point": world + t * direction}))
        return found

"""What ``viewer.MapViewer`` draws and computes beside the voxels: the color compensation of lit meshes,
a terrain layer as a colored height surface, the difference of two maps (against a ground truth when
one is given), and the orientation aids (ground grid, scale bar, measured distances).

Everything here is numpy on arrays the viewer already holds; the viewer owns the viser handles.

Lit meshes. viser draws meshes (``--style boxes``, the terrain surface) with three.js's
MeshStandardMaterial under the client's ACES filmic tone mapping, and point clouds unlit and not
tone mapped. A mesh's color c (0..1, taken as linear reflectance) lit by an ambient light A and a
directional light D at angle t to the face's normal leaves the face with radiance c (A + D cos t) / pi,
which is tone mapped, ACES(x) = OUT . rrt(IN . x / 0.6), and sRGB-encoded. Under viser's default
lights (an environment map and two directional lights) the same colors come out pale: the boxes looked
washed out beside the points. ``configure_lighting`` sets one ambient and one directional light, and
``mesh_colors`` inverts the chain for faces that look up, so that their tops show the palette's color
(as closely as ACES can render it) while the sides, lit less, shade the boxes.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------------------------------------- lit meshes
AMBIENT_INTENSITY = 5.0
SUN_INTENSITY = 9.0
SUN_POSITION = (3.0, -4.0, 10.0)  # the directional light shines from here towards the scene origin
TOP_GAIN = (AMBIENT_INTENSITY + SUN_INTENSITY * SUN_POSITION[2] / math.hypot(*SUN_POSITION)) / math.pi
# three.js ACESFilmicToneMapping (column-major mat3 in GLSL, written here as row-major matrices acting on x)
_ACES_IN = np.array([[0.59719, 0.35458, 0.04823], [0.07600, 0.90834, 0.01566], [0.02840, 0.13383, 0.83777]])
_ACES_OUT = np.array([[1.60475, -0.53108, -0.07367], [-0.10208, 1.10813, -0.00605], [-0.00327, -0.07276, 1.07602]])
_RRT = (0.0245786, 0.000090537, 0.983729, 0.4329510, 0.238081)


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB values 0..255 as linear light 0..1 (the standard sRGB transfer curve)."""
    s = np.asarray(rgb, np.float64) / 255.0
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear light 0..1 as sRGB values 0..255 (the inverse of srgb_to_linear)."""
    v = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return 255.0 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def aces(radiance: np.ndarray) -> np.ndarray:
    """three.js's ACES filmic tone map of linear radiance [..., 3] (output linear, 0..1)."""
    a, b, c, d, e = _RRT
    v = (np.asarray(radiance, np.float64) / 0.6) @ _ACES_IN.T
    v = (v * (v + a) - b) / (v * (c * v + d) + e)
    return np.clip(v @ _ACES_OUT.T, 0.0, 1.0)


def aces_inverse(linear: np.ndarray) -> np.ndarray:
    """The radiance whose tone map is ``linear`` (clipped to >= 0 where ACES cannot reach the color)."""
    a, b, c, d, e = _RRT
    z = np.clip(np.asarray(linear, np.float64) @ np.linalg.inv(_ACES_OUT).T, 0.0, 0.999 / c)
    # rrt(v) = z  <=>  v^2 (1 - c z) + v (a - d z) - (b + e z) = 0, the root >= 0
    qa, qb, qc = 1.0 - c * z, a - d * z, -(b + e * z)
    v = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    return np.maximum(0.6 * (v @ np.linalg.inv(_ACES_IN).T), 0.0)


_MESH_COLOR_CACHE: dict[int, tuple[int, int, int]] = {}
_MESH_COLOR_LOCK = threading.Lock()  # GUI callbacks run on viser's threads


def _solve_mesh_colors(table: np.ndarray) -> np.ndarray:
    """[n, 3] sent colors (float 0..255) whose top faces render nearest to the sRGB colors ``table``."""
    target = table.astype(np.float64)
    levels = np.arange(256, dtype=np.float64)

    def error(candidates):  # [colors, n, 3] sent -> [colors, n] max channel error, ties broken by the squared error
        shown = linear_to_srgb(aces(candidates / 255.0 * TOP_GAIN))
        diff = np.abs(shown - target[:, None, :])
        return diff.max(axis=-1) + 1e-3 * (diff ** 2).sum(axis=-1)

    # the exact inverse where ACES reaches the color, or the best of a coarse grid; then, per channel in
    # turn, the value whose rendering is nearest (this also settles the colors ACES cannot reach exactly)
    exact = np.round(np.clip(aces_inverse(srgb_to_linear(table)) / TOP_GAIN, 0.0, 1.0) * 255.0)
    coarse = np.array([0, 2, 5, 10, 18, 30, 48, 75, 110, 160, 210, 255], np.float64)
    grid = np.stack(np.meshgrid(coarse, coarse, coarse, indexing="ij"), axis=-1).reshape(1, -1, 3)
    starts = np.concatenate([exact[:, None, :], np.repeat(grid, len(table), axis=0)], axis=1)
    sent = starts[np.arange(len(table)), np.argmin(error(starts), axis=1)]
    for _ in range(3):
        for channel in range(3):
            candidates = np.repeat(sent[:, None, :], 256, axis=1)
            candidates[:, :, channel] = levels
            sent[:, channel] = levels[np.argmin(error(candidates), axis=1)]
    return sent


def mesh_colors(rgb: np.ndarray) -> np.ndarray:
    """[N, 3] uint8 instance colors that a mesh face looking up renders as ``rgb`` (sRGB) under
    ``configure_lighting`` (``rendered_top_color`` gives what it renders as). Solved once per distinct
    color (cached), 256 colors at a time."""
    rgb = np.asarray(rgb, np.uint8)
    flat = rgb.reshape(-1, 3)
    keys = (flat[:, 0].astype(np.int64) << 16) | (flat[:, 1].astype(np.int64) << 8) | flat[:, 2].astype(np.int64)
    unique, inverse = np.unique(keys, return_inverse=True)
    with _MESH_COLOR_LOCK:
        if len(_MESH_COLOR_CACHE) + len(unique) > 200_000:  # a bound on memory: color ramps of many values
            _MESH_COLOR_CACHE.clear()
        missing = np.array([k for k in unique.tolist() if k not in _MESH_COLOR_CACHE], np.int64)
        for start in range(0, len(missing), 256):
            chunk = missing[start:start + 256]
            table = np.stack([(chunk >> 16) & 255, (chunk >> 8) & 255, chunk & 255], axis=1).astype(np.uint8)
            for key, sent in zip(chunk.tolist(), _solve_mesh_colors(table).astype(np.uint8).tolist()):
                _MESH_COLOR_CACHE[key] = tuple(sent)
        solved = np.array([_MESH_COLOR_CACHE[k] for k in unique.tolist()], np.uint8).reshape(-1, 3)
    return solved[inverse.reshape(-1)].reshape(rgb.shape)


def rendered_top_color(sent: np.ndarray) -> np.ndarray:
    """What the browser shows for a face looking up with instance color ``sent`` (the forward model)."""
    return np.round(linear_to_srgb(aces(np.asarray(sent, np.float64) / 255.0 * TOP_GAIN))).astype(np.uint8)


def configure_lighting(scene) -> None:
    """One ambient and one directional light instead of viser's environment map and default lights."""
    scene.configure_environment_map(None)
    scene.configure_default_lights(enabled=False)
    scene.add_light_ambient("/lights/ambient", intensity=AMBIENT_INTENSITY)
    scene.add_light_directional("/lights/sun", intensity=SUN_INTENSITY, position=SUN_POSITION)


# ---------------------------------------------------------------------------------------------- colors
_VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
                     (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float64)
# blue (the first map surer) - white - red (the second surer), ColorBrewer RdBu
_DIVERGING = np.array([(33, 102, 172), (103, 169, 207), (209, 229, 240), (247, 247, 247), (253, 219, 199),
                       (239, 138, 98), (178, 24, 43)], np.float64)
NO_DATA = np.array([128, 128, 128], np.uint8)


def ramp(values: np.ndarray, lo: float, hi: float, stops: np.ndarray = _VIRIDIS) -> np.ndarray:
    """Colors of ``values`` on a color ramp over [lo, hi]; NaN grey."""
    values = np.asarray(values, np.float64)
    finite = np.isfinite(values)
    t = np.clip((np.where(finite, values, lo) - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    at = np.linspace(0, 1, len(stops))
    out = np.stack([np.interp(t, at, stops[:, c]) for c in range(3)], axis=-1).astype(np.uint8)
    out[~finite] = NO_DATA
    return out


def diverging(values: np.ndarray, limit: float) -> np.ndarray:
    """Colors of signed ``values`` on a blue-white-red ramp over [-limit, limit]."""
    return ramp(values, -limit, limit, _DIVERGING)


def color_bar_image(lo: float, hi: float, label: str, stops: np.ndarray = _VIRIDIS, width: int = 220) -> np.ndarray:
    """A 46-pixel-high color bar with its ends' values and a label (a legend image)."""
    from PIL import Image, ImageDraw

    bar = ramp(np.linspace(lo, hi, 200), lo, hi, stops)
    img = Image.new("RGB", (width, 46), (255, 255, 255))
    img.paste(Image.fromarray(np.repeat(bar[None], 16, axis=0)), (10, 4))
    draw = ImageDraw.Draw(img)
    draw.text((10, 24), f"{lo:.3g}", fill=(0, 0, 0))
    text = f"{hi:.3g}"
    draw.text((210 - 6 * len(text), 24), text, fill=(0, 0, 0))
    draw.text((10, 34), label, fill=(0, 0, 0))
    return np.asarray(img)


def swatch_image(entries: list[tuple[str, tuple]], width: int = 220) -> np.ndarray:
    """A legend of colored squares and names."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (width, 18 * len(entries) + 4), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, (name, color) in enumerate(entries):
        draw.rectangle([4, 4 + 18 * k, 18, 18 + 18 * k], fill=tuple(int(c) for c in color), outline=(90, 90, 90))
        draw.text((26, 5 + 18 * k), name, fill=(0, 0, 0))
    return np.asarray(img)


# ---------------------------------------------------------------------------------------------- terrain
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
        from ..terrain.layers import CLASS_BANDS

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
        return ramp(values, lo, hi)

    def legend(self, band: str, classes: list[str], palette: np.ndarray) -> np.ndarray:
        """An RGB image of ``band``'s color bar (values with their unit) or class legend, for the side panel."""
        from ..terrain.layers import band_units

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
        from ..terrain.layers import band_units

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
    from ..core.map_store import MapStore, is_store
    from ..core.mapper import load_map
    from ..terrain import compute_layers, load_terrain_config

    source = MapStore(path, cache_tiles=4) if is_store(path) else load_map(path)
    voxel_m = source.config.resolution_m
    return compute_layers(source, resolution_m=resolution_m, bounds=bounds, config=load_terrain_config(costs)), voxel_m


# ---------------------------------------------------------------------------------------------- diff
DIFF_MODES = ("off", "labels differ", "variance difference")
DIFF_COLORS = {
    "first map agrees with the truth": (0, 158, 115),
    "second map agrees with the truth": (0, 114, 178),
    "neither agrees with the truth": (213, 94, 0),
    "labels differ (no truth here)": (204, 121, 167),
}


@dataclass
class MapDiff:
    """Voxels of map ``a`` with a voxel of map ``b`` at the same place (same lattice): rows of each,
    whether their labels differ, the truth's label there (-1: none) and the variance difference."""

    a_name: str
    b_name: str
    a_rows: np.ndarray
    b_rows: np.ndarray
    differ: np.ndarray
    a_label: np.ndarray
    b_label: np.ndarray
    truth: np.ndarray
    variance_difference: np.ndarray  # variance in a - variance in b
    only_a: int
    only_b: int
    classes: list[str] = field(default_factory=list)

    def category(self) -> np.ndarray:
        """Per compared voxel: 0 a agrees with the truth, 1 b agrees, 2 neither, 3 no truth; -1 same label."""
        out = np.full(len(self.a_rows), -1, np.int64)
        known = self.truth >= 0
        out[self.differ & ~known] = 3
        out[self.differ & known & (self.a_label == self.truth)] = 0
        out[self.differ & known & (self.b_label == self.truth)] = 1
        out[self.differ & known & (self.a_label != self.truth) & (self.b_label != self.truth)] = 2
        return out

    def counts(self, keep: np.ndarray | None = None) -> dict[str, int]:
        """Counts over the compared voxels (``keep``: a mask over them, e.g. the shown ones)."""
        keep = np.ones(len(self.a_rows), bool) if keep is None else keep
        category = self.category()[keep]
        names = list(DIFF_COLORS)
        out = {"compared": int(keep.sum()), "differ": int(self.differ[keep].sum()), "with truth": int((self.truth[keep] >= 0).sum())}
        out.update({name: int((category == k).sum()) for k, name in enumerate(names)})
        known = self.truth[keep] >= 0
        out["first map right"] = int((self.a_label[keep][known] == self.truth[keep][known]).sum())
        out["second map right"] = int((self.b_label[keep][known] == self.truth[keep][known]).sum())
        return out

    def describe(self, keep: np.ndarray | None = None) -> str:
        """Markdown: how many voxels differ, and, with a truth, which map agrees with it where they do."""
        c = self.counts(keep)
        share = 100.0 * c["differ"] / c["compared"] if c["compared"] else 0.0
        lines = [f"first **{self.a_name}**, second **{self.b_name}**",
                 f"{c['compared']:,} voxels shown in both; labels differ in **{c['differ']:,}** ({share:.1f} %)",
                 f"only in the first: {self.only_a:,}; only in the second: {self.only_b:,}"]
        if c["with truth"]:
            lines.append(f"where the truth says ({c['with truth']:,} voxels): first right {c['first map right']:,}, "
                         f"second right {c['second map right']:,}")
            lines.append("of the differing: " + ", ".join(f"{name} **{c[name]:,}**" for name in DIFF_COLORS))
        return "\n\n".join(lines)


def compare_maps(a, b, truth: np.ndarray | None = None) -> MapDiff:
    """Match the voxels of two viewer ``MapLayer``s of one frame and lattice by place; ``truth``: the
    truth's label per voxel of ``a`` in ``a``'s class indices (-1: none), ``load_truth``."""
    if abs(a.resolution - b.resolution) > 1e-9 * a.resolution or abs(a.grid_offset - b.grid_offset) > 1e-9:
        raise ValueError(f"compare: {a.name} has {a.resolution} m voxels (grid offset {a.grid_offset}) and {b.name} "
                         f"{b.resolution} m ({b.grid_offset}): only maps of one voxel lattice are compared voxel by voxel")
    if [c.lower() for c in a.classes] != [c.lower() for c in b.classes]:
        raise ValueError(f"compare: {a.name} and {b.name} have different class lists ({a.classes} and {b.classes})")
    b_of_a = b.voxel_at(a.centers) if len(a.centers) else np.zeros(0, np.int64)
    a_rows = np.flatnonzero(b_of_a >= 0)
    b_rows = b_of_a[a_rows]
    a_label, b_label = a.label[a_rows].astype(np.int64), b.label[b_rows].astype(np.int64)
    truth_rows = np.full(len(a_rows), -1, np.int64) if truth is None else np.asarray(truth, np.int64)[a_rows]
    return MapDiff(a.name, b.name, a_rows, b_rows, a_label != b_label, a_label, b_label, truth_rows,
                   a.variance[a_rows].astype(np.float64) - b.variance[b_rows].astype(np.float64),
                   only_a=int(len(a.centers) - len(a_rows)), only_b=int(len(b.centers) - len(np.unique(b_rows))), classes=list(a.classes))


def load_truth(path, layer, frame=None) -> np.ndarray:
    """The ground truth's label of every voxel of ``layer`` (its class indices, -1 where none):

    - a projection (``evsemmap project``'s ground_truth.npz: ``points`` [N, 3] in the world frame,
      ``labels`` [N] remap-v3 class indices, ``frame``): the most frequent label of the points in a voxel;
    - a map file: its label where it has an OCCUPIED voxel.

    Class names are matched by name; a frame recorded in the file must be ``frame``."""
    from ..core.map_file import is_compact
    from ..core.mapper import read_map_arrays
    from ..frames import WorldFrame, check_same_frame

    path = Path(path)
    names = [c.lower() for c in layer.classes]
    map_file = path.is_file() and is_compact(path)  # a map file of format 3 or later is no npz
    try:
        arrays = {}
        if not map_file:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
    except FileNotFoundError:
        raise ValueError(f"{path}: no such ground-truth file") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz ({exc})") from None
    if "points" in arrays and "labels" in arrays:
        from ..classes import class_set

        recorded = arrays.get("frame")
        if recorded is not None:
            truth_frame = WorldFrame.from_dict(json.loads(str(recorded)), f"{path}: frame")
            check_same_frame("compare with the truth", (str(layer.path), frame), (str(path), truth_frame))
        points = np.asarray(arrays["points"], np.float64).reshape(-1, 3)
        labels = np.asarray(arrays["labels"], np.int64).reshape(-1)
        if len(points) != len(labels):
            raise ValueError(f"{path}: {len(points)} points but {len(labels)} labels")
        source_names = [n.lower() for n in class_set("remap_v3").names]
        table = np.array([names.index(n) if n in names else -1 for n in source_names] + [-1], np.int64)
        labels = table[np.where((labels >= 0) & (labels < len(source_names)), labels, len(source_names))]
        rows = layer.voxel_at(points)
        ok = (rows >= 0) & (labels >= 0)
        k = len(names)
        votes = np.bincount(rows[ok] * k + labels[ok], minlength=len(layer.centers) * k).reshape(len(layer.centers), k)
        return np.where(votes.sum(axis=1) > 0, votes.argmax(axis=1), -1)
    if map_file or "alpha" in arrays or "centers" in arrays:
        data, meta = read_map_arrays(path)
        other = type(layer).from_arrays(path.stem, path, data, meta)  # the viewer's MapLayer, without importing the viewer back
        check_same_frame("compare with the truth", (str(layer.path), frame), (str(path), WorldFrame.from_dict(meta.get("frame"), f"{path}: meta.frame")))
        other_names = [c.lower() for c in other.classes]
        table = np.array([names.index(n) if n in names else -1 for n in other_names], np.int64)
        rows = other.voxel_at(layer.centers)
        found = rows >= 0
        out = np.full(len(layer.centers), -1, np.int64)
        occupied = other.state[rows[found]] == 2
        out[np.flatnonzero(found)[occupied]] = table[other.label[rows[found]][occupied]]
        return out
    raise ValueError(f"{path}: not a ground truth: expected 'points' and 'labels' (evsemmap project's ground_truth.npz) "
                     f"or a map file, found arrays {sorted(arrays)}")


# ---------------------------------------------------------------------------------------------- orientation
def nice_length(at_most: float) -> float:
    """The largest 1, 2 or 5 x 10^k not above ``at_most`` (> 0)."""
    at_most = float(at_most)
    if not at_most > 0 or not math.isfinite(at_most):
        return 1.0
    power = 10.0 ** math.floor(math.log10(at_most))
    for step in (5.0, 2.0, 1.0):
        if step * power <= at_most * (1 + 1e-9):
            return step * power
    return power


def format_metres(value: float, step: float) -> str:
    """A grid line's coordinate, with as many decimals as its spacing needs."""
    decimals = max(0, -int(math.floor(math.log10(step)))) if step < 1 else 0
    return f"{value:,.{decimals}f} m"


@dataclass
class GroundGrid:
    """A grid at ``z`` (world) over the cells of ``section`` metres meeting the maps' x-y extent, its
    lines on multiples of ``section`` in world coordinates, a finer line every ``cell``; ``labels``:
    (text, world position) of the section lines along the south and west edges."""

    x0: float
    y0: float
    x1: float
    y1: float
    z: float
    section: float
    cell: float
    labels: list[tuple[str, np.ndarray]]


def ground_grid(lo: np.ndarray, hi: np.ndarray, ground_z: float, max_labels: int = 12) -> GroundGrid:
    """Grid lines and metre labels on the ground plane ``ground_z`` covering the box ``lo``..``hi`` (m), at a round spacing,
    in an even number of sections along each axis, every line labelled."""
    extent = float(max(hi[0] - lo[0], hi[1] - lo[1], 1.0))
    section = nice_length(extent / 4.0)
    while (hi[0] - lo[0]) / section > max_labels or (hi[1] - lo[1]) / section > max_labels:
        section = nice_length(section * 2.5)
    cell = section / 5.0
    x0, y0 = math.floor(lo[0] / section) * section, math.floor(lo[1] / section) * section
    x1, y1 = math.ceil(hi[0] / section) * section, math.ceil(hi[1] / section) * section
    x1, y1 = max(x1, x0 + section), max(y1, y0 + section)
    # viser draws a grid about its center: an even number of sections keeps its lines on the round coordinates
    x1 += section * (round((x1 - x0) / section) % 2)
    y1 += section * (round((y1 - y0) / section) % 2)
    labels = []
    for x in np.arange(x0, x1 + section / 2, section):
        labels.append((f"x {format_metres(x, section)}", np.array([x, y0 - 0.04 * (y1 - y0), ground_z])))
    for y in np.arange(y0, y1 + section / 2, section):
        labels.append((f"y {format_metres(y, section)}", np.array([x0 - 0.04 * (x1 - x0), y, ground_z])))
    return GroundGrid(x0, y0, x1, y1, ground_z, section, cell, labels)


def metres_per_pixel(camera_position, look_at, fov_rad: float, image_height_px: float) -> float:
    """Metres per screen pixel at the orbit center (the look-at point) of a perspective camera."""
    distance = float(np.linalg.norm(np.asarray(camera_position, np.float64) - np.asarray(look_at, np.float64)))
    return 2.0 * distance * math.tan(float(fov_rad) / 2.0) / max(float(image_height_px), 1.0)


def scale_bar_html(m_per_px: float, target_px: float = 120.0) -> tuple[str, float, float]:
    """(html, metres, pixels) of a scale bar about ``target_px`` long at ``m_per_px``."""
    metres = nice_length(target_px * m_per_px)
    pixels = metres / m_per_px
    text = f"{metres:g} m"
    html = (f'<div id="evsemmap-scale-bar" data-metres="{metres:g}" data-pixels="{pixels:.2f}" '
            'style="font:12px sans-serif;padding:2px 0 4px 4px">'
            f'<div style="width:{pixels:.2f}px;height:7px;border:2px solid #222;border-top:none;box-sizing:border-box"></div>'
            f'<span>{text}</span> <span style="color:#666">(at the orbit center)</span></div>')
    return html, metres, pixels


def measurement_text(a: np.ndarray, b: np.ndarray, frame_text: str) -> str:
    """Markdown: the two picked points in world coordinates, their distance and height difference (m)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = b - a
    return (f"distance **{np.linalg.norm(d):.3f} m**, horizontal {np.hypot(d[0], d[1]):.3f} m, "
            f"height difference **{d[2]:+.3f} m** (second minus first)\n\n"
            f"first: x={a[0]:.3f}, y={a[1]:.3f}, z={a[2]:.3f}; second: x={b[0]:.3f}, y={b[1]:.3f}, z={b[2]:.3f} m in {frame_text}")

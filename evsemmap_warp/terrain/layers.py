"""2.5-D terrain layers from a voxel map: elevation, slope, roughness, step, the surface's class and its
uncertainty, observations, traversability cost and a lethal mask per x-y cell (docs/terrain.md).

    layers = compute_layers(Mapper.load("map.npz"))               # terrain.compute_layers: cells of the voxel size
    layers.bands["traversability_cost"]                           # [rows, columns] float32, north-up

The column reduction and the neighbourhood filters are Warp kernels (``kernels/terrain.py``); this
module picks the grid, launches them, gathers each cell's voxel values and applies the cost model. A
grid's cells are squares of ``cell_m`` whose edges lie on the map's lattice (``offset_m + k cell_m``);
bands are north-up (row 0 the northern edge), like a GeoTIFF's, in the map's world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import Fusion
from ..core.mapper import Mapper, VoxelState
from ..core.warp_runtime import init_warp, resolve_device
from ..frames import WorldFrame
from .config import TerrainConfig, load_terrain_config
from .known import evidence_sums, is_known

wp = init_warp()
from ..kernels import terrain as tk  # noqa: E402

# Band order of every output (GeoTIFF bands, npz arrays, grid_map layers); per-class probability bands follow.
SCALAR_BANDS = (
    "elevation", "elevation_top", "cover_height", "slope", "roughness", "step", "surface_class", "surface_probability",
    "semantic_variance", "surface_uncommitted", "surface_conflict", "input_uncertainty", "cover_class", "lethal_class_probability",
    "observations", "known", "class_cost_mean", "class_cost_std", "traversability_cost", "lethal",
)
UNITS = {
    "elevation": "m", "elevation_top": "m", "cover_height": "m", "slope": "deg", "roughness": "m", "step": "m",
    "surface_class": "class index", "surface_probability": "1", "semantic_variance": "1", "surface_uncommitted": "1", "surface_conflict": "1",
    "input_uncertainty": "1",
    "cover_class": "class index", "lethal_class_probability": "1", "observations": "contributions", "known": "0/1",
    "class_cost_mean": "cost", "class_cost_std": "cost", "traversability_cost": "cost in [0, 1]", "lethal": "0/1",
}
CLASS_BANDS = ("surface_class", "cover_class")
MAX_CELLS = 1 << 30  # a grid of more cells is refused (a typo in --bounds or --resolution-m)


def probability_band(name: str) -> str:
    """The band name of class ``name``'s expected probability: ``probability_<name>``."""
    return f"probability_{name}"


def band_names(class_names) -> list[str]:
    """Every band of layers of these classes, in file order: the scalar bands, then one probability band per
    class."""
    return list(SCALAR_BANDS) + [probability_band(n) for n in class_names]


def band_units(name: str) -> str:
    """The unit of band ``name`` (``m``, ``deg``, ...; ``1`` for unitless bands)."""
    return UNITS.get(name, "1")


@dataclass(frozen=True)
class LayerGrid:
    """A raster of ``width`` x ``height`` cells of ``cell_m``: cell (i, j) (global indices, j grows
    northward) spans x in [offset + i cell, offset + (i + 1) cell), y likewise; ``first_cell`` is the
    south-west cell."""

    cell_m: float
    offset_m: float
    first_cell: tuple[int, int]
    width: int
    height: int

    @property
    def x0_m(self) -> float:
        """The grid's western edge (m, the map's world frame)."""
        return self.offset_m + self.first_cell[0] * self.cell_m

    @property
    def y0_m(self) -> float:
        """The grid's southern edge (m, the map's world frame)."""
        return self.offset_m + self.first_cell[1] * self.cell_m

    @property
    def x1_m(self) -> float:
        """The grid's eastern edge (m, the map's world frame)."""
        return self.x0_m + self.width * self.cell_m

    @property
    def y1_m(self) -> float:
        """The grid's northern edge (m, the map's world frame)."""
        return self.y0_m + self.height * self.cell_m

    def transform(self) -> tuple[float, float, float, float, float, float]:
        """The north-up affine (GDAL's a, b, c, d, e, f): x = c + a col, y = f + e row, at cell corners."""
        return (self.cell_m, 0.0, self.x0_m, 0.0, -self.cell_m, self.y1_m)

    def window_in(self, outer: "LayerGrid") -> tuple[int, int]:
        """(row, column) of this grid's north-west cell in ``outer`` (same lattice), north-up rows."""
        column = self.first_cell[0] - outer.first_cell[0]
        row = (outer.first_cell[1] + outer.height) - (self.first_cell[1] + self.height)
        return row, column

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """x [width] and y [height] of the cell centers, y north-up (m)."""
        x = self.x0_m + (np.arange(self.width) + 0.5) * self.cell_m
        y = self.y1_m - (np.arange(self.height) + 0.5) * self.cell_m
        return x, y

    def as_dict(self) -> dict:
        """The grid as plain values for JSON metadata, with its bounds (m)."""
        return {"cell_m": self.cell_m, "offset_m": self.offset_m, "first_cell": list(self.first_cell), "width": self.width,
                "height": self.height, "bounds_m": [self.x0_m, self.y0_m, self.x1_m, self.y1_m]}


@dataclass
class TerrainLayers:
    """Layers of one grid: ``bands`` name -> [height, width] float32, north-up, NaN where unknown."""

    grid: LayerGrid
    frame: WorldFrame | None
    class_names: tuple[str, ...]
    bands: dict[str, np.ndarray]
    config: TerrainConfig

    @property
    def band_names(self) -> list[str]:
        """Every band name, in file order."""
        return band_names(self.class_names)

    def metadata(self) -> dict:
        """The layers' metadata for files: grid, frame, classes, bands, units and the cost file."""
        return {"grid": self.grid.as_dict(), "frame": None if self.frame is None else self.frame.as_dict(),
                "classes": list(self.class_names), "bands": self.band_names, "units": {b: band_units(b) for b in self.band_names},
                "costs_file": self.config.source}


# Input checks ---------------------------------------------------------------------------------------
def check_resolution(resolution_m, voxel_m: float) -> float:
    """The cell size (m): the map's voxel size by default; finite, > 0 and not finer than a voxel."""
    if resolution_m is None:
        return float(voxel_m)
    try:
        value = float(resolution_m)
    except (TypeError, ValueError):
        raise ValueError(f"resolution_m = {resolution_m!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"resolution_m = {resolution_m!r} must be a finite number > 0 (m)")
    if value < voxel_m * (1 - 1e-9):
        raise ValueError(f"resolution_m = {value} is finer than the map's voxels ({voxel_m} m): most cells would hold no voxel center")
    return value


def check_bounds(bounds) -> np.ndarray | None:
    """[[x0, y0, z0], [x1, y1, z1]] (m; z -inf..inf when 4 numbers x0 y0 x1 y1 are given), or None."""
    if bounds is None:
        return None
    values = np.asarray(bounds, dtype=np.float64).reshape(-1)
    if len(values) == 4:
        values = np.array([values[0], values[1], -np.inf, values[2], values[3], np.inf])
    elif len(values) != 6:
        raise ValueError(f"bounds {values.tolist()}: give 4 numbers (x0 y0 x1 y1) or 6 (x0 y0 z0 x1 y1 z1), got {len(values)}")
    if np.isnan(values).any() or np.isinf(values[[0, 1, 3, 4]]).any():
        raise ValueError(f"bounds {values.tolist()}: x and y must be finite numbers")
    low, high = values[:3], values[3:]
    if np.any(low > high):
        axis = "xyz"[int(np.flatnonzero(low > high)[0])]
        raise ValueError(f"bounds {values.tolist()}: the {axis} minimum {low['xyz'.index(axis)]} is larger than its maximum {high['xyz'.index(axis)]}")
    return np.stack([low, high])


def grid_covering(x_range, y_range, cell_m: float, offset_m: float) -> LayerGrid:
    """The cells meeting [x0, x1] x [y0, y1] (m)."""
    i0 = math.floor((x_range[0] - offset_m) / cell_m)
    j0 = math.floor((y_range[0] - offset_m) / cell_m)
    i1 = max(i0, math.ceil((x_range[1] - offset_m) / cell_m) - 1)
    j1 = max(j0, math.ceil((y_range[1] - offset_m) / cell_m) - 1)
    width, height = i1 - i0 + 1, j1 - j0 + 1
    if width * height > MAX_CELLS:
        raise ValueError(f"a grid of {width} x {height} cells of {cell_m} m is too large (more than {MAX_CELLS:,} cells); "
                         "choose a smaller region (bounds) or larger cells (resolution_m)")
    return LayerGrid(cell_m, offset_m, (i0, j0), width, height)


def voxel_extent(index: np.ndarray, voxel_m: float, offset_m: float) -> np.ndarray:
    """[[x0, y0, z0], [x1, y1, z1]]: the box of the voxels' centers (m)."""
    return (np.stack([index.min(axis=0), index.max(axis=0)]).astype(np.float64) + 0.5) * voxel_m + offset_m


def grid_for(extent: np.ndarray, cell_m: float, offset_m: float, bounds: np.ndarray | None, where: str) -> LayerGrid:
    """The grid over the voxels' extent, or over ``bounds`` (which must meet it)."""
    if bounds is None:
        return grid_covering(extent[:, 0], extent[:, 1], cell_m, offset_m)
    if np.any(bounds[0] > extent[1]) or np.any(bounds[1] < extent[0]):
        box = ", ".join(f"{a} {lo:.2f}..{hi:.2f}" for a, lo, hi in zip("xyz", extent[0], extent[1]))
        raise ValueError(f"bounds {bounds.reshape(-1).tolist()} lie outside {where} (voxel centers span {box})")
    return grid_covering(bounds[:, 0], bounds[:, 1], cell_m, offset_m)


# Voxels a grid is computed from ----------------------------------------------------------------------
@dataclass
class VoxelColumns:
    """What the column reduction reads per voxel (global indices), and what is gathered for the chosen ones."""

    index: np.ndarray  # [V, 3] int64
    label: np.ndarray  # [V] int32
    occupied: np.ndarray  # [V] bool
    hits: np.ndarray  # [V] float64
    probabilities: np.ndarray  # [V, K]
    variance: np.ndarray  # [V]
    weight_sum: np.ndarray  # [V]
    weighted_uncertainty_sum: np.ndarray  # [V]
    evidence: np.ndarray  # [V, K]
    height_offset: np.ndarray  # [V] m: the mean height of the points that reached the voxel, above its center

    @classmethod
    def of(cls, mappers: list[Mapper], *, min_evidence: float = 0.0) -> "VoxelColumns":
        """The voxels of ``mappers``; a voxel counts as occupied when its state is OCCUPIED and it is known
        (``terrain.known``: its evidence adds up to ``min_evidence`` or more)."""
        return cls.of_parts([m.voxels() for m in mappers], min_evidence=min_evidence)

    @classmethod
    def of_parts(cls, parts: list, *, min_evidence: float = 0.0) -> "VoxelColumns":
        """The voxels of (VoxelArrays, DirichletSummary) pairs: a map's, or a store's tiles of one column."""
        if not parts:
            raise ValueError("no maps to compute layers from")

        def cat(get):  # one part (a map, most store columns): its arrays as they are
            return get(*parts[0]) if len(parts) == 1 else np.concatenate([get(a, s) for a, s in parts])

        return cls(index=cat(lambda a, s: a.index), label=cat(lambda a, s: s.label).astype(np.int32),
                   occupied=cat(lambda a, s: (s.state == VoxelState.OCCUPIED) & is_known(evidence_sums(a.evidence), min_evidence)),
                   hits=cat(lambda a, s: a.hits).astype(np.float64),
                   probabilities=cat(lambda a, s: s.probabilities), variance=cat(lambda a, s: s.variance),
                   weight_sum=cat(lambda a, s: a.weight_sum), weighted_uncertainty_sum=cat(lambda a, s: a.weighted_uncertainty_sum),
                   evidence=cat(lambda a, s: a.evidence), height_offset=cat(lambda a, s: a.mean_height_offset()))


def dirichlet_prior(mapper: Mapper) -> float:
    """The prior concentration per class of ``dirichlet_concentrations``: the map's prior, 1 for Dempster-Shafer."""
    return 1.0 if mapper.config.fusion is Fusion.DEMPSTER else float(mapper.config.prior)


def dirichlet_concentrations(mapper: Mapper, evidence: np.ndarray) -> np.ndarray:
    """[n, K] Dirichlet concentrations of voxels: prior + evidence; for the Dempster-Shafer method the
    subjective-logic Dirichlet of its masses (alpha = m S + 1, S = K / u, u the uncommitted mass)."""
    if mapper.config.fusion is not Fusion.DEMPSTER:
        return mapper.concentrations(evidence)
    masses = mapper.concentrations(evidence)
    k = masses.shape[1]
    uncommitted = np.maximum(1.0 - masses.sum(axis=1), 1e-12)
    return masses * (k / uncommitted)[:, None] + 1.0


# The column reduction ----------------------------------------------------------------------------------
def column_reduction(voxels: VoxelColumns, grid: LayerGrid, *, voxel_m: float, offset_m: float, surface_mask: np.ndarray,
                     clearance_m: float, z_range_m=(-np.inf, np.inf), device: str = "cpu") -> dict[str, np.ndarray]:
    """Per cell (flat, row j growing northward): the rows of the top, support and cover voxels (-1:
    none), their z indices (global) and the summed contribution counts (kernels/terrain.py)."""
    cells = grid.width * grid.height
    out = {"top_row": np.full(cells, -1, np.int64), "support_row": np.full(cells, -1, np.int64), "cover_row": np.full(cells, -1, np.int64),
           "top_z": np.zeros(cells, np.int64), "support_z": np.zeros(cells, np.int64), "cover_z": np.zeros(cells, np.int64),
           "observations": np.zeros(cells)}
    if len(voxels.index) == 0:
        return out
    if len(voxels.index) >= 1 << 32:
        raise ValueError(f"{len(voxels.index):,} voxels in one grid: the column keys hold 2^32 rows; compute a store tile by tile")
    reference = voxels.index.min(axis=0)
    local = voxels.index - reference
    if local.max() >= tk.Z_OFFSET:
        raise ValueError(f"the voxels span {local.max(axis=0).tolist()} voxels: more than the column kernels' 2^30")
    shift_x = (reference[0] * voxel_m + offset_m) - grid.x0_m
    shift_y = (reference[1] * voxel_m + offset_m) - grid.y0_m
    limit = tk.Z_OFFSET - 1
    low = -limit if not np.isfinite(z_range_m[0]) else math.ceil((z_range_m[0] - offset_m) / voxel_m - 0.5) - int(reference[2])
    high = limit if not np.isfinite(z_range_m[1]) else math.floor((z_range_m[1] - offset_m) / voxel_m - 0.5) - int(reference[2])
    low, high = int(np.clip(low, -limit, limit)), int(np.clip(high, -limit - 1, limit))
    device = resolve_device(device)
    d = device
    index_wp = wp.array(np.ascontiguousarray(local, dtype=np.int32), dtype=wp.vec3i, device=d)
    label_wp = wp.array(voxels.label.astype(np.int32), dtype=wp.int32, device=d)
    occupied_wp = wp.array(voxels.occupied.astype(np.int32), dtype=wp.int32, device=d)
    surface_wp = wp.array(surface_mask.astype(np.int32), dtype=wp.int32, device=d)
    hits_wp = wp.array(voxels.hits, dtype=wp.float64, device=d)
    top = wp.array(np.full(cells, tk.NO_VOXEL, np.int64), dtype=wp.int64, device=d)
    support = wp.array(np.full(cells, tk.NO_VOXEL, np.int64), dtype=wp.int64, device=d)
    cover = wp.array(np.full(cells, tk.NO_VOXEL, np.int64), dtype=wp.int64, device=d)
    low_z = wp.array(np.full(cells, np.iinfo(np.int32).max, np.int32), dtype=wp.int32, device=d)
    observations = wp.zeros(cells, dtype=wp.float64, device=d)
    geometry = tk.column_grid(voxel_m, shift_x, shift_y, grid.cell_m, grid.width, grid.height, low, high)
    n = len(local)
    wp.launch(tk.column_extremes, dim=n, device=d, inputs=[index_wp, label_wp, occupied_wp, surface_wp, hits_wp, geometry, top, support, low_z,
                                                          observations])
    clearance_voxels = int(math.floor(clearance_m / voxel_m + 1e-9))
    wp.launch(tk.column_cover, dim=n, device=d, inputs=[index_wp, occupied_wp, geometry, clearance_voxels, support, low_z, cover])
    out["observations"] = observations.numpy()
    for name, keys in (("top", top), ("support", support), ("cover", cover)):
        key = keys.numpy()
        found = key >= 0
        out[f"{name}_row"] = np.where(found, key & 0xFFFFFFFF, -1)
        out[f"{name}_z"] = np.where(found, (key >> 32) - tk.Z_OFFSET + reference[2], 0)
    return out


def base_layers(voxels: VoxelColumns, reduced: dict[str, np.ndarray], grid: LayerGrid, *, voxel_m: float, offset_m: float,
                concentrations, prior: float, config: TerrainConfig, class_names) -> dict[str, np.ndarray]:
    """Everything a cell gets from its own column: [height, width] float64 bands, row j northward."""
    shape = (grid.height, grid.width)
    k = len(class_names)
    bands = {}

    def height_of(name):
        # the mean height of the points that reached the voxel, not its center: a surface between two voxel
        # centers reads as itself, not in voxel-size steps that a plane fit turns into slope (docs/terrain.md)
        row = reduced[f"{name}_row"]
        found = row >= 0
        height = np.full(len(row), np.nan)
        height[found] = (reduced[f"{name}_z"][found] + 0.5) * voxel_m + offset_m + voxels.height_offset[row[found]]
        return height.reshape(shape)

    bands["elevation"] = height_of("support")
    bands["elevation_top"] = height_of("top")
    bands["cover_height"] = height_of("cover")
    support = reduced["support_row"]
    has_support = support >= 0
    rows = support[has_support]

    def per_support(values, fill=np.nan):
        out = np.full(len(support), fill, np.float64)
        out[has_support] = values
        return out.reshape(shape)

    label = voxels.label[rows]
    bands["surface_class"] = per_support(label)
    bands["surface_probability"] = per_support(voxels.probabilities[rows, label])
    bands["semantic_variance"] = per_support(voxels.variance[rows])
    # subjective logic's two kinds of doubt, kept apart: how little was seen (u) and how much what was seen
    # disagrees with the label (1 - b_label / (1 - u) = 1 - e_label / sum e); the second ranks the surface
    # class's errors, where the variance ranks them backwards (docs/terrain.md §7)
    belief, uncommitted = subjective_opinion(concentrations(voxels.evidence[rows]), prior) if len(rows) else (np.zeros((0, k)), np.zeros(0))
    bands["surface_uncommitted"] = per_support(uncommitted)
    bands["surface_conflict"] = per_support(1.0 - committed_share(belief)[np.arange(len(rows)), label])
    weight = voxels.weight_sum[rows]
    with np.errstate(invalid="ignore", divide="ignore"):
        bands["input_uncertainty"] = per_support(np.where(weight > 0, voxels.weighted_uncertainty_sum[rows] / weight, np.nan))
    cover = reduced["cover_row"]
    known = cover >= 0
    cover_rows = cover[known]

    def per_cover(values):
        out = np.full(len(cover), np.nan, np.float64)
        out[known] = values
        return out.reshape(shape)

    bands["cover_class"] = per_cover(voxels.label[cover_rows])
    alpha = concentrations(voxels.evidence[cover_rows]) if len(cover_rows) else np.zeros((0, k))
    mean, std, lethal_p = class_cost(alpha, config, class_names, prior)
    bands["lethal_class_probability"] = per_cover(lethal_p)
    bands["class_cost_mean"] = per_cover(mean)
    bands["class_cost_std"] = per_cover(std)
    bands["observations"] = reduced["observations"].reshape(shape).astype(np.float64)
    bands["known"] = known.reshape(shape).astype(np.float64)
    probabilities = np.full((len(support), k), np.nan)
    probabilities[has_support] = voxels.probabilities[rows]
    for c, name in enumerate(class_names):
        bands[probability_band(name)] = probabilities[:, c].reshape(shape)
    return bands


def subjective_opinion(alpha: np.ndarray, prior: float) -> tuple[np.ndarray, np.ndarray]:
    """Subjective logic's reading of Dirichlets alpha = prior + e [n, K]: the belief per class b = e / S and
    the uncommitted mass u = K prior / S (S = sum alpha), which add up to 1."""
    alpha = np.asarray(alpha, np.float64)
    total = alpha.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (alpha - prior) / total, (alpha.shape[1] * prior) / total[:, 0]


def committed_share(belief: np.ndarray) -> np.ndarray:
    """[n, K] the belief renormalized over the committed mass, b_k / (1 - u) = e_k / sum e: the class mix of the
    evidence itself, however much of it there is; 0 in a row of no evidence at all."""
    committed = belief.sum(axis=1, keepdims=True)
    return np.divide(belief, committed, out=np.zeros_like(belief), where=committed > 0)


def class_cost(alpha: np.ndarray, config: TerrainConfig, class_names, prior: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A cell's class cost, its standard deviation under the Dirichlet, and the lethal classes' share
    (docs/terrain.md), for concentrations ``alpha`` = ``prior`` + evidence.

    The standard deviation of c . theta, theta ~ Dir(alpha): Var = (sum_k c_k^2 p_k - E^2) / (S + 1),
    p = alpha / S, E = sum_k c_k p_k. The ``evidential`` rule's cost and lethal share are those of the
    committed belief (``committed_share``), a voxel of no evidence costing ``unknown_cost``; the
    ``expected`` rule's cost is E and its lethal share the lethal classes' expected probability."""
    alpha = np.asarray(alpha, np.float64)
    costs = np.array([float(config.costs.classes[name]) for name in class_names])
    lethal = np.array([name in config.costs.lethal_classes for name in class_names])
    total = alpha.sum(axis=1)
    p = alpha / total[:, None] if len(alpha) else alpha
    expected = p @ costs
    std = np.sqrt(np.maximum(p @ (costs * costs) - expected * expected, 0.0) / (total + 1.0))
    if config.costs.rule == "expected":
        return expected, std, p[:, lethal].sum(axis=1)
    # the uncommitted mass is left out of the cost: charging it at a fixed cost ranks cells by how often they
    # were seen rather than by class (docs/terrain.md §7), so it is a band of its own (surface_uncommitted)
    share = committed_share(subjective_opinion(alpha, prior)[0]) if len(alpha) else alpha
    seen = share.sum(axis=1) > 0
    return np.where(seen, share @ costs, config.costs.unknown_cost), std, share[:, lethal].sum(axis=1)


# The neighbourhood filters -------------------------------------------------------------------------------
def neighbourhood_filters(elevation: np.ndarray, cover_height: np.ndarray, *, cell_m: float, config: TerrainConfig,
                          device: str = "cpu") -> dict[str, np.ndarray]:
    """slope (deg) and roughness (m) of a plane fit to the elevation, and the step (m) of the cover
    height, on [rows, columns] float64 grids (NaN unknown)."""
    device = resolve_device(device)
    settings = config.layers
    out = {}
    shape = elevation.shape
    if elevation.size == 0:
        return {name: np.zeros(shape) for name in ("slope", "roughness", "step")}
    height_wp = wp.array(np.ascontiguousarray(elevation, np.float64), dtype=wp.float64, device=device)
    slope = wp.zeros(shape, dtype=wp.float64, device=device)
    rough = wp.zeros(shape, dtype=wp.float64, device=device)
    wp.launch(tk.plane_fit, dim=shape, device=device, inputs=[height_wp, settings.plane_window_cells // 2, wp.float64(cell_m),
                                                              settings.min_plane_cells, slope, rough])
    cover_wp = wp.array(np.ascontiguousarray(cover_height, np.float64), dtype=wp.float64, device=device)
    step = wp.zeros(shape, dtype=wp.float64, device=device)
    wp.launch(tk.max_step, dim=shape, device=device, inputs=[cover_wp, settings.step_window_cells // 2, step])
    out["slope"], out["roughness"], out["step"] = slope.numpy(), rough.numpy(), step.numpy()
    return out


def halo_cells(config: TerrainConfig) -> int:
    """How many cells beyond a region the filters read."""
    return max(config.layers.plane_window_cells, config.layers.step_window_cells) // 2


def finish_layers(bands: dict[str, np.ndarray], config: TerrainConfig, class_names) -> None:
    """Add the traversability cost and the lethal mask (docs/terrain.md) to a cell's own and filtered bands."""
    costs = config.costs
    known = bands["known"] > 0
    lethal_ids = [c for c, name in enumerate(class_names) if name in costs.lethal_classes]
    slope = np.nan_to_num(bands["slope"], nan=0.0)
    step = np.nan_to_num(bands["step"], nan=0.0)
    # the evidential rule's uncertainty is a band of its own (surface_uncommitted), not a part of the cost
    semantic = bands["class_cost_mean"] + (costs.uncertainty_weight * bands["class_cost_std"] if costs.rule == "expected" else 0.0)
    geometric = (costs.slope_weight * np.clip(slope / costs.max_slope_deg, 0, 1)
                 + costs.step_weight * np.clip((step - costs.free_step_m) / (costs.max_step_m - costs.free_step_m), 0, 1))
    with np.errstate(invalid="ignore"):
        lethal = known & (np.isin(bands["cover_class"], lethal_ids) | (bands["lethal_class_probability"] >= costs.lethal_probability)
                          | (slope > costs.max_slope_deg) | (step > costs.max_step_m))
        cost = np.minimum(semantic + geometric, 1.0)
    cost[lethal] = 1.0
    cost[~known] = np.nan
    bands["traversability_cost"] = cost
    bands["lethal"] = lethal.astype(np.float64)


def to_north_up(bands: dict[str, np.ndarray], class_names) -> dict[str, np.ndarray]:
    """Bands in output order, float32, row 0 the northern edge."""
    return {name: np.ascontiguousarray(bands[name][::-1], dtype=np.float32) for name in band_names(class_names)}


# The API -------------------------------------------------------------------------------------------------
def surface_mask(config: TerrainConfig, class_names) -> np.ndarray:
    """[K] int32: 1 for the classes the config's ``surface_classes`` name, else 0."""
    return np.array([name in config.layers.surface_classes for name in class_names], np.int32)


def map_layers(mapper: Mapper, *, resolution_m=None, bounds=None, config: TerrainConfig | None = None, device: str = "cpu") -> TerrainLayers:
    """The terrain layers of a Mapper (``terrain.compute_layers`` takes stores too).

    ``resolution_m``: cell edge (m), default the map's voxel size. ``bounds``: [x0, y0, x1, y1] or
    [x0, y0, z0, x1, y1, z1] (m, the map's world frame): the grid covers the cells meeting it, and only
    voxels whose centers lie in its z range count. ``config``: settings and cost table
    (``load_terrain_config``; default: configs/terrain/costs_v3.yaml)."""
    config = config if config is not None else load_terrain_config()
    if not isinstance(mapper, Mapper):
        raise ValueError(f"map_layers takes a Mapper, got {type(mapper).__name__}")
    config.check_classes(mapper.class_names)
    voxel_m = mapper.config.resolution_m
    cell_m = check_resolution(resolution_m, voxel_m)
    bounds = check_bounds(bounds)
    voxels = VoxelColumns.of([mapper], min_evidence=config.layers.min_evidence)
    if len(voxels.index) == 0:
        raise ValueError("the map holds no voxels: there is nothing to compute layers from")
    grid = grid_for(voxel_extent(voxels.index, voxel_m, mapper.grid_offset_m), cell_m, mapper.grid_offset_m, bounds, "the map")
    return layers_of_voxels(voxels, grid, mapper=mapper, config=config, bounds=bounds, device=device)


def layers_of_voxels(voxels: VoxelColumns, grid: LayerGrid, *, mapper: Mapper, config: TerrainConfig, bounds=None,
                     device: str = "cpu") -> TerrainLayers:
    """All layers of one grid from the voxels that fall in it (no halo: cells at the edge see fewer neighbours)."""
    bands = own_bands(voxels, grid, mapper=mapper, config=config, bounds=bounds, device=device)
    bands.update(neighbourhood_filters(bands["elevation"], bands["cover_height"], cell_m=grid.cell_m, config=config, device=device))
    finish_layers(bands, config, mapper.class_names)
    return TerrainLayers(grid, mapper.frame, tuple(mapper.class_names), to_north_up(bands, mapper.class_names), config)


def own_bands(voxels: VoxelColumns, grid: LayerGrid, *, mapper: Mapper, config: TerrainConfig, bounds=None, device: str = "cpu"):
    """The bands a cell gets from its own column (before the filters), row j northward."""
    z_range = (-np.inf, np.inf) if bounds is None else (bounds[0, 2], bounds[1, 2])
    voxel_m = mapper.config.resolution_m
    reduced = column_reduction(voxels, grid, voxel_m=voxel_m, offset_m=mapper.grid_offset_m,
                               surface_mask=surface_mask(config, mapper.class_names), clearance_m=config.layers.clearance_m,
                               z_range_m=z_range, device=device)
    return base_layers(voxels, reduced, grid, voxel_m=voxel_m, offset_m=mapper.grid_offset_m,
                       concentrations=lambda evidence: dirichlet_concentrations(mapper, evidence), prior=dirichlet_prior(mapper),
                       config=config, class_names=mapper.class_names)

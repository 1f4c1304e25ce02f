"""Writing terrain layers: a multi-band GeoTIFF (rasterio), an .npz, PNG previews with color bars and
class legends, and a ROS 1 bag with a ``grid_map_msgs/GridMap`` and a ``nav_msgs/OccupancyGrid``
(rosbags). Each writer takes the layers grid by grid (a map's one grid, or a store's tiles in turn),
so a store is written with the memory of a tile (docs/terrain.md).

GeoTIFF: float32 bands in ``band_names`` order, described by name and unit, nodata NaN, north-up, the
affine transform of the map's world frame, its CRS when it has one, and its name in the tags
(``FRAME``, always). grid_map: every band a layer, in grid_map's storage order (column-major, index
(0, 0) at the +x +y corner), the grid's center as its pose in the world frame. OccupancyGrid: the
traversability cost as 0..99, lethal 100, unknown -1, row 0 at the southern edge.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
from pathlib import Path
from typing import Iterator

import numpy as np

from .. import __version__
from ..files import error_naming, write_atomically, write_json_atomically
from ..frames import WorldFrame
from .layers import CLASS_BANDS, LayerGrid, TerrainLayers, band_names, band_units

GEOTIFF_NAME = "layers.tif"
NPZ_NAME = "layers.npz"
BAG_NAME = "layers.bag"
PREVIEW_DIR = "previews"
GRID_MAP_TOPIC = "/terrain/grid_map"
COSTMAP_TOPIC = "/terrain/costmap"
BAG_STAMP_NS = 1_000_000_000  # a fixed stamp (1 s): the same layers give the same bag; messages of a store follow 1 ns apart
UNFRAMED = "map"  # the frame id of maps written before maps recorded their frame

# grid_map's message definitions (ANYbotics/grid_map, grid_map_msgs, ROS 1): registered with rosbags from
# their text, so their MD5 sums are the ones ROS 1 tools expect (tests check them).
GRID_MAP_INFO_MSG = """# Header (time and frame)
Header header

# Resolution of the grid [m/cell].
float64 resolution

# Length in x-direction [m].
float64 length_x

# Length in y-direction [m].
float64 length_y

# Pose of the grid map center in the frame defined in `header` [m].
geometry_msgs/Pose pose
"""
GRID_MAP_MSG = """# Grid map header
GridMapInfo info

# Grid map layer names.
string[] layers

# Grid map basic layer names (optional). The basic layers
# determine which layers from `layers` need to be valid
# in order for a cell of the grid map to be valid.
string[] basic_layers

# Grid map data.
std_msgs/Float32MultiArray[] data

# Row start index (default 0).
uint16 outer_start_index

# Column start index (default 0).
uint16 inner_start_index
"""


def check_output_folder(out) -> Path:
    """The output folder: refused when the path exists as a file."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is a file; the layers are written into a folder (give a new path or a folder)")
    return out


@contextlib.contextmanager
def staged_output_folder(out, marker: str) -> Iterator[Path]:
    """A folder to write a whole output into, beside ``out``, that replaces ``out`` when the block ends
    without error and is removed otherwise: a rerun with other bounds leaves none of the last run's
    files, and a run interrupted (Ctrl-C) or failing (a full disk) leaves the last run's output whole.
    ``out`` must be new, empty, or an earlier output (holding ``marker``, e.g. layers.json): other
    files there would be replaced with it. One run at a time per folder (a lock on ``out``)."""
    import fcntl

    out = check_output_folder(out)
    if out.is_dir() and any(out.iterdir()) and not (out / marker).is_file():
        raise ValueError(f"--out {out}: exists and is not a layers folder (no {marker}); the layers replace the folder's content "
                         f"whole: give a new path or an empty folder")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    handle = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    token = f"{os.getpid()}-{secrets.token_hex(4)}"
    staging = out.parent / f".{out.name}.writing-{token}"
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"--out {out}: another layers run is writing this folder now; wait for it to finish, or give "
                             f"another --out") from None
        staging.mkdir()
        try:
            yield staging
            previous = out.parent / f".{out.name}.previous-{token}"
            os.rename(out, previous)
            try:
                os.rename(staging, out)
            except OSError:  # the last output back where it was: never no output at all
                os.rename(previous, out)
                raise
        except OSError as exc:  # a full disk names the folder asked for, not the staging one
            raise error_naming(exc, out, "writing the layers") from None
        created = False
        shutil.rmtree(previous, ignore_errors=True)
    finally:
        os.close(handle)  # releases the lock
        shutil.rmtree(staging, ignore_errors=True)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()


def frame_id(frame: WorldFrame | None) -> str:
    """The ROS frame id of the layers' world frame (``map`` for maps written before frames were recorded)."""
    return UNFRAMED if frame is None else frame.name


# GeoTIFF -----------------------------------------------------------------------------------------------
def _rasterio():
    try:
        import rasterio
    except ImportError:
        raise ValueError('writing GeoTIFFs needs rasterio: pip install "evsemmap_warp[geo]"') from None
    return rasterio


# Bands that are counts or masks: 0, not NaN, where no part of a mosaic reached.
UNREACHED_ZERO_BANDS = ("observations", "known", "lethal")


class GeoTiffWriter:
    """One multi-band GeoTIFF over ``grid``, written grid by grid (windows); renamed into place on close."""

    def __init__(self, path, grid: LayerGrid, frame: WorldFrame | None, class_names, *, costs_file: str):
        rasterio = _rasterio()
        from rasterio.crs import CRS
        from rasterio.transform import Affine

        self.path = Path(path)
        self.grid = grid
        self.names = band_names(class_names)
        self._temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tiled = grid.width >= 256 and grid.height >= 256
        self.dataset = rasterio.open(
            self._temporary, "w", driver="GTiff", width=grid.width, height=grid.height, count=len(self.names), dtype="float32",
            nodata=float("nan"), crs=CRS.from_string(frame.crs) if frame is not None and frame.crs else None,
            # DEFLATE, which every GeoTIFF reader knows (ZSTD is not known to older ones), at level 1 and with
            # no predictor (docs/performance.md, "Measurements behind the code's choices")
            transform=Affine(*grid.transform()), compress="deflate", zlevel=1, predictor=1, tiled=tiled,
            **({"blockxsize": 256, "blockysize": 256} if tiled else {}), BIGTIFF="IF_SAFER")
        self.dataset.update_tags(FRAME=frame_id(frame), FRAME_CRS=(frame.crs if frame is not None and frame.crs else ""),
                                 CLASSES=json.dumps(list(class_names)), COSTS_FILE=costs_file, CELL_M=str(grid.cell_m),
                                 SOFTWARE=f"evsemmap_warp {__version__}")
        for b, name in enumerate(self.names, start=1):
            self.dataset.set_band_description(b, name)
            self.dataset.set_band_unit(b, band_units(name))  # what GIS readers show; the UNITS tag is read by older tools
            tags = {"NAME": name, "UNITS": band_units(name)}
            if name in CLASS_BANDS:
                tags["CLASSES"] = json.dumps(list(class_names))
            self.dataset.update_tags(b, **tags)
        # cells no grid reaches stay unknown (NaN) but known, lethal and observations are 0 there
        self._covered = np.zeros((grid.height, grid.width), bool) if grid.width * grid.height <= 1 << 26 else None

    def write(self, layers: TerrainLayers) -> None:
        """Write every band of ``layers`` (a part of the writer's grid) into its window."""
        from rasterio.windows import Window

        row, column = layers.grid.window_in(self.grid)
        window = Window(column, row, layers.grid.width, layers.grid.height)
        for b, name in enumerate(self.names, start=1):
            self.dataset.write(layers.bands[name], b, window=window)
        if self._covered is not None:
            self._covered[row:row + layers.grid.height, column:column + layers.grid.width] = True

    def close(self) -> Path:
        """Finish the file (cells no part reached get zero counts and masks) and rename it into place;
        returns its path."""
        from rasterio.windows import Window

        if self._covered is not None and not self._covered.all():
            # Where no part reached, known / lethal / observations are 0 and every other band NaN. Every band is
            # written there: the file interleaves bands by pixel, so a block written for one band holds every band,
            # and the others read 0 there, not the nodata NaN (a store whose tile columns left cells unreached read
            # elevation 0 in them). The reached cells are a union of rectangles, so consecutive rows alike share
            # their runs of unreached cells: one window per run and such band of rows.
            covered = self._covered
            fill = np.array([0.0 if name in UNREACHED_ZERO_BANDS else np.nan for name in self.names], np.float32)
            changes = np.flatnonzero(np.any(covered[1:] != covered[:-1], axis=1)) + 1
            for top, bottom in zip(np.r_[0, changes], np.r_[changes, len(covered)]):
                edges = np.flatnonzero(np.diff(np.concatenate([[0], (~covered[top]).astype(np.int8), [0]])))
                for start, stop in zip(edges[::2], edges[1::2]):
                    width = int(stop - start)
                    step = max(1, (1 << 22) // (width * len(self.names)))  # at most 16 MB at a time
                    for row in range(int(top), int(bottom), step):
                        height = min(step, int(bottom) - row)
                        values = np.broadcast_to(fill[:, None, None], (len(self.names), height, width))
                        self.dataset.write(np.ascontiguousarray(values), window=Window(int(start), row, width, height))
        self.dataset.close()
        os.replace(self._temporary, self.path)
        return self.path

    def abort(self) -> None:
        """Close and delete the unfinished file; the final path is left untouched."""
        try:
            self.dataset.close()
        finally:
            self._temporary.unlink(missing_ok=True)


# npz -------------------------------------------------------------------------------------------------------
def write_npz(path, layers: TerrainLayers) -> Path:
    """Every band as a [height, width] float32 array (north-up, NaN unknown) and ``meta``: a JSON string with the
    grid, the frame, the classes, the bands' units and the affine transform. Compressed at zlib level 1
    (numpy's savez_compressed uses 6, whose time dominated a store's layers)."""
    import zipfile

    meta = layers.metadata() | {"transform": list(layers.grid.transform()), "written_by": f"evsemmap_warp {__version__}"}
    arrays = {"meta": np.array(json.dumps(meta))} | {name: layers.bands[name] for name in layers.band_names}

    def write(file):
        with zipfile.ZipFile(file, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
            for name, values in arrays.items():
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(values), allow_pickle=False)

    return write_atomically(path, write)


def read_npz(path) -> tuple[dict[str, np.ndarray], dict]:
    """The bands (name -> [height, width] float32) and metadata of a ``layers.npz`` or tile npz."""
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        return {name: data[name] for name in meta["bands"]}, meta


# PNG previews ------------------------------------------------------------------------------------------------
PREVIEW_COLORMAPS = {
    "elevation": "terrain", "elevation_top": "terrain", "cover_height": "terrain", "slope": "magma", "roughness": "viridis",
    "step": "magma", "surface_probability": "viridis", "semantic_variance": "inferno", "input_uncertainty": "inferno",
    "lethal_class_probability": "Reds", "observations": "cividis", "class_cost_mean": "RdYlGn_r", "class_cost_std": "inferno",
    "traversability_cost": "RdYlGn_r", "surface_uncommitted": "inferno", "surface_conflict": "inferno",
}
MAX_PREVIEW_PIXELS = 1600  # the longer side of a preview; larger grids are shown decimated
# zlib level 1: about half the encoding time of the default (6) for PNGs a few % larger (a preview is not an archive)
PREVIEW_PNG_LEVEL = 1


def preview_stride(grid: LayerGrid) -> int:
    """The decimation of previews of ``grid``: the smallest step that keeps its longer side within
    MAX_PREVIEW_PIXELS."""
    return max(1, int(np.ceil(max(grid.width, grid.height) / MAX_PREVIEW_PIXELS)))


def _nearest(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``values`` sampled at the centers of a ``shape`` raster over it (nearest), when larger than ``shape``."""
    rows, columns = values.shape
    if rows > shape[0]:
        values = values[((np.arange(shape[0]) + 0.5) * rows / shape[0]).astype(np.intp)]
    if columns > shape[1]:
        values = values[:, ((np.arange(shape[1]) + 0.5) * columns / shape[1]).astype(np.intp)]
    return values


def _pixels_of(fig, ax) -> tuple[int, int]:
    """(rows, columns) of device pixels the map covers in ``ax`` (after its equal aspect)."""
    ax.apply_aspect()
    box = ax.get_position()
    width, height = fig.get_size_inches() * fig.dpi
    return max(1, int(np.ceil(box.height * height))), max(1, int(np.ceil(box.width * width)))


UNKNOWN_COLOR = (0.85, 0.85, 0.85)  # cells no layer knows: the maps' background


class _BandFigure:
    """The one figure every band's preview is drawn on (building one per band costs more than drawing it):
    fixed places for the map and its color bar or legend (a layout engine would draw every figure twice),
    its frame (axes, ticks, labels) drawn once, and each band drawn over a copy of it with only its own
    image (colored here, at the pixels the map covers: matplotlib would resample the whole float band and
    its mask), title, color bar and legend."""

    def __init__(self, grid: LayerGrid, frame: WorldFrame | None, stride: int):
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize
        from matplotlib.figure import Figure
        from matplotlib.ticker import FixedLocator

        where = f"{frame_id(frame)}" + (f" ({frame.crs})" if frame is not None and frame.crs else "")
        aspect = grid.height / max(grid.width, 1)
        self.suffix = f" (one cell in {stride} along each axis)" if stride > 1 else ""
        self.fig = fig = Figure(figsize=(9.0, float(np.clip(9.0 * aspect, 3.0, 12.0))), dpi=100)
        FigureCanvasAgg(fig)
        self.ax = ax = fig.add_axes((0.08, 0.1, 0.66, 0.8))
        ax.set_facecolor(UNKNOWN_COLOR)
        ax.set_xlabel(f"x (m, {where})")
        ax.set_ylabel("y (m)")
        self.cax = fig.add_axes((0.8, 0.15, 0.025, 0.7))
        self.image = ax.imshow(np.zeros((1, 1, 4), np.uint8), extent=(grid.x0_m, grid.x1_m, grid.y0_m, grid.y1_m), origin="upper",
                               interpolation="nearest")
        self.shape = _pixels_of(fig, ax)
        for axis in (ax.xaxis, ax.yaxis):  # the same ticks on every band: not located again at each draw
            axis.set_major_locator(FixedLocator(axis.get_majorticklocs()))
        self.scale = ScalarMappable(Normalize(0.0, 1.0), matplotlib.colormaps["viridis"])
        self.bar = fig.colorbar(self.scale, cax=self.cax)
        self.image.set_visible(False)
        self.cax.set_visible(False)
        fig.canvas.draw()
        self.frame_pixels = fig.canvas.copy_from_bbox(fig.bbox)
        self.image.set_visible(True)
        self.cax.set_visible(True)

    def rgba(self, values, cmap, norm) -> np.ndarray:
        """``values`` colored at the map's pixels; NaN: the colormap's bad color, transparent."""
        return cmap(norm(_nearest(np.asarray(values, np.float32), self.shape)), bytes=True)

    def draw(self, name, values, cmap, norm, *, handles=None, legend=None, color_bar=False) -> None:
        """The band ``name`` over the frame: ``values`` colored by ``cmap`` and ``norm`` (or RGBA already)."""
        ax, fig = self.ax, self.fig
        fig.canvas.restore_region(self.frame_pixels)
        self.image.set_data(values if values.ndim == 3 else self.rgba(values, cmap, norm))
        ax.draw_artist(self.image)
        for spine in ax.spines.values():  # over the image's edge, as in a whole draw
            ax.draw_artist(spine)
        ax.title.set_text(name.replace("_", " ") + self.suffix)
        ax.draw_artist(ax.title)
        if ax.legend_ is not None:
            ax.legend_.remove()
        if handles:
            ax.draw_artist(ax.legend(handles=handles, **legend))
        if color_bar:
            # the bar's own norm keeps its ticks (a new norm would rebuild them); one update, not one per change
            with self.scale.callbacks.blocked():
                self.scale.set_cmap(cmap)
                self.scale.set_clim(norm.vmin, norm.vmax)
            self.bar.update_normal(self.scale)
            self.bar.set_label(f"{name} ({band_units(name)})")
            fig.draw_artist(self.cax)


def _band_previews(figure: _BandFigure, bands: dict[str, np.ndarray], class_names, colors: np.ndarray):
    """(name, values, cmap, norm, options of ``_BandFigure.draw``) of each band's preview, in order: the
    scalar bands with color bars, the class bands and the masks with legends."""
    import matplotlib
    from matplotlib.colors import ListedColormap, Normalize
    from matplotlib.patches import Patch

    for name in [n for n in band_names(class_names) if n in PREVIEW_COLORMAPS]:
        values = bands[name]
        if name in ("traversability_cost", "class_cost_mean", "surface_probability", "lethal_class_probability", "surface_uncommitted",
                    "surface_conflict"):
            low, high = 0.0, 1.0
        else:  # the band's range, as imshow scales it
            finite = values[np.isfinite(values)]
            low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        cmap, norm = matplotlib.colormaps[PREVIEW_COLORMAPS[name]], Normalize(low, high)
        options = {"color_bar": True}
        if name == "traversability_cost" and "lethal" in bands:
            colored = figure.rgba(values, cmap, norm)
            colored[_nearest(np.asarray(bands["lethal"]), figure.shape) > 0] = (26, 26, 26, 255)  # lethal, (0.1, 0.1, 0.1), over the costs
            values = colored
            options |= {"handles": [Patch(color=(0.1, 0.1, 0.1), label="lethal"), Patch(color=UNKNOWN_COLOR, label="unknown")],
                        "legend": {"loc": "lower left", "bbox_to_anchor": (1.0, 1.0), "fontsize": 8}}
        yield name, values, cmap, norm, options
    for name in CLASS_BANDS:
        values = bands[name]
        index = values[np.isfinite(values)].astype(np.intp)
        present = np.flatnonzero(np.bincount(index[(index >= 0) & (index < len(class_names))], minlength=len(class_names)))
        handles = [Patch(facecolor=colors[c], edgecolor="k", label=class_names[c]) for c in present]
        handles.append(Patch(color=UNKNOWN_COLOR, label="unknown"))
        yield name, values, ListedColormap(colors), Normalize(-0.5, len(class_names) - 0.5), {
            "handles": handles, "legend": {"loc": "center left", "bbox_to_anchor": (1.01, 0.5), "fontsize": 8, "title": "class"}}
    mask = ListedColormap([(1, 1, 1), (0.15, 0.15, 0.15)])
    for name, label in (("known", "known (an occupied voxel in the column)"), ("lethal", "lethal")):
        yield name, bands[name], mask, Normalize(0, 1), {
            "legend": {"loc": "center left", "bbox_to_anchor": (1.01, 0.5), "fontsize": 8},
            "handles": [Patch(facecolor=(0.15, 0.15, 0.15), label=label), Patch(facecolor=(1, 1, 1), edgecolor="k", label="not")]}


def _class_probabilities_figure(bands: dict[str, np.ndarray], grid: LayerGrid, class_names):
    """One figure of every class's probability band, three to a row, with one color bar."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    columns = 3
    rows = int(np.ceil(len(class_names) / columns))
    aspect = grid.height / max(grid.width, 1)
    fig = Figure(figsize=(12, max(3.0, 12 * aspect * rows / columns + 1)), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, columns, squeeze=False)
    fig.subplots_adjust(left=0.05, right=0.86, bottom=0.05, top=0.95, wspace=0.25, hspace=0.3)
    probability, norm = matplotlib.colormaps["viridis"], Normalize(0, 1)
    for c, ax in enumerate(axes.ravel()):
        if c >= len(class_names):
            ax.axis("off")
            continue
        ax.set_facecolor(UNKNOWN_COLOR)
        ax.imshow(np.zeros((1, 1, 4), np.uint8), extent=(grid.x0_m, grid.x1_m, grid.y0_m, grid.y1_m), origin="upper", interpolation="nearest")
        values = np.asarray(bands[f"probability_{class_names[c]}"], np.float32)
        ax.images[0].set_data(probability(norm(_nearest(values, _pixels_of(fig, ax))), bytes=True))
        ax.set_title(f"p({class_names[c]})", fontsize=9)
        ax.tick_params(labelsize=7)
    fig.colorbar(ScalarMappable(norm, probability), cax=fig.add_axes((0.9, 0.2, 0.02, 0.6)),
                 label="probability of the surface voxel's class")
    fig.canvas.draw()
    return fig


def write_previews(folder, bands: dict[str, np.ndarray], grid: LayerGrid, class_names, class_colors: np.ndarray, *,
                   frame: WorldFrame | None, stride: int = 1) -> list[Path]:
    """One PNG per band (scalar bands with a color bar and unit, class bands and masks with legends),
    plus ``class_probabilities.png`` with every class's probability. ``bands`` may be decimated by
    ``stride`` (cells per pixel) from ``grid``. The bands share one figure (``_BandFigure``)."""
    from PIL import Image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []

    def save(fig, name):
        path = folder / f"{name}.png"
        # the figure is opaque: RGB, a quarter fewer bytes to compress than savefig's RGBA
        Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).save(path, compress_level=PREVIEW_PNG_LEVEL)
        written.append(path)

    figure = _BandFigure(grid, frame, stride)
    for name, values, cmap, norm, options in _band_previews(figure, bands, class_names, np.asarray(class_colors, np.float64) / 255.0):
        figure.draw(name, values, cmap, norm, **options)
        save(figure.fig, name)
    save(_class_probabilities_figure(bands, grid, class_names), "class_probabilities")
    return written


# ROS bag ------------------------------------------------------------------------------------------------------
def grid_map_typestore():
    """rosbags' ROS 1 (Noetic) type store with grid_map_msgs/GridMap and GridMapInfo registered from their text."""
    try:
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    except ImportError:
        raise ValueError('writing ROS bags needs the rosbags package: pip install "evsemmap_warp[ros]"') from None
    store = get_typestore(Stores.ROS1_NOETIC)
    types = get_types_from_msg(GRID_MAP_INFO_MSG, "grid_map_msgs/msg/GridMapInfo")
    types.update(get_types_from_msg(GRID_MAP_MSG, "grid_map_msgs/msg/GridMap"))
    store.register(types)
    return store


def grid_map_data(values: np.ndarray) -> np.ndarray:
    """A north-up [height, width] band in grid_map's storage order: matrix (i, j), i along x from the
    +x edge, j along y from the +y edge, column-major (data[i + j * size_x])."""
    return np.ascontiguousarray(values[:, ::-1], dtype=np.float32).reshape(-1)


def band_from_grid_map(data: np.ndarray, size_x: int, size_y: int) -> np.ndarray:
    """The inverse of ``grid_map_data``."""
    return np.asarray(data, np.float32).reshape(size_y, size_x)[:, ::-1]


def occupancy_values(cost: np.ndarray, lethal: np.ndarray) -> np.ndarray:
    """North-up cost [0, 1] (NaN unknown) and lethal mask -> OccupancyGrid values, int8: 0..99, 100 lethal, -1 unknown."""
    values = np.where(np.isnan(cost), -1, np.clip(np.round(np.nan_to_num(cost) * 99), 0, 99)).astype(np.int8)
    values[(lethal > 0) & ~np.isnan(cost)] = 100
    return values


class BagWriter:
    """A ROS 1 bag with GridMap messages (one per grid written) and, on close, one OccupancyGrid."""

    def __init__(self, path, frame: WorldFrame | None):
        try:
            from rosbags.rosbag1 import Writer
        except ImportError:
            raise ValueError('writing ROS bags needs the rosbags package: pip install "evsemmap_warp[ros]"') from None
        self.path = Path(path)
        self.store = grid_map_typestore()
        self.types = self.store.types
        self.frame_id = frame_id(frame)
        self._temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp.bag")
        self._temporary.unlink(missing_ok=True)
        self.writer = Writer(self._temporary)
        self.writer.open()
        self.connections = {}
        self.messages = 0

    def _header(self, seq: int):
        T = self.types
        stamp = BAG_STAMP_NS + self.messages
        return T["std_msgs/msg/Header"](seq=seq, stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                                        frame_id=self.frame_id)

    def _write(self, topic: str, msg) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store, latching=1)
        self.writer.write(self.connections[topic], BAG_STAMP_NS + self.messages, self.store.serialize_ros1(msg, msgtype))
        self.messages += 1

    def _pose(self, x: float, y: float):
        T = self.types
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                          orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))

    def write_grid_map(self, layers: TerrainLayers) -> None:
        """Add one ``grid_map_msgs/GridMap`` of ``layers`` (every band a layer, ``elevation`` the basic
        layer) on the grid map topic."""
        T = self.types
        grid = layers.grid
        size_x, size_y = grid.width, grid.height
        dims = [T["std_msgs/msg/MultiArrayDimension"](label="column_index", size=size_y, stride=size_x * size_y),
                T["std_msgs/msg/MultiArrayDimension"](label="row_index", size=size_x, stride=size_x)]
        layout = T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
        data = [T["std_msgs/msg/Float32MultiArray"](layout=layout, data=grid_map_data(layers.bands[name])) for name in layers.band_names]
        info = T["grid_map_msgs/msg/GridMapInfo"](header=self._header(self.messages), resolution=float(grid.cell_m),
                                                  length_x=float(size_x * grid.cell_m), length_y=float(size_y * grid.cell_m),
                                                  pose=self._pose((grid.x0_m + grid.x1_m) / 2, (grid.y0_m + grid.y1_m) / 2))
        self._write(GRID_MAP_TOPIC, T["grid_map_msgs/msg/GridMap"](info=info, layers=list(layers.band_names), basic_layers=["elevation"],
                                                                  data=data, outer_start_index=0, inner_start_index=0))

    def write_occupancy_grid(self, values: np.ndarray, grid: LayerGrid) -> None:
        """``values``: north-up int8 from ``occupancy_values``."""
        T = self.types
        header = self._header(self.messages)
        info = T["nav_msgs/msg/MapMetaData"](map_load_time=header.stamp, resolution=float(grid.cell_m), width=grid.width,
                                             height=grid.height, origin=self._pose(grid.x0_m, grid.y0_m))
        self._write(COSTMAP_TOPIC, T["nav_msgs/msg/OccupancyGrid"](header=header, info=info,
                                                                  data=np.ascontiguousarray(values[::-1]).reshape(-1)))

    def close(self) -> Path:
        """Finish the bag and rename it into place; returns its path."""
        self.writer.close()
        os.replace(self._temporary, self.path)
        return self.path

    def abort(self) -> None:
        """Close and delete the unfinished bag; the final path is left untouched."""
        try:
            self.writer.close()
        except Exception:  # noqa: BLE001 - a writer that failed midway may not close; the temporary goes either way
            pass
        self._temporary.unlink(missing_ok=True)


def write_summary(path, summary: dict) -> Path:
    """Write ``summary`` as JSON to ``path`` atomically (``layers.json``); returns the path."""
    return write_json_atomically(path, summary, indent=1)

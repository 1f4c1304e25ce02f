"""Browser-based map inspection with viser: ``MapViewer`` and ``evsemmap view``.

The viewer reads map files only (``map_file.read_map_arrays``); it launches no kernel. Voxels are drawn as
point sprites or instanced boxes, in float32 positions relative to a local origin (viser's default
float16 would quantise a map a few hundred metres from its origin). Everything a control changes
goes through ``refresh()``, so the same code serves the browser and the tests.

Coordinates: a map's voxel centres are float64 world coordinates of its world frame (``frames.WorldFrame``:
a name and an optional EPSG CRS, e.g. UTM metres). The viewer shows that frame, reports a clicked voxel's
centre in it (float64, mm digits), and draws a world-axes marker at the local origin labelled with the
origin's world coordinates. Maps are shown together (switchable or side by side) only when their frames
agree (two maps written before frames were recorded agree; an unrecorded and a recorded frame do not).
``--trajectory`` and ``--scan`` files are read as world coordinates of the maps' frame. Exports: the PLY
holds float64 world coordinates (header comments ``frame`` and ``crs``); the HTML holds viser's float32
positions relative to the local origin, and states that origin and the frame in a ``<meta>`` element, a
comment and a visible note.
"""

from __future__ import annotations

import html
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..classes import named_colors
from ..core.map_file import read_map_arrays
from ..data.point_files import read_npy, read_point_file
from ..frames import WorldFrame, check_same_frame, describe_frame

STATE_NAMES = ("UNKNOWN", "FREE", "OCCUPIED")
COLOR_MODES = ("semantic", "variance", "mean uncertainty", "observations")
# Class colours come from configs/classes (docs/algorithm.md §5.1 for the mapping classes); other names get tab10.
CLASS_COLORS = named_colors()
_FALLBACK = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                      (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)], np.uint8)
# viridis at 9 stops; np.interp between them is indistinguishable at voxel-colour precision.
_VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
                     (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float64)
_NO_DATA = np.array([128, 128, 128], np.uint8)


def class_palette(classes: list[str]) -> np.ndarray:
    """[K, 3] uint8: the class set's colour for known class names, a tab10 colour otherwise."""
    return np.array([CLASS_COLORS.get(name.lower(), tuple(_FALLBACK[i % len(_FALLBACK)])) for i, name in enumerate(classes)], np.uint8)


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """viridis colours for values in [lo, hi]; NaN -> grey."""
    finite = np.isfinite(values)
    t = np.clip((np.where(finite, values, lo) - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    stops = np.linspace(0, 1, len(_VIRIDIS))
    out = np.stack([np.interp(t, stops, _VIRIDIS[:, c]) for c in range(3)], axis=1).astype(np.uint8)
    out[~finite] = _NO_DATA
    return out


def frame_of(meta: dict, where) -> WorldFrame | None:
    """The world frame a map file's meta records (None: written before maps recorded their frame)."""
    frame = (meta or {}).get("frame")
    return frame if isinstance(frame, WorldFrame) else WorldFrame.from_dict(frame, f"{where}: meta.frame")


def frame_label(frame: WorldFrame | None) -> str:
    """"map (EPSG:32617)", "map", or "not recorded": the frame as the GUI names it."""
    if frame is None:
        return "not recorded"
    return frame.name + (f" ({frame.crs})" if frame.crs else "")


@dataclass
class MapLayer:
    """One map file, as the viewer needs it: float64 centres in world coordinates of ``frame`` (metres)."""

    name: str
    path: Path
    classes: list[str]
    resolution: float
    grid_offset: float
    centers: np.ndarray
    voxel_index: np.ndarray
    alpha: np.ndarray
    label: np.ndarray
    state: np.ndarray
    variance: np.ndarray
    hits: np.ndarray
    mean_uncertainty: np.ndarray
    method: str
    frame: WorldFrame | None = None

    @classmethod
    def from_file(cls, path) -> "MapLayer":
        arrays, meta = read_map_arrays(path)
        return cls.from_arrays(Path(path).stem, Path(path), arrays, meta)

    @classmethod
    def from_arrays(cls, name: str, path: Path, arrays: dict, meta: dict) -> "MapLayer":
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_unc = np.where(arrays["weight_sum"] > 0, arrays["weighted_uncertainty_sum"] / arrays["weight_sum"], np.nan)
        return cls(name, path, list(meta["classes"]), float(arrays["resolution"]), float(meta.get("grid_offset_m", 0.0)),
                   np.asarray(arrays["centers"], np.float64), arrays["voxel_index"].astype(np.int64), arrays["alpha"],
                   arrays["label"], arrays["state"], arrays["variance"], arrays["hits"], mean_unc, meta["method"],
                   frame_of(meta, path))

    def voxel_at(self, points_world: np.ndarray) -> np.ndarray:
        """Row of the voxel containing each point, -1 where none is stored (map files are sorted by key)."""
        if len(self.voxel_index) == 0:
            return np.full(len(points_world), -1)
        # Global indices can exceed the table's 21-bit key range (far maps), so pack relative to the
        # map's own bounding box; the order stays x, then y, then z, as the file is sorted.
        index = np.floor((np.asarray(points_world, np.float64) - self.grid_offset) / self.resolution)
        lo, hi = self.voxel_index.min(axis=0), self.voxel_index.max(axis=0)
        inside = np.all((index >= lo) & (index <= hi), axis=1)
        span = hi - lo + 1

        def pack(rows):
            rows = np.asarray(rows, np.int64) - lo
            return (rows[:, 0] * span[1] + rows[:, 1]) * span[2] + rows[:, 2]

        stored = pack(self.voxel_index)
        keys = pack(np.where(inside[:, None], index, lo).astype(np.int64))
        rows = np.clip(np.searchsorted(stored, keys), 0, len(stored) - 1)
        return np.where(inside & (stored[rows] == keys), rows, -1)


_LAYER_ARRAYS = ("centers", "voxel_index", "alpha", "label", "state", "variance", "hits", "weight_sum", "weighted_uncertainty_sum")


class StoreOverview:
    """A map store in the viewer: every tile decimated to a share of ``max_voxels`` (read one tile at
    a time, so the overview, not the store, is what is held), and one selected tile in full detail."""

    def __init__(self, path, max_voxels: int):
        from ..core.map_store import MapStore

        self.store = MapStore(path, cache_tiles=1)
        self.path = Path(path)
        total = max(self.store.voxel_count, 1)
        self.parts: dict[str, dict] = {}
        self.meta = None
        for name in sorted(self.store.tiles):
            arrays, meta = read_map_arrays(self.store.tile_path(name))
            self.meta = self.meta or meta
            n = len(arrays["state"])
            keep = max(1, int(max_voxels * n / total)) if n else 0
            rows = np.linspace(0, n - 1, min(keep, n)).astype(np.int64) if n else np.zeros(0, np.int64)
            self.parts[name] = {k: arrays[k][rows] for k in _LAYER_ARRAYS} | {"resolution": arrays["resolution"]}
        self.detail = ""
        # store.json's frame (MapStore.frame); a store from before stores recorded it: its tiles' meta
        self.frame = self.store.frame if hasattr(self.store, "frame") else frame_of(self.meta, self.path)

    def layer(self, detail: str = "") -> MapLayer:
        """The overview, with tile ``detail`` (a tile name; "" for none) in full."""
        parts = dict(self.parts)
        if detail:
            arrays, _ = read_map_arrays(self.store.tile_path(detail))
            parts[detail] = {k: arrays[k] for k in _LAYER_ARRAYS} | {"resolution": arrays["resolution"]}
        self.detail = detail
        joined = {k: np.concatenate([p[k] for p in parts.values()]) for k in _LAYER_ARRAYS} if parts else {}
        if not parts:
            raise ValueError(f"{self.path}: the store has no tiles")
        joined["resolution"] = next(iter(parts.values()))["resolution"]
        order = np.lexsort(joined["voxel_index"].T[::-1])  # key order (x, then y, then z), as a map file's: voxel_at needs it
        joined.update({k: joined[k][order] for k in _LAYER_ARRAYS})
        layer = MapLayer.from_arrays(self.path.name, self.path, joined, self.meta)
        layer.frame = self.frame
        return layer


def load_trajectory(path) -> np.ndarray:
    """Positions [N, 3] from a KITTI/RELLIS poses.txt (12 numbers per line), or N x 3 .txt/.npy."""
    path = Path(path)
    if path.suffix == ".npy":
        data = read_npy(path)
    else:
        try:
            data = np.loadtxt(path, ndmin=2)
        except ValueError as exc:  # UnicodeDecodeError included: binary junk
            raise ValueError(f"{path}: not a table of numbers ({exc})") from None
    if data.ndim == 2 and data.shape[1] == 12:
        return data[:, [3, 7, 11]]
    if data.ndim == 2 and data.shape[1] == 3:
        return data
    raise ValueError(f"{path}: a trajectory needs 3 (x y z) or 12 (3x4 pose) numbers per row, got shape {list(data.shape)}")


def load_points(path) -> np.ndarray:
    """Points [N, 3] from any plain point file (.pcd, .ply, .npy, KITTI .bin)."""
    return read_point_file(path).points


def check_address(host: str, port: int) -> None:
    """Refuse a host this machine cannot serve on (viser would wait forever on it) or a port out of range."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"port {port} is outside 1..65535")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind((address[0], 0))  # any free port: only whether the address is ours is in question
    except (OSError, UnicodeError) as exc:
        raise ValueError(f"cannot serve on host {host!r}: {exc}") from None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class MapViewer:
    """A viser server showing one or more map files, with filters, colourings, picking and export.

    All maps must be in one world frame (``frame``; a ``FrameError`` naming both files and both frames
    otherwise). ``trajectory`` and ``scan`` are read as world coordinates of that frame. The scene is
    drawn relative to ``origin`` (float64 world coordinates, marked by a world-axes frame and a label).
    Handles are attributes: ``server``, ``gui_*`` for the controls, ``voxel_handles`` per layer,
    ``origin_axes`` and ``origin_label``."""

    def __init__(self, map_paths, *, host: str = "127.0.0.1", port: int = 8080, style: str = "points",
                 max_voxels: int = 500_000, trajectory=None, scan=None, export_dir=None):
        import viser

        if style not in ("points", "boxes"):
            raise ValueError(f"style must be 'points' or 'boxes', got {style!r}")
        if not map_paths:
            raise ValueError("give at least one map file")
        from ..core.map_store import is_store

        self.stores = {i: StoreOverview(p, max_voxels) for i, p in enumerate(map_paths) if is_store(p)}
        self.layers = [self.stores[i].layer() if i in self.stores else MapLayer.from_file(p) for i, p in enumerate(map_paths)]
        for layer in self.layers[1:]:  # switchable or side by side: only maps of one frame share the scene
            check_same_frame("view together", (str(self.layers[0].path), self.layers[0].frame), (str(layer.path), layer.frame))
        self.frame = self.layers[0].frame
        self.style = style
        self.max_voxels = int(max_voxels)
        self.export_dir = Path(export_dir) if export_dir else self.layers[0].path.parent
        self.classes = list(dict.fromkeys(c for layer in self.layers for c in layer.classes))
        self.palette = dict(zip(self.classes, class_palette(self.classes)))
        lo = np.min([layer.centers.min(axis=0) for layer in self.layers if len(layer.centers)] or [np.zeros(3)], axis=0)
        hi = np.max([layer.centers.max(axis=0) for layer in self.layers if len(layer.centers)] or [np.zeros(3)], axis=0)
        # A local origin keeps float32 positions fine-grained however far the map is from 0.
        self.origin = np.round((lo + hi) / 2.0)
        self.side_by_side_step = float(hi[0] - lo[0]) + 2.0
        # A fixed random order per layer: decimation keeps the same voxels as filters change.
        self._lod_order = [np.random.default_rng(0).permutation(len(layer.centers)) for layer in self.layers]
        self.visible_rows: list[np.ndarray] = [np.zeros(0, np.int64) for _ in self.layers]

        check_address(host, port)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        extent = float(max(np.max(hi - lo), 1.0))
        self.server.initial_camera.position = (0.0, -0.9 * extent, 0.7 * extent)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self._build_gui()
        self._add_origin_marker(extent)
        self.voxel_handles: list = [None] * len(self.layers)
        # trajectory and scan: world coordinates of the maps' frame, drawn relative to the local origin
        if trajectory is not None:
            positions = load_trajectory(trajectory) - self.origin
            if len(positions) >= 2:
                self.server.scene.add_spline_catmull_rom("/trajectory", positions.astype(np.float32), color=(255, 80, 0), thickness=3.0, thickness_units="screen")
            self.server.scene.add_point_cloud("/trajectory_poses", positions.astype(np.float32), colors=(255, 80, 0),
                                              point_size=0.3, precision="float32")
        if scan is not None:
            points = load_points(scan) - self.origin
            self.server.scene.add_point_cloud("/scan", points.astype(np.float32), colors=(200, 200, 200),
                                              point_size=0.05, precision="float32")
        self.server.scene.on_click()(self._on_click)
        self.refresh()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Map"):
            names = tuple(f"{i}: {layer.name} ({layer.method})" for i, layer in enumerate(self.layers))
            self.gui_map = gui.add_dropdown("Map", options=names, initial_value=names[0])
            self.gui_side_by_side = gui.add_checkbox("Side by side", initial_value=False, disabled=len(self.layers) == 1)
            self.gui_color_by = gui.add_dropdown("Colour by", options=COLOR_MODES, initial_value="semantic")
            max_var = max([float(layer.variance.max()) for layer in self.layers if len(layer.variance)] or [1.0])
            self.gui_max_variance = gui.add_slider("Max variance", min=0.0, max=max_var, step=max_var / 200, initial_value=max_var)
            self.gui_show_free = gui.add_checkbox("Show FREE", initial_value=False)
            self.gui_show_unknown = gui.add_checkbox("Show UNKNOWN", initial_value=False)
            self.gui_full_map = gui.add_checkbox("Full map (no decimation)", initial_value=False)
            self.gui_tile = None
            if self.stores:  # a store: its overview, and one tile in full detail
                tiles = ("(overview only)",) + tuple(f"{i}: {t}" for i, o in self.stores.items() for t in sorted(o.store.tiles))
                self.gui_tile = gui.add_dropdown("Store tile in full", options=tiles, initial_value=tiles[0])
                self.gui_tile.on_update(lambda _event: self.show_tile(self.gui_tile.value))
            self.gui_status = gui.add_markdown("")
            self.gui_frame = gui.add_markdown(self._frame_text())
        with gui.add_folder("Classes"):
            self.gui_classes = {name: gui.add_checkbox(name, initial_value=True) for name in self.classes}
        with gui.add_folder("Legend"):
            self.gui_legend = gui.add_image(self._legend_image(), label=None)
        with gui.add_folder("Selected voxel"):
            self.gui_selection = gui.add_markdown("Click a voxel.")
        with gui.add_folder("Export"):
            self.gui_export_html = gui.add_button("Standalone HTML")
            self.gui_export_ply = gui.add_button("PLY point cloud")
            self.gui_export_status = gui.add_markdown("")
        for handle in (self.gui_map, self.gui_side_by_side, self.gui_color_by, self.gui_max_variance,
                       self.gui_show_free, self.gui_show_unknown, self.gui_full_map, *self.gui_classes.values()):
            handle.on_update(lambda _event: self.refresh())
        self.gui_export_html.on_click(lambda _event: self._export_from_gui("html"))
        self.gui_export_ply.on_click(lambda _event: self._export_from_gui("ply"))

    # ------------------------------------------------------------------ world frame
    def origin_text(self) -> str:
        """The local origin in world coordinates of the frame, e.g. "map: x=500003.000, y=4000003.000, z=100.000 m"."""
        name = self.frame.name if self.frame is not None else "world (frame not recorded)"
        return f"{name}: " + ", ".join(f"{axis}={value:.3f}" for axis, value in zip("xyz", self.origin)) + " m"

    def _frame_text(self) -> str:
        count = len(self.layers)
        lines = [f"frame: **{frame_label(self.frame)}**" + (f" (all {count} maps)" if count > 1 else ""),
                 f"axes at the local origin, {self.origin_text()}"]
        if count > 1 and self.gui_side_by_side.value:
            lines.append(f"side by side: map *i* is drawn shifted by *i* x {self.side_by_side_step:.1f} m along x "
                         "(display only; a clicked voxel reports world coordinates)")
        return "\n\n".join(lines)

    def _add_origin_marker(self, extent: float) -> None:
        """World axes at the local origin (the scene's 0), labelled with its world coordinates in the frame."""
        length = float(np.clip(0.1 * extent, 1.0, 50.0))
        self.origin_axes = self.server.scene.add_frame("/world_origin", axes_length=length, axes_radius=length / 40)
        self.origin_label = self.server.scene.add_label("/world_origin/label", self.origin_text(), anchor="top-right")
        for k, axis in enumerate("xyz"):
            tip = np.zeros(3)
            tip[k] = 1.1 * length
            self.server.scene.add_label(f"/world_origin/{axis}", f"+{axis}", position=tuple(tip), anchor="center-center")

    def show_tile(self, choice: str) -> None:
        """Show a store's tile ("i: X_Y_Z", or "(overview only)") in full detail over its overview."""
        chosen = None if choice.startswith("(") else (int(choice.split(":")[0]), choice.split(": ")[1])
        for i, overview in self.stores.items():
            detail = chosen[1] if chosen and chosen[0] == i else ""
            if detail != overview.detail:
                self.layers[i] = overview.layer(detail)
                self._lod_order[i] = np.random.default_rng(0).permutation(len(self.layers[i].centers))
        self.refresh()

    def _shown_layers(self) -> list[int]:
        if self.gui_side_by_side.value:
            return list(range(len(self.layers)))
        return [int(self.gui_map.value.split(":")[0])]

    def _shift(self, i: int) -> np.ndarray:
        return np.array([self.side_by_side_step * i if self.gui_side_by_side.value else 0.0, 0.0, 0.0])

    def visible_mask(self, i: int) -> np.ndarray:
        layer = self.layers[i]
        keep = np.ones(len(layer.state), bool)
        if not self.gui_show_free.value:
            keep &= layer.state != STATE_NAMES.index("FREE")
        if not self.gui_show_unknown.value:
            keep &= layer.state != STATE_NAMES.index("UNKNOWN")
        keep &= layer.variance <= self.gui_max_variance.value + 1e-12
        hidden = [k for k, name in enumerate(layer.classes) if not self.gui_classes[name].value]
        if hidden:
            keep &= ~np.isin(layer.label, hidden)
        return keep

    def colors(self, i: int, rows: np.ndarray) -> np.ndarray:
        layer = self.layers[i]
        mode = self.gui_color_by.value
        if mode == "semantic":
            table = np.array([self.palette[name] for name in layer.classes], np.uint8)
            return table[layer.label[rows]]
        values = {"variance": layer.variance, "mean uncertainty": layer.mean_uncertainty,
                  "observations": np.log10(1.0 + layer.hits.astype(np.float64))}[mode][rows]
        finite = values[np.isfinite(values)]
        lo, hi = (float(finite.min()), float(finite.max())) if len(finite) else (0.0, 1.0)
        self._color_range = (lo, hi)
        return colormap(values, lo, hi)

    def refresh(self) -> None:
        """Recompute what is shown from the controls and push it to every browser."""
        shown = self._shown_layers()
        total_visible = total_drawn = 0
        self._color_range = None
        with self.server.atomic():
            for i, layer in enumerate(self.layers):
                if i not in shown:
                    if self.voxel_handles[i] is not None:
                        self.voxel_handles[i].visible = False
                    self.visible_rows[i] = np.zeros(0, np.int64)
                    continue
                keep = self.visible_mask(i)
                total_visible += int(keep.sum())
                order = self._lod_order[i]
                rows = order[keep[order]]
                # a store's layer is decimated already (its overview), except the tile asked for in full
                if not self.gui_full_map.value and len(rows) > self.max_voxels and i not in self.stores:
                    rows = rows[: self.max_voxels]
                rows = np.sort(rows)
                self.visible_rows[i] = rows
                total_drawn += len(rows)
                self._draw_layer(i, rows)
        self.gui_status.content = (f"{total_drawn:,} of {total_visible:,} visible voxels drawn"
                                   + ("" if total_drawn == total_visible else " (decimated; tick *Full map* for all)"))
        self.gui_legend.image = self._legend_image()
        self.gui_frame.content = self._frame_text()

    def _draw_layer(self, i: int, rows: np.ndarray) -> None:
        layer = self.layers[i]
        positions = (layer.centers[rows] - self.origin + self._shift(i)).astype(np.float32)
        colors = self.colors(i, rows)
        name = f"/maps/{i}_{layer.name}"
        if len(rows) == 0:  # viser wants at least one point; hide an empty layer instead
            positions, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        if self.style == "points":
            self.voxel_handles[i] = self.server.scene.add_point_cloud(
                name, positions, colors, point_size=layer.resolution, point_shape="square", precision="float32", visible=len(rows) > 0)
        else:
            import trimesh

            box = trimesh.creation.box(extents=[layer.resolution * 0.95] * 3)
            self.voxel_handles[i] = self.server.scene.add_batched_meshes_simple(
                name, box.vertices.astype(np.float32), box.faces.astype(np.uint32),
                batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(positions), 1)),
                batched_positions=positions, batched_colors=colors, visible=len(rows) > 0)

    def _legend_image(self) -> np.ndarray:
        from PIL import Image, ImageDraw

        if self.gui_color_by.value == "semantic":
            names = self.classes
            img = Image.new("RGB", (220, 18 * len(names) + 4), (255, 255, 255))
            draw = ImageDraw.Draw(img)
            for k, name in enumerate(names):
                draw.rectangle([4, 4 + 18 * k, 18, 18 + 18 * k], fill=tuple(int(c) for c in self.palette[name]), outline=(90, 90, 90))
                draw.text((26, 5 + 18 * k), name, fill=(0, 0, 0))
            return np.asarray(img)
        lo, hi = getattr(self, "_color_range", None) or (0.0, 1.0)
        bar = colormap(np.linspace(lo, hi, 200), lo, hi)
        img = Image.new("RGB", (220, 46), (255, 255, 255))
        img.paste(Image.fromarray(np.repeat(bar[None], 16, axis=0)), (10, 4))
        draw = ImageDraw.Draw(img)
        label = self.gui_color_by.value + (" (log10 1+n)" if self.gui_color_by.value == "observations" else "")
        draw.text((10, 24), f"{lo:.3g}", fill=(0, 0, 0))
        draw.text((150, 24), f"{hi:.3g}", fill=(0, 0, 0))
        draw.text((10, 34), label, fill=(0, 0, 0))
        return np.asarray(img)

    # ------------------------------------------------------------------ picking
    def pick(self, ray_origin, ray_direction) -> tuple[int, int] | None:
        """(layer, row) of the first visible voxel along a ray given in display coordinates."""
        d = np.asarray(ray_direction, np.float64)
        d = d / np.linalg.norm(d)
        best = None
        for i in self._shown_layers():
            rows = self.visible_rows[i]
            if len(rows) == 0:
                continue
            layer = self.layers[i]
            o = np.asarray(ray_origin, np.float64) + self.origin - self._shift(i)  # world frame
            lo = layer.centers[rows].min(axis=0) - layer.resolution
            hi = layer.centers[rows].max(axis=0) + layer.resolution
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (lo - o) / d, (hi - o) / d
            t_near = np.nanmax(np.minimum(t1, t2))
            t_far = np.nanmin(np.maximum(t1, t2))
            if t_far < max(t_near, 0.0):
                continue
            ts = np.arange(max(t_near, 0.0), t_far, layer.resolution / 4.0)[:400_000]
            hit_rows = layer.voxel_at(o + ts[:, None] * d)
            visible = np.zeros(len(layer.state), bool)
            visible[rows] = True
            good = np.flatnonzero((hit_rows >= 0) & visible[np.maximum(hit_rows, 0)])
            if len(good) and (best is None or ts[good[0]] < best[0]):
                best = (ts[good[0]], i, int(hit_rows[good[0]]))
        return None if best is None else (best[1], best[2])

    def describe(self, i: int, row: int) -> str:
        """Markdown for a voxel: its centre in world coordinates of the map's frame (float64, mm), label, evidence."""
        layer = self.layers[i]
        alpha = layer.alpha[row]
        probs = alpha / alpha.sum()
        centre = np.asarray(layer.centers[row], np.float64)
        lines = [f"**{layer.name}** voxel {tuple(int(v) for v in layer.voxel_index[row])}",
                 f"centre in {describe_frame(layer.frame)}: " + ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", centre)) + " m",
                 f"label: **{layer.classes[layer.label[row]]}** ({layer.label[row]}), state {STATE_NAMES[layer.state[row]]}",
                 f"variance: {layer.variance[row]:.3g}, observations: {int(layer.hits[row])}",
                 "", "| class | alpha | p |", "|---|---|---|"]
        lines += [f"| {name} | {a:.4g} | {p:.3f} |" for name, a, p in zip(layer.classes, alpha, probs)]
        return "\n".join(lines)

    def _on_click(self, event) -> None:
        hit = self.pick(event.ray_origin, event.ray_direction)
        self.gui_selection.content = "No visible voxel under the cursor." if hit is None else self.describe(*hit)

    # ------------------------------------------------------------------ export
    def offset_note(self) -> str:
        """What an HTML export's positions are: relative to the local origin, given in world coordinates."""
        x, y, z = self.origin
        note = (f"positions are relative to the local origin at x={x:.3f} y={y:.3f} z={z:.3f} m in "
                f"{describe_frame(self.frame)}; add it for world coordinates")
        if len(self._shown_layers()) > 1:
            note += f"; side by side, map i is drawn shifted by a further i x {self.side_by_side_step:.3f} m along x"
        return note

    def export_html(self, path) -> Path:
        """A standalone HTML file of the current scene (viewable offline, without the GUI panel).

        Its positions are viser's float32 scene positions, relative to the local origin (``origin``), not
        world coordinates; the page states the offset: ``<meta name="evsemmap-frame">`` (the frame's name,
        "none" where not recorded), ``evsemmap-crs`` (an EPSG code or "none"), ``evsemmap-local-origin``
        ("x y z", metres in that frame), an HTML comment and a visible note saying the same, and the scene's
        labelled world axes at the origin."""
        x, y, z = self.origin
        note = self.offset_note()
        metas = {"evsemmap-frame": self.frame.name if self.frame is not None else "none",
                 "evsemmap-crs": (self.frame.crs if self.frame is not None else None) or "none",
                 "evsemmap-local-origin": f"{x:.3f} {y:.3f} {z:.3f}",
                 "evsemmap-coordinates": note}
        head = "".join(f'<meta name="{key}" content="{html.escape(value, quote=True)}" />' for key, value in metas.items())
        head += "<!-- evsemmap_warp map viewer export: " + note.replace("--", "- -") + " -->"
        visible = ('<div id="evsemmap-frame-note" style="position:fixed;left:8px;bottom:8px;z-index:1000;'
                   'pointer-events:none;font:12px sans-serif;background:rgba(255,255,255,0.8);padding:2px 6px;'
                   f'border-radius:4px">{html.escape(note, quote=False)}</div>')
        page = self.server.get_scene_serializer().as_html()
        at = page.find("<head>")
        page = page[: at + 6] + head + page[at + 6:] if at >= 0 else head + page
        at = page.rfind("</body>")
        page = page[:at] + visible + page[at:] if at >= 0 else page + visible
        path = Path(path)
        path.write_text(page, encoding="utf-8")
        return path

    def export_ply(self, path) -> Path:
        """The visible voxels of the shown maps as a binary PLY point cloud: vertex positions are float64
        (``property double x/y/z``) world coordinates of the maps' frame, metres, not shifted side by side;
        colour (RGBA) and label, state, variance and observation count as per-vertex properties. The
        header names the frame: ``comment frame NAME`` and ``comment crs EPSG:NNNN`` ("none" where not
        recorded)."""
        parts = [(i, self.visible_rows[i]) for i in self._shown_layers()]
        colors = np.concatenate([self.colors(i, r) for i, r in parts])
        fields = {"label": "label", "state": "state", "variance": "variance", "observations": "hits"}
        vertex = np.zeros(len(colors), [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
                                        ("blue", "u1"), ("alpha", "u1")] + [(name, "<f4") for name in fields])
        centers = np.concatenate([np.asarray(self.layers[i].centers[r], np.float64) for i, r in parts])
        for k, axis in enumerate("xyz"):
            vertex[axis] = centers[:, k]
        for k, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = colors[:, k]
        vertex["alpha"] = 255
        for name, attribute in fields.items():
            vertex[name] = np.concatenate([getattr(self.layers[i], attribute)[r] for i, r in parts])

        def one_line(text: str) -> str:
            return " ".join(str(text).splitlines())

        types = {"<f8": "double", "|u1": "uchar", "<f4": "float"}
        header = ["ply", "format binary_little_endian 1.0",
                  "comment evsemmap_warp map viewer export: voxel centres, float64 world coordinates (m) of the frame below",
                  f"comment frame {one_line(self.frame.name) if self.frame is not None else 'none'}",
                  f"comment crs {(self.frame.crs if self.frame is not None else None) or 'none'}",
                  f"element vertex {len(vertex)}"]
        header += [f"property {types[vertex.dtype[name].str]} {name}" for name in vertex.dtype.names]
        header.append("end_header")
        path = Path(path)
        path.write_bytes(("\n".join(header) + "\n").encode("utf-8") + vertex.tobytes())
        return path

    def _export_from_gui(self, kind: str) -> None:
        stem = self.export_dir / f"{self.layers[self._shown_layers()[0]].name}_view"
        path = self.export_html(stem.with_suffix(".html")) if kind == "html" else self.export_ply(stem.with_suffix(".ply"))
        self.gui_export_status.content = f"written: `{path}`"

    def serve_forever(self) -> None:
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            self.server.stop()

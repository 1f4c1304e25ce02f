"""The voxels in the viewer's scene: ``VoxelLayers`` is the part of ``MapViewer`` that chooses which voxels
of each shown map the panel's filters leave (decimated to ``max_voxels`` in a fixed random order, so that
the same voxels stay as filters change), colors them, draws them as point sprites or lit boxes, and keeps
the counter and the legend. The shared scene is colored as the local view (scripts, exports) asks; a tab
that asks for another coloring gets its own nodes of the same names, which shadow the shared ones for it."""

from __future__ import annotations

import numpy as np

from ...terrain.known import is_known
from .colors import color_bar_image, colormap, faded, swatch_image, value_range
from .lighting import mesh_colors
from .map_layer import STATE_NAMES


class VoxelLayers:
    """Map ``i``'s voxels drawn: ``visible_rows[i]`` (rows of ``viewer.layers[i]``), ``handles[i]`` (the shared
    scene node), ``color_ranges`` (each value coloring's color bar range, from the last map drawn in it),
    ``hidden_below`` (the voxels of the shown maps that the other filters leave but that are below the
    evidence threshold and hidden; about as many where a store's overview stands for more)."""

    MIN_POINT_PX = 2.0  # a voxel drawn as a point is never smaller than this on screen, at the orbit center
    VARIANCE_PERCENTILES = (1.0, 99.0)  # "color by variance" spans these percentiles of the drawn voxels' log10 variance
    VARIANCE_FLOOR = 1e-12  # variances under it (a Dempster-Shafer map's zeros) are drawn as it, not as no data

    def __init__(self, viewer):
        self.viewer = viewer
        count = len(viewer.layers)
        # A fixed random order per layer: decimation keeps the same voxels as filters change.
        self.lod_order = [np.random.default_rng(0).permutation(len(layer.centers)) for layer in viewer.layers]
        self.visible_rows: list[np.ndarray] = [np.zeros(0, np.int64) for _ in range(count)]
        self.handles: list = [None] * count
        self.color_ranges: dict[str, tuple[float, float]] = {}
        self.hidden_below = 0.0

    def replace(self, i: int, layer) -> None:
        """Map ``i`` is ``layer`` from now on: its own random order, and its nodes gone when its name (theirs) changes."""
        if layer.name != self.viewer.layers[i].name:
            if self.handles[i] is not None:
                self.handles[i].remove()
                self.handles[i] = None
            for view in self.viewer.tabs.all_views():
                if view.voxel_handles.get(i) is not None:
                    view.voxel_handles.pop(i).remove()
        self.lod_order[i] = np.random.default_rng(0).permutation(len(layer.centers))

    # ------------------------------------------------------------------ which voxels
    def visible_mask(self, i: int, *, compared: bool = True) -> np.ndarray:
        """[V] bool: the voxels of layer ``i`` the panel's filters (states, the evidence threshold, classes, maximum
        variance, and, unless ``compared`` is False, the comparison's own choice) leave visible."""
        keep = self._filtered(i, compared)
        if not self.viewer.gui_show_below.value:
            keep &= self.known(i)
        return keep

    def known(self, i: int) -> np.ndarray:
        """[V] bool: layer ``i``'s voxels at or above the evidence threshold (``terrain.known``)."""
        return is_known(self.viewer.layers[i].evidence_sum, self.viewer.min_evidence)

    def _filtered(self, i: int, compared: bool = True) -> np.ndarray:
        """[V] bool: the voxels of layer ``i`` every filter but the evidence threshold leaves (the comparison's
        choice among them where ``compared``)."""
        viewer = self.viewer
        layer = viewer.layers[i]
        keep = np.ones(len(layer.state), bool)
        if not viewer.gui_show_free.value:
            keep &= layer.state != STATE_NAMES.index("FREE")
        if not viewer.gui_show_unknown.value:
            keep &= layer.state != STATE_NAMES.index("UNKNOWN")
        keep &= layer.variance <= viewer.max_variance + 1e-12
        hidden = [k for k, name in enumerate(layer.classes) if name in viewer.gui_classes and not viewer.gui_classes[name].value]
        if hidden:
            keep &= ~np.isin(layer.label, hidden)
        chosen = viewer.comparison.rows_compared(i) if compared else None
        if chosen is not None:
            keep &= chosen
        return keep

    def _choose_rows(self, i: int) -> tuple[np.ndarray, int, float, float]:
        """(rows drawn, voxels visible, voxels of the map they stand for, voxels hidden below the evidence threshold)
        of map ``i``."""
        viewer = self.viewer
        layer = viewer.layers[i]
        keep = self._filtered(i)
        below = np.zeros_like(keep) if viewer.gui_show_below.value else keep & ~self.known(i)
        keep &= ~below
        weight = layer.weight if layer.weight is not None else np.ones(len(keep))
        stands_for, hidden = float(weight[keep].sum()), float(weight[below].sum())
        order = self.lod_order[i]
        rows = order[keep[order]]
        # a store's layer is decimated already (its overview), except the tile asked for in full
        if not viewer.gui_full_map.value and len(rows) > viewer.max_voxels and i not in viewer.stores:
            rows = rows[: viewer.max_voxels]
        return np.sort(rows), int(keep.sum()), stands_for, hidden

    # ------------------------------------------------------------------ colors
    def colors(self, i: int, rows: np.ndarray, mode: str | None = None) -> np.ndarray:
        """[len(rows), 3] uint8 sRGB colors of layer ``i``'s voxels ``rows``: the comparison's while map ``i`` is
        compared, otherwise by ``mode`` (a *Color by* choice; None: the shared scene's, the local view's)."""
        return self._colors(i, rows, mode)[0]

    def _colors(self, i: int, rows: np.ndarray, mode: str | None) -> tuple[np.ndarray, tuple[float, float] | None]:
        viewer = self.viewer
        layer = viewer.layers[i]
        pair = viewer.comparison.pair()
        if pair is not None and i == pair[0]:
            return viewer.comparison.colors(i, rows)
        mode = mode or viewer.tabs.local.color_by.value
        if mode == "semantic":
            table = np.array([viewer.palette[name] for name in layer.classes], np.uint8)
            return table[layer.label[rows]], None
        if mode == "variance":
            # most of a map's variances bunch in a narrow band beside rare far ones (a decade or more away): on a
            # linear ramp from the minimum to the maximum the bunch takes one color. A log scale from the 1st to
            # the 99th percentile of the voxels drawn spreads them over the ramp (the legend says so).
            values = np.log10(np.maximum(layer.variance[rows], self.VARIANCE_FLOOR))
            lo, hi = value_range(values, self.VARIANCE_PERCENTILES)
            return colormap(values, lo, hi), (lo, hi)
        values = {"mean uncertainty": layer.mean_uncertainty,
                  "observations": np.log10(1.0 + layer.hits.astype(np.float64))}[mode][rows]
        lo, hi = value_range(values)
        return colormap(values, lo, hi), (lo, hi)

    def legend_image(self, mode: str | None = None) -> np.ndarray:
        """The legend of the coloring ``mode`` (None: the shared scene's): class swatches or a color bar."""
        viewer = self.viewer
        if viewer.comparison.pair() is not None:
            return viewer.comparison.legend_image(self.color_ranges.get("comparison"))
        mode = mode or viewer.tabs.local.color_by.value
        if mode == "semantic":
            return swatch_image([(name, viewer.palette[name]) for name in viewer.present_classes] or [("no classes", (128, 128, 128))])
        lo, hi = self.color_ranges.get(mode) or (0.0, 1.0)
        return color_bar_image(lo, hi, self.legend_label(mode))

    def legend_label(self, mode: str) -> str:
        """What a value coloring's color bar shows: its quantity and its scale."""
        if mode == "variance":
            low, high = self.VARIANCE_PERCENTILES
            return f"log10 variance, p{low:g}-p{high:g} of those drawn"
        return mode + (" (log10 1+n)" if mode == "observations" else "")

    # ------------------------------------------------------------------ drawing
    def draw(self, shown: list[int], hide: bool) -> tuple[int, int, float]:
        """Draw the shown maps' visible voxels in the shared scene (none where ``hide``); (drawn, visible, the
        voxels of the maps they stand for)."""
        viewer = self.viewer
        drawn = visible = 0
        stands_for = 0.0
        self.color_ranges = {}
        self.hidden_below = 0.0
        for i in range(len(viewer.layers)):
            if i not in shown or hide:
                if self.handles[i] is not None:
                    self.handles[i].visible = False
                self.visible_rows[i] = np.zeros(0, np.int64)
                continue
            rows, count, share, hidden = self._choose_rows(i)
            self.hidden_below += hidden
            self.visible_rows[i] = rows
            drawn, visible, stands_for = drawn + len(rows), visible + count, stands_for + share
            colors, color_range = self._colors(i, rows, None)
            self._note_range(None, color_range)
            self.handles[i] = self._add(viewer.server.scene, i, rows, colors)
        return drawn, visible, stands_for

    def draw_view(self, view) -> None:
        """A tab's own coloring: where it differs from the shared scene's, its own nodes of the shown maps
        (shadowing the shared ones), otherwise none; and its legend."""
        viewer = self.viewer
        with viewer.lock:
            mode = view.color_by.value
            own = (view is not viewer.tabs.local and mode != viewer.tabs.local.color_by.value and viewer.comparison.pair() is None
                   and not viewer.terrain.voxels_hidden())
            shown = viewer.comparison.shown_layers() if own else []
            for i in list(view.voxel_handles):
                if i not in shown:
                    view.voxel_handles.pop(i).remove()
            for i in shown:
                colors, color_range = self._colors(i, self.visible_rows[i], mode)
                self._note_range(mode, color_range)
                view.voxel_handles[i] = self._add(view.scene, i, self.visible_rows[i], colors)
            view.legend.image = self.legend_image(mode)
            view.legend.visible = not viewer.terrain.voxels_hidden()

    def _note_range(self, mode: str | None, color_range) -> None:
        if color_range is not None:
            key = "comparison" if self.viewer.comparison.pair() is not None else mode or self.viewer.tabs.local.color_by.value
            self.color_ranges[key] = color_range

    def _add(self, scene, i: int, rows: np.ndarray, colors: np.ndarray):
        """Map ``i``'s voxels ``rows`` in ``colors`` as a node of ``scene`` (the shared one or a tab's), named after the map."""
        viewer = self.viewer
        layer = viewer.layers[i]
        positions = (layer.centers[rows] - viewer.origin + viewer.comparison.shift(i)).astype(np.float32)
        if viewer.map_fade > 0:
            colors = faded(colors, viewer.map_fade)
        name = f"/maps/{i}_{layer.name}"
        if len(rows) == 0:  # viser wants at least one point; hide an empty layer instead
            positions, colors = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        if viewer.style == "points":
            return scene.add_point_cloud(name, positions, colors, point_size=self.point_size(i), point_shape="square",
                                         precision="float32", visible=len(rows) > 0)
        import trimesh

        box = trimesh.creation.box(extents=[layer.resolution * 0.95] * 3)
        return scene.add_batched_meshes_simple(
            name, box.vertices.astype(np.float32), box.faces.astype(np.uint32),
            batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(positions), 1)),
            batched_positions=positions, batched_colors=mesh_colors(colors), cast_shadow=False, receive_shadow=False,
            visible=len(rows) > 0)

    def point_size(self, i: int) -> float:
        """Layer ``i``'s point size (m): its voxel edge, or, when that would be under ``MIN_POINT_PX`` pixels at the
        last camera's orbit center, that many pixels' worth. viser sizes points in world units (shrinking with
        distance, with no screen minimum): a long store seen whole, 0.2 m voxels over kilometres, would draw nothing."""
        scale_bar = self.viewer.cameras.scale_bar
        floor = self.MIN_POINT_PX * scale_bar[2] if scale_bar is not None else 0.0
        return max(float(self.viewer.layers[i].resolution), floor)

    def fit_point_sizes(self) -> None:
        """Resize the drawn point layers to the camera (a size change only: the points are not sent again). The
        size is the scene's, shared by every browser: the camera that moved last sets it."""
        viewer = self.viewer
        if viewer.style != "points":
            return
        # under the layers' lock: a store loader or a live map may be replacing these handles right now (viser
        # refuses writes to a removed one), and a layer drawn anew takes its size from point_size anyway
        with viewer.lock:
            handles = [(i, handle) for i, handle in enumerate(self.handles) if handle is not None]
            handles += [(i, handle) for view in viewer.tabs.all_views() for i, handle in view.voxel_handles.items()]
            for i, handle in handles:
                size = self.point_size(i)
                if abs(handle.point_size - size) > 0.05 * size:  # not for every small camera move
                    handle.point_size = size

    # ------------------------------------------------------------------ the counter
    def status_text(self, shown, drawn: int, visible: int, stands_for: float, hide: bool) -> str:
        """The counter: drawn against visible voxels, a store's overview against the store it stands for, and
        how many voxels the evidence threshold hides."""
        text = self._drawn_text(shown, drawn, visible, stands_for, hide)
        if hide or self.hidden_below <= 0:
            return text
        about = "about " if any(self.viewer.layers[i].weight is not None for i in shown) else ""
        return (f"{text}; {about}{round(self.hidden_below):,} below the evidence threshold (min_evidence "
                f"{self.viewer.min_evidence:g}) hidden: tick *Show below the evidence threshold*")

    def _drawn_text(self, shown, drawn: int, visible: int, stands_for: float, hide: bool) -> str:
        viewer = self.viewer
        layers, stores = viewer.layers, viewer.stores
        if hide:
            return "voxels hidden: the terrain surface is drawn instead"
        held = sum(len(layers[i].state) for i in shown)
        if any(i in stores for i in shown):
            total = sum(stores[i].total_voxels for i in shown if i in stores) + sum(len(layers[i].state) for i in shown if i not in stores)
            unread = sum(len(stores[i].unread) for i in shown if i in stores)
            reading = f"; reading its tiles: {unread:,} to go" if unread else ""
            full = sum(len(stores[i].detail) for i in shown if i in stores)
            detail = f"; {full} tile(s) in full" if full else ""
            if held < total:
                return (f"{drawn:,} voxels drawn of about {round(stands_for):,} visible in the store (decimated: a store overview holds "
                        f"{held:,} of its {total:,} voxels{detail}{reading}; come near a tile, click it or choose it for full detail)")
        elif any(layers[i].weight is not None for i in shown):  # an overview of tiles as they are written
            total = round(sum(float(layers[i].weight.sum()) if layers[i].weight is not None else len(layers[i].state) for i in shown))
            if held < total:
                return (f"{drawn:,} voxels drawn of about {round(stands_for):,} visible (decimated: the overview holds {held:,} of the "
                        f"tiles' {total:,} voxels)")
        return f"{drawn:,} of {visible:,} visible voxels drawn" + ("" if drawn == visible else " (decimated; tick *Full map* for all)")

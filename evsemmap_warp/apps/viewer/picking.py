"""Picking and measuring in the viewer: ``Picking`` is the part of ``MapViewer`` that finds what a ray (a
click, the screen's center) meets first, a visible voxel, a terrain cell or the ground grid's plane, in
world coordinates; describes and marks a clicked voxel; and measures between two clicked points. Each
browser tab has its own selection and measurement (``tabs.ClientView``)."""

from __future__ import annotations

import numpy as np

from ...frames import describe_frame
from .colors import SELECTION_COLOR
from .map_layer import STATE_NAMES


def measurement_text(a: np.ndarray, b: np.ndarray, frame_text: str) -> str:
    """Markdown: the two picked points in world coordinates, their distance and height difference (m)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = b - a
    return (f"distance **{np.linalg.norm(d):.3f} m**, horizontal {np.hypot(d[0], d[1]):.3f} m, "
            f"height difference **{d[2]:+.3f} m** (second minus first)\n\n"
            f"first: x={a[0]:.3f}, y={a[1]:.3f}, z={a[2]:.3f}; second: x={b[0]:.3f}, y={b[1]:.3f}, z={b[2]:.3f} m in {frame_text}")


class Picking:
    """Rays in display coordinates (the scene's, relative to the local origin), hits in world coordinates."""

    CLICK_RADIUS_PX = 6.0  # a click this many pixels (at the orbit center's scale) from an overview's point picks it
    SELECTION_STEM_VOXELS = 6.0  # the stem above the selected voxel, in voxel edges

    def __init__(self, viewer):
        self.viewer = viewer
        viewer.server.scene.on_click()(lambda event: self.click(event.ray_origin, event.ray_direction, event.client))

    def _pick_voxel(self, ray_origin, ray_direction) -> tuple[float, int, int] | None:
        viewer = self.viewer
        d = np.asarray(ray_direction, np.float64)
        d = d / np.linalg.norm(d)
        best = None
        for i in viewer.comparison.shown_layers():
            rows = viewer.voxels.visible_rows[i]
            if len(rows) == 0:
                continue
            layer = viewer.layers[i]
            o = np.asarray(ray_origin, np.float64) + viewer.origin - viewer.comparison.shift(i)  # world frame
            if layer.weight is not None:  # a decimated overview: a ray passes between its points, a click beside one picks it
                point = self._pick_overview_point(i, o, d)
                if point is not None and (best is None or point[0] < best[0]):
                    best = (point[0], i, point[1])
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
                row = int(hit_rows[good[0]])
                # where the ray enters that voxel's box
                half = layer.resolution / 2.0
                with np.errstate(divide="ignore", invalid="ignore"):
                    a, b = (layer.centers[row] - half - o) / d, (layer.centers[row] + half - o) / d
                entry = float(np.nanmax(np.minimum(a, b)))
                best = (max(entry, 0.0) if np.isfinite(entry) else float(ts[good[0]]), i, row)
        return best

    def _pick_overview_point(self, i: int, ray_origin_world: np.ndarray, direction: np.ndarray) -> tuple[float, int] | None:
        """(distance along the ray, row) of the nearest visible decimated point of layer ``i`` (one standing for several
        voxels; a tile in full is picked voxel by voxel) that the ray (world frame, unit direction) passes within
        its drawn size or ``CLICK_RADIUS_PX`` of."""
        layer, rows = self.viewer.layers[i], self.viewer.voxels.visible_rows[i]
        rows = rows[layer.weight[rows] > 1.0]
        offsets = layer.centers[rows] - ray_origin_world
        along = offsets @ direction
        # squared distances from the ray, without an [N, 3] temporary: this runs on every camera move (the center line)
        beside2 = np.einsum("ij,ij->i", offsets, offsets) - along * along
        scale_bar = self.viewer.cameras.scale_bar
        radius = max(self.viewer.voxels.point_size(i), self.CLICK_RADIUS_PX * scale_bar[2] if scale_bar is not None else 0.0)
        near = np.flatnonzero((along > 0) & (beside2 <= radius * radius))
        if len(near) == 0:
            return None
        k = near[np.argmin(along[near])]
        return max(float(along[k]) - layer.resolution / 2, 0.0), int(rows[k])

    def pick(self, ray_origin, ray_direction) -> tuple[int, int] | None:
        """(layer, row) of the first visible voxel along a ray given in display coordinates."""
        hit = self._pick_voxel(ray_origin, ray_direction)
        return None if hit is None else (hit[1], hit[2])

    def pick_point(self, ray_origin, ray_direction) -> dict | None:
        """What a ray hits first: a visible voxel, a cell of the terrain surface, or the ground grid's plane; a
        dict with ``kind`` ("voxel", "cell", "ground"), ``point`` (world coordinates, m) and ``layer`` / ``row`` /
        ``column``."""
        viewer = self.viewer
        o = np.asarray(ray_origin, np.float64)
        d = np.asarray(ray_direction, np.float64)
        d = d / np.linalg.norm(d)
        hits = []
        voxel = self._pick_voxel(o, d)
        if voxel is not None:
            t, i, row = voxel
            hits.append((t, {"kind": "voxel", "layer": i, "row": row, "point": o + t * d + viewer.origin - viewer.comparison.shift(i)}))
        hits += viewer.terrain.hits(o, d, viewer.comparison.shown_layers())
        if viewer.gui_grid.value and d[2] < 0:
            t = (viewer.orientation.ground.z - viewer.origin[2] - o[2]) / d[2]
            if t > 0:
                hits.append((t, {"kind": "ground", "point": o + t * d + viewer.origin}))
        return min(hits, key=lambda h: h[0])[1] if hits else None

    def describe(self, i: int, row: int) -> str:
        """Markdown for a voxel: its center in world coordinates of the map's frame (float64, mm), label, evidence."""
        layer = self.viewer.layers[i]
        alpha = layer.alpha[row]
        probs = alpha / alpha.sum()
        center = np.asarray(layer.centers[row], np.float64)
        lines = [f"**{layer.name}** voxel {tuple(int(v) for v in layer.voxel_index[row])}",
                 f"center in {describe_frame(layer.frame)}: " + ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", center)) + " m",
                 self._label_line(i, row),
                 f"variance: {layer.variance[row]:.3g}, observations: {int(layer.hits[row])}, "
                 f"evidence: {layer.evidence_sum[row]:.3g} (min_evidence {self.viewer.min_evidence:g})",
                 "", "| class | alpha | p |", "|---|---|---|"]
        lines += [f"| {name} | {a:.4g} | {p:.3f} |" for name, a, p in zip(layer.classes, alpha, probs)]
        compared = self.viewer.comparison.describe_voxel(i, row)
        if compared is not None:
            lines.insert(4, compared)
        return "\n".join(lines)

    def _label_line(self, i: int, row: int) -> str:
        """The voxel's label and state; for one below the evidence threshold, that, instead of a class its
        evidence is too faint to tell."""
        layer = self.viewer.layers[i]
        if not self.viewer.voxels.known(i)[row]:
            return (f"**below the evidence threshold**: no class known (the label {layer.classes[layer.label[row]]} rests on "
                    f"evidence under it), state {STATE_NAMES[layer.state[row]]}")
        return f"label: **{layer.classes[layer.label[row]]}** ({layer.label[row]}), state {STATE_NAMES[layer.state[row]]}"

    def click(self, ray_origin, ray_direction, client=None) -> None:
        """What a click does (a ray in display coordinates; ``client``: the browser tab clicked in, None for a
        script's click): the tab's selection reports and marks what the ray hits, a store's voxel brings its tile
        column in full, and with *Measure* ticked the point is measured."""
        viewer = self.viewer
        view = viewer.tabs.acting = viewer.tabs.view_of(client)
        hit = self.pick_point(ray_origin, ray_direction)
        self._highlight(view, hit)
        if hit is None:
            view.selection.content = "Nothing under the cursor."
            return
        point = np.asarray(hit["point"], np.float64)
        view.last_point = point
        frame = describe_frame(viewer.frame)
        where = f"clicked point in {frame}: " + ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", point)) + " m"
        if hit["kind"] == "voxel":
            text = self.describe(hit["layer"], hit["row"])
            if hit["layer"] in viewer.stores:  # a store's voxel: its tile column in full
                viewer.tiles.request(hit["layer"], viewer.stores[hit["layer"]].tiles_at(point))
        elif hit["kind"] == "cell":
            classes = viewer.layers[hit["layer"]].classes
            text = viewer.terrain.surfaces[hit["layer"]].describe(hit["row"], hit["column"], classes, frame)
        else:
            text = "on the ground grid's plane"
        view.selection.content = where + "\n\n" + text
        if view.measure.value:
            self._add_measure_point(view, point)

    def _highlight(self, view, hit: dict | None) -> None:
        """The clicked voxel marked: a wireframe box around it (a little larger, so that its own faces do not
        hide it) and, since its neighbours hide most of the box, a stem rising from it to a label, which show
        above the map; removed when a click hits something else."""
        for handle in view.selection_handles:
            handle.remove()
        view.selection_handles = []
        if hit is None or hit["kind"] != "voxel":
            return
        viewer = self.viewer
        layer = viewer.layers[hit["layer"]]
        center = np.asarray(layer.centers[hit["row"]], np.float64) - viewer.origin + viewer.comparison.shift(hit["layer"])
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(corners[a] - corners[b]).sum() == 2]
        half = 0.6 * layer.resolution
        segments = [[corners[a] * half + center, corners[b] * half + center] for a, b in edges]
        top = center + [0.0, 0.0, half + self.SELECTION_STEM_VOXELS * layer.resolution]
        segments.append([center + [0.0, 0.0, half], top])
        scene = view.scene
        view.selection_handles = [
            scene.add_line_segments("/selection/box", np.array(segments, np.float32), colors=SELECTION_COLOR, thickness=4.0,
                                    thickness_units="screen"),
            scene.add_label("/selection/label", "selected", position=tuple(top), anchor="bottom-center")]

    # ------------------------------------------------------------------ measuring
    def reset_measure(self, view, *, acting: bool = False) -> None:
        """Drop a view's measured points (*Measure* ticked or unticked; ``acting``: that view acted last)."""
        if acting:
            self.viewer.tabs.acting = view
        view.measure_points.clear()
        for handle in view.measure_handles:
            handle.remove()
        view.measure_handles.clear()
        view.measure_result.content = "Click the first point." if view.measure.value else ""

    def _add_measure_point(self, view, point: np.ndarray) -> None:
        """Two clicks: the distance and height difference between them (a third click starts again)."""
        if len(view.measure_points) >= 2:
            self.reset_measure(view)
        view.measure_points.append(np.asarray(point, np.float64))
        local = [p - self.viewer.origin for p in view.measure_points]
        scene = view.scene
        view.measure_handles.append(scene.add_point_cloud(f"/measure/point{len(local)}", local[-1][None].astype(np.float32),
                                                           colors=(230, 0, 230), point_size=0.25, point_shape="circle", precision="float32"))
        if len(view.measure_points) == 1:
            view.measure_result.content = "first point set; click the second."
            return
        a, b = view.measure_points
        view.measure_handles.append(scene.add_line_segments("/measure/line", np.array([local], np.float32), colors=(230, 0, 230),
                                                             thickness=3.0, thickness_units="screen"))
        view.measure_handles.append(scene.add_label("/measure/label", f"{np.linalg.norm(b - a):.2f} m, dz {b[2] - a[2]:+.2f} m",
                                                     position=tuple((local[0] + local[1]) / 2), anchor="bottom-center"))
        view.measure_result.content = measurement_text(a, b, describe_frame(self.viewer.frame))

"""Orientation in the viewer: the ground grid under the maps (its lines on round world coordinates,
labelled in metres of the frame), the world axes at the local origin, the scale bar's length, and the
panel's frame lines (``Orientation``, a part of ``MapViewer``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .map_layer import STATE_NAMES, frame_label


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


class Orientation:
    """The part of a ``MapViewer`` that shows where the maps are: world axes at the local origin, labelled with its
    world coordinates (``origin_axes``, ``origin_label``), and the ground grid (``ground``, ``grid_handle``,
    ``grid_label_handles``) under the maps."""

    def __init__(self, viewer):
        self.viewer = viewer
        self.ground: GroundGrid | None = None
        self.grid_handle = None
        self.grid_label_handles: list = []
        self.origin_axes = self.origin_label = None

    def origin_text(self) -> str:
        """The local origin in world coordinates of the frame, e.g. "map: x=500003.000, y=4000003.000, z=100.000 m"."""
        frame = self.viewer.frame
        name = frame.name if frame is not None else "world (frame not recorded)"
        return f"{name}: " + ", ".join(f"{axis}={value:.3f}" for axis, value in zip("xyz", self.viewer.origin)) + " m"

    def frame_text(self) -> str:
        """The *Frame* folder: the maps' frame, the local origin in it, and the side-by-side shift."""
        viewer = self.viewer
        count = len(viewer.layers)
        lines = [f"frame: **{frame_label(viewer.frame)}**" + (f" (all {count} maps)" if count > 1 else ""),
                 f"axes at the local origin, {self.origin_text()}"]
        if count > 1 and viewer.gui_side_by_side.value:
            lines.append(f"side by side: map *i* is drawn shifted by *i* x {viewer.comparison.side_by_side_step:.1f} m along x "
                         "(display only; a clicked voxel reports world coordinates)")
        return "\n\n".join(lines)

    def add_origin_marker(self, extent: float) -> None:
        """World axes at the local origin (the scene's 0), labelled with its world coordinates in the frame."""
        scene = self.viewer.server.scene
        length = float(np.clip(0.1 * extent, 1.0, 50.0))
        self.origin_axes = scene.add_frame("/world_origin", axes_length=length, axes_radius=length / 40)
        self.origin_label = scene.add_label("/world_origin/label", self.origin_text(), anchor="top-right")
        for k, axis in enumerate("xyz"):
            tip = np.zeros(3)
            tip[k] = 1.1 * length
            scene.add_label(f"/world_origin/{axis}", f"+{axis}", position=tuple(tip), anchor="center-center")

    def add_ground_grid(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """A grid under the maps, its lines on round world coordinates, labelled in metres of the frame."""
        viewer = self.viewer
        occupied = [layer.centers[layer.state == STATE_NAMES.index("OCCUPIED"), 2] for layer in viewer.layers]
        occupied = np.concatenate(occupied) if occupied else np.zeros(0)
        resolution = min(layer.resolution for layer in viewer.layers)
        ground = float(np.percentile(occupied, 1.0)) if len(occupied) else float(lo[2])
        grid = self.ground = ground_grid(lo, hi, ground - 0.5 * resolution)
        for handle in self.grid_label_handles:  # a grid redrawn for maps that grew
            handle.remove()
        center = np.array([(grid.x0 + grid.x1) / 2, (grid.y0 + grid.y1) / 2, grid.z]) - viewer.origin
        size = max(grid.x1 - grid.x0, grid.y1 - grid.y0)
        visible = viewer.gui_grid.value
        self.grid_handle = viewer.server.scene.add_grid(
            "/ground_grid", width=grid.x1 - grid.x0, height=grid.y1 - grid.y0, plane="xy", cell_size=grid.cell, section_size=grid.section,
            cell_color=(215, 215, 215), section_color=(150, 150, 150), section_thickness=1.5, fade_distance=4.0 * size,
            shadow_opacity=0.0, position=tuple(center), visible=visible)
        self.grid_label_handles = [
            viewer.server.scene.add_label(f"/ground_grid_labels/{k}", text, position=tuple(position - viewer.origin), anchor="center-center",
                                          font_screen_scale=0.8, visible=visible)
            for k, (text, position) in enumerate(grid.labels)]

    def show_grid(self, visible: bool) -> None:
        """Show or hide the ground grid and its labels."""
        for handle in [self.grid_handle, *self.grid_label_handles]:
            handle.visible = bool(visible)

    def covers(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether the ground grid covers the box ``lo``..``hi`` in x and y."""
        grid = self.ground
        return not (np.any(lo[:2] < (grid.x0, grid.y0)) or np.any(hi[:2] > (grid.x1, grid.y1)))

"""The browsers' cameras in the viewer: ``Cameras`` is the part of ``MapViewer`` that frames the maps (and
follows them as they grow, for cameras their users have not moved), answers the *View* buttons, and takes
each camera report: the scale bar, the crosshair at the orbit center, the panel's line on what lies under
the screen's center, and a store's tiles in full near the camera."""

from __future__ import annotations

import collections
import threading

import numpy as np

from ...frames import describe_frame
from .orientation import metres_per_pixel, scale_bar_html

VIEW_BUTTONS = ("top-down", "reset view")


class Cameras:
    """``auto_camera``: the (position, look_at) the viewer last set; ``scale_bar``: (metres, pixels, metres per
    pixel) for the camera reported last; ``center_hit``: what lies under its screen's center (``pick_point``)."""

    def __init__(self, viewer):
        self.viewer = viewer
        self.auto_camera = None  # browsers still there follow the maps as they grow
        # every position the viewer has put cameras at: a browser's report can lag a move or two behind (it was
        # sent before the move arrived), and a camera at any of them has not been moved by its user
        self._auto_positions: collections.deque = collections.deque(maxlen=64)
        self._placed: set[int] = set()  # browsers whose camera has been where the viewer put it
        self.scale_bar: tuple[float, float, float] | None = None
        self.center_hit: dict | None = None
        self._center_camera = None  # (position, look_at) a browser last reported, waiting for the center's thread
        self._center_wake = threading.Condition()
        # the orbit center's crosshair, sized in screen pixels on each camera move (update_scale_bar)
        self.crosshair = viewer.server.scene.add_line_segments(
            "/view_center", np.array([[[-1, 0, 0], [1, 0, 0]], [[0, -1, 0], [0, 1, 0]], [[0, 0, -1], [0, 0, 1]]], np.float32),
            colors=(30, 30, 30), thickness=2.0, thickness_units="screen", visible=False)
        threading.Thread(target=self._follow_view_center, name="evsemmap-view-center", daemon=True).start()

    def stop(self) -> None:
        """Wake the center's thread so that it sees the viewer closed."""
        with self._center_wake:
            self._center_wake.notify_all()

    # ------------------------------------------------------------------ placing cameras
    def frame(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Point the initial camera, and the cameras of browsers whose users have not moved theirs, at the box
        ``lo``..``hi`` (world coordinates, m)."""
        server = self.viewer.server
        extent = float(max(np.max(hi - lo), 1.0))
        position, look_at = self.framing(lo, hi)
        previous, self.auto_camera = self.auto_camera, (position, look_at)
        server.initial_camera.position, server.initial_camera.look_at = tuple(position), tuple(look_at)
        # viser clips at 1 km by default: a long store framed whole (its camera a few km away) drew nothing
        far = self.far_plane_m(extent)
        server.initial_camera.far = far
        for client in server.get_clients().values():
            client.camera.far = far  # (its setter sends nothing when unchanged)
            if previous is not None and self._left_alone(client.camera):
                client.camera.position, client.camera.look_at = tuple(position), tuple(look_at)
        self._auto_positions.append((position, 1e-3 * max(float(np.linalg.norm(position - look_at)), 1.0)))

    def framing(self, lo: np.ndarray, hi: np.ndarray, *, panel_margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(position, look_at) in display coordinates of a camera that sees the box ``lo``..``hi`` (world
        coordinates) whole from the south, above. ``panel_margin``: the box's share of its width moved left
        of the screen's center, out from under the GUI panel on the right, with the camera that much further away."""
        extent = float(max(np.max(hi - lo), 1.0))
        look_at = np.round((lo + hi) / 2.0) - self.viewer.origin + np.array([panel_margin * float(hi[0] - lo[0]), 0.0, 0.0])
        reach = extent * (1.0 + panel_margin)
        return look_at + np.array([0.0, -0.9 * reach, 0.7 * reach]), look_at

    def place(self, client, position: np.ndarray, look_at: np.ndarray) -> None:
        """Move one browser's camera (``client``; every browser's for None) to ``position``, looking at ``look_at``."""
        clients = [client] if client is not None else list(self.viewer.server.get_clients().values())
        for each in clients:
            each.camera.position, each.camera.look_at = tuple(position), tuple(look_at)  # position moves look_at along: it goes first

    def set_view(self, which: str, client=None) -> None:
        """The View buttons: "top-down" looks straight down at what a browser's camera looks at, from as far;
        "reset view" puts it where the viewer first put it (the maps whole, from the south)."""
        if which == VIEW_BUTTONS[1]:
            self.place(client, *self.auto_camera)
            return
        for each in [client] if client is not None else list(self.viewer.server.get_clients().values()):
            look_at = np.asarray(each.camera.look_at, np.float64)
            distance = float(np.linalg.norm(np.asarray(each.camera.position, np.float64) - look_at))
            # a little south of straight above: orbit controls have no heading when looking exactly along the up axis
            self.place(each, look_at + np.array([0.0, -1e-3 * distance, distance]), look_at)

    def frame_shown(self, client=None) -> None:
        """Point a browser's camera (every browser's for None) at the maps shown, all of them side by side, clear
        of the GUI panel."""
        viewer = self.viewer
        shown = [i for i in viewer.comparison.shown_layers() if len(viewer.layers[i].centers)]
        if not shown:
            return
        lo = np.min([viewer.layers[i].centers.min(axis=0) + viewer.comparison.shift(i) for i in shown], axis=0)
        hi = np.max([viewer.layers[i].centers.max(axis=0) + viewer.comparison.shift(i) for i in shown], axis=0)
        self.place(client, *self.framing(lo, hi, panel_margin=0.15 if len(shown) > 1 else 0.0))

    @staticmethod
    def far_plane_m(extent_m: float) -> float:
        """The cameras' far clipping plane for maps ``extent_m`` across: the whole of them from the initial
        camera (about 1.14 extents away) and from a camera pulled back a few times further; never nearer
        than viser's 1 km."""
        return max(1000.0, 8.0 * extent_m)

    def _left_alone(self, camera) -> bool:
        """Whether a browser's camera is still where the viewer put it, at this or an earlier move (the position
        alone: a report sent between a move's position and its look-at holds the one and not the other)."""
        try:
            reported = np.asarray(camera.position, dtype=np.float64)
        except AssertionError:  # viser: this browser has not reported its camera yet; the initial camera will place it
            return False
        return any(np.linalg.norm(reported - placed) < tolerance for placed, tolerance in self._auto_positions)

    # ------------------------------------------------------------------ camera reports
    def report(self, camera, client_id: int | None = None) -> None:
        """What a browser's camera report does (``camera``: viser's camera handle, or anything with ``position``,
        ``look_at``, ``fov`` and ``image_height``, display coordinates; ``client_id``: the browser's, None for a
        script's camera): the scale bar, the line on what lies under the screen's center, and a store's tiles
        in full near the camera."""
        self.update_scale_bar(camera)
        if not self.viewer.stores:
            return
        # A browser first reports viser's default camera (3 m from the origin), then the initial one: only a
        # camera that has been where the viewer put it has come near anything.
        if client_id is not None and client_id not in self._placed:
            position, look_at = self.auto_camera
            if np.linalg.norm(np.asarray(camera.position) - position) > 1e-3 * max(float(np.linalg.norm(position - look_at)), 1.0):
                return
            self._placed.add(client_id)
        self.viewer.tiles.approach(camera)

    def update_scale_bar(self, camera) -> None:
        """The scale bar for a browser's camera: a round length and its screen pixels at the orbit center."""
        viewer = self.viewer
        try:
            height = float(camera.image_height)
            m_per_px = metres_per_pixel(camera.position, camera.look_at, camera.fov, height)
        except (AttributeError, TypeError, ValueError):
            return
        if not height > 0 or not np.isfinite(m_per_px) or m_per_px <= 0:
            return
        html_text, metres, pixels = scale_bar_html(m_per_px)
        self.scale_bar = (metres, pixels, m_per_px)
        viewer.gui_scale_bar.content = html_text
        viewer.voxels.fit_point_sizes()
        look_at = np.asarray(camera.look_at, np.float64)
        self.crosshair.position = tuple(look_at)
        self.crosshair.scale = 8.0 * m_per_px
        if not self.crosshair.visible:  # once: each assignment is a message to every browser
            self.crosshair.visible = True
        with self._center_wake:
            self._center_camera = (np.asarray(camera.position, np.float64), look_at)
            self._center_wake.notify_all()

    def _follow_view_center(self) -> None:
        """The panel's line on what lies under the screen's center, for the camera reported last: picking walks the
        visible voxels, so it runs here, off viser's callbacks, and skips the cameras a drag passed through."""
        viewer = self.viewer
        while not viewer.closed.is_set():
            with self._center_wake:
                while self._center_camera is None and not viewer.closed.is_set():
                    self._center_wake.wait(1.0)
                camera, self._center_camera = self._center_camera, None
            if camera is None:
                continue
            position, look_at = camera
            try:
                with viewer.lock:
                    hit = viewer.picking.pick_point(position, look_at - position) if np.linalg.norm(look_at - position) > 0 else None
                    self.center_hit = hit
                    viewer.gui_view_center.content = self._center_text(hit)
            except Exception:  # noqa: BLE001 - a layer replaced under the pick, or the server stopping: the next camera tries again
                if viewer.closed.is_set():
                    return

    def _center_text(self, hit: dict | None) -> str:
        if hit is None:
            return "under the screen's center: nothing (no voxel, surface or ground there)"
        layers = self.viewer.layers
        where = ", ".join(f"{a}={c:.3f}" for a, c in zip("xyz", hit["point"]))
        if hit["kind"] == "voxel":
            layer = layers[hit["layer"]]
            what = f"a voxel of {layer.name}, {layer.classes[layer.label[hit['row']]]}"
        elif hit["kind"] == "cell":
            what = f"the terrain surface of {layers[hit['layer']].name}"
        else:
            what = "the ground grid's plane"
        return f"under the screen's center ({what}): {where} m in {describe_frame(self.viewer.frame)}"

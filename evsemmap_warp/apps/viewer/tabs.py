"""What each browser tab has of its own (``ClientView``): its coloring and legend, its selection and its
measurement, from the defaults when it connects. ``Tabs`` is the part of ``MapViewer`` that makes them
as tabs connect; scripts and tests, which have no tab, act through a view of ``LocalControl``s."""

from __future__ import annotations

import threading
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

SELECTION_PROMPT = "Click a voxel, the terrain surface or the ground."
COLOR_MODES = ("semantic", "variance", "mean uncertainty", "observations")


class LocalControl:
    """A control of a view without a browser (a script's, a test's clicks): a viser handle's ``value``,
    ``content``, ``image`` and ``visible``, whose ``on_update`` callbacks run when ``value`` is set."""

    def __init__(self, value=None, content: str = ""):
        self._value, self.content, self._callbacks = value, content, []
        self.image, self.visible = None, True

    @property
    def value(self):
        """The control's value; setting it runs the ``on_update`` callbacks, as a browser's change would."""
        return self._value

    @value.setter
    def value(self, value) -> None:
        """Set the value and run the callbacks."""
        self._value = value
        for callback in self._callbacks:
            callback(None)

    def on_update(self, callback):
        """Run ``callback(None)`` whenever ``value`` is set (a viser handle's decorator); returns it."""
        self._callbacks.append(callback)
        return callback


@dataclass
class ClientView:
    """One browser tab's own controls and marks. ``scene``: where its marks and its own coloring of the voxels
    are drawn (the client's scene, seen by that tab only; its nodes shadow the shared ones of the same name);
    ``color_by``, ``legend``: its coloring and legend; ``selection``, ``measure``, ``measure_result``: its
    selection and measuring tool in the panel."""

    scene: object
    color_by: object
    legend: object
    selection: object
    measure: object
    measure_result: object
    measure_points: list = field(default_factory=list)
    last_point: np.ndarray | None = None  # world coordinates of the last clicked point
    measure_handles: list = field(default_factory=list)
    selection_handles: list = field(default_factory=list)
    voxel_handles: dict = field(default_factory=dict)  # map index -> its voxels in this tab's coloring (shadowing the shared node)


class Tabs:
    """The part of a ``MapViewer`` that gives each browser tab its ``ClientView`` as it connects, and drops it
    as it goes. ``local``: the view of scripts and tests (its coloring is the shared scene's, which exports
    hold); ``acting``: the view whose control a click or a change touched last."""

    def __init__(self, viewer):
        self.viewer = viewer
        self.local = ClientView(viewer.server.scene, LocalControl("semantic"), LocalControl(), LocalControl(content=SELECTION_PROMPT),
                                LocalControl(False), LocalControl(content=""))
        self.local.color_by.on_update(lambda _event: self._recolor_scene())
        self.local.measure.on_update(lambda _event: viewer.picking.reset_measure(self.local, acting=True))
        self.views: dict[int, ClientView] = {}
        self.acting = self.local
        self._lock = threading.Lock()
        viewer.server.on_client_connect(self._connect)
        viewer.server.on_client_disconnect(self._disconnect)

    def all_views(self) -> list[ClientView]:
        """Every tab's view and the local one."""
        with self._lock:
            return [self.local, *self.views.values()]

    def view_of(self, client) -> ClientView:
        """A browser tab's own view (``client``: a viser client; None: the view of scripts and tests)."""
        if client is None:
            return self.local
        return self.views.get(client.client_id) or self.local

    @contextmanager
    def scene_colored_as(self, view: ClientView):
        """The shared scene in ``view``'s coloring for the while (an export from that tab), then as before."""
        with self.viewer.lock:
            previous, acting = self.local.color_by.value, self.acting
            if view.color_by.value != previous:
                self.local.color_by.value = view.color_by.value
            try:
                yield
            finally:
                if self.local.color_by.value != previous:
                    self.local.color_by.value = previous
                self.acting = acting

    def _recolor_scene(self) -> None:
        self.acting = self.local
        self.viewer.on_control()

    def _connect(self, client) -> None:
        viewer = self.viewer
        with viewer.gui_map_folder:  # after *Side by side*, where the shared control stood
            color_by = client.gui.add_dropdown("Color by", options=COLOR_MODES, initial_value=COLOR_MODES[0],
                                               order=viewer.gui_side_by_side.order + 0.5)
        with viewer.gui_legend_folder:
            legend = client.gui.add_image(np.full((4, 4, 3), 255, np.uint8), label=None, order=viewer.gui_terrain_legend.order - 0.5)
        with viewer.gui_selected_folder:
            selection = client.gui.add_markdown(SELECTION_PROMPT)
        with viewer.gui_orientation_folder:
            measure = client.gui.add_checkbox("Measure (click 2 points)", initial_value=False)
            result = client.gui.add_markdown("")
        view = ClientView(client.scene, color_by, legend, selection, measure, result)
        color_by.on_update(lambda _event: self._recolor(view))
        measure.on_update(lambda _event: viewer.picking.reset_measure(view, acting=True))
        with self._lock:
            self.views[client.client_id] = view
        viewer.voxels.draw_view(view)
        client.camera.on_update(lambda camera: viewer.cameras.report(camera, client.client_id))
        viewer.cameras.update_scale_bar(client.camera)

    def _recolor(self, view: ClientView) -> None:
        self.acting = view
        self.viewer.voxels.draw_view(view)

    def _disconnect(self, client) -> None:
        with self._lock:
            view = self.views.pop(client.client_id, None)
        if view is self.acting:
            self.acting = self.local

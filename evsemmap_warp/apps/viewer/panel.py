"""The viewer's panel: the shared controls every tab sees, in the order a user reads them (the map, its
coloring, the counter, the legend and the scale first; filters, classes and tools after). ``add_panel``
makes them as a ``MapViewer``'s ``gui_*`` handles; each tab's own controls (its coloring, legend, selection
and measuring) join these folders as it connects (``tabs``)."""

from __future__ import annotations

import math

from .camera import VIEW_BUTTONS
from .colors import swatch_image
from .comparison import DIFF_MODES
from .exports import export_from_gui
from .terrain import TERRAIN_MODES


def variance_slider_range(layers) -> tuple[float, float, float, str]:
    """(unit, step, top, label) of the variance slider for the maps' largest variance."""
    max_var = max([float(layer.variance.max()) for layer in layers if len(layer.variance)] or [1.0])
    # The slider counts in units of 10^e so that its number box shows the whole value ("1.71", not "0.01710").
    unit = 10.0 ** math.floor(math.log10(max_var)) if max_var > 0 else 1.0
    step = 10.0 ** math.floor(math.log10(max(max_var / unit, 1e-12) / 200))
    top = math.ceil(max_var / unit / step - 1e-9) * step if max_var > 0 else 1.0
    exponent = int(round(math.log10(unit)))
    return unit, step, top, "Max variance" + (f" ×1e{exponent}" if exponent else "")


def add_panel(viewer) -> None:
    """Make ``viewer``'s shared controls (its ``gui_*`` handles) and connect them."""
    gui = viewer.server.gui
    names = tuple(f"{i}: {layer.name} ({layer.method})" for i, layer in enumerate(viewer.layers))
    _add_map_and_legend(viewer, gui, names)
    _add_filters(viewer, gui)
    viewer.gui_orientation_folder = gui.add_folder("Orientation and measuring")
    with viewer.gui_orientation_folder:
        viewer.gui_view = gui.add_button_group("View", VIEW_BUTTONS)
        viewer.gui_grid = gui.add_checkbox("Ground grid", initial_value=True)
    with gui.add_folder("Terrain layers"):
        viewer.gui_terrain_compute = gui.add_button("Compute terrain layers")
        viewer.gui_terrain_show = gui.add_checkbox("Show surface", initial_value=True)
        viewer.gui_terrain_band = gui.add_dropdown("Layer", options=("traversability_cost",), initial_value="traversability_cost")
        viewer.gui_terrain_status = gui.add_markdown("Not computed: the button computes the layers of each map (docs/terrain.md).")
    viewer.gui_diff = viewer.gui_diff_against = viewer.gui_diff_status = None
    if len(viewer.layers) > 1:
        with gui.add_folder("Compare maps"):
            viewer.gui_diff = gui.add_dropdown("Show", options=DIFF_MODES, initial_value="off")
            viewer.gui_diff_against = gui.add_dropdown("Second map", options=names, initial_value=names[1])
            truth_path = viewer.comparison.truth_path
            truth = f"truth: `{truth_path.name}`" if truth_path else "no ground truth given (`--truth`)"
            viewer.gui_diff_status = gui.add_markdown(f"The first map is the one chosen above; {truth}.")
    with gui.add_folder("Frame"):
        viewer.gui_frame = gui.add_markdown(viewer.orientation.frame_text())
    with gui.add_folder("Export"):
        viewer.gui_export_html = gui.add_button("Standalone HTML")
        viewer.gui_export_ply = gui.add_button("PLY point cloud")
        viewer.gui_export_status = gui.add_markdown("")
    _connect(viewer)


def _add_map_and_legend(viewer, gui, names: tuple[str, ...]) -> None:
    viewer.gui_map_folder = gui.add_folder("Map")
    with viewer.gui_map_folder:
        viewer.gui_map = gui.add_dropdown("Map", options=names, initial_value=names[0])
        viewer.gui_side_by_side = gui.add_checkbox("Side by side", initial_value=False, disabled=len(viewer.layers) == 1)
        # each tab's own *Color by* comes next (tabs); *Draw* is here, not in the terrain folder: with terrain
        # layers, what is drawn is the first thing a user switches
        viewer.gui_terrain_mode = gui.add_dropdown("Draw", options=TERRAIN_MODES, initial_value=TERRAIN_MODES[1], visible=False)
        viewer.gui_status = gui.add_markdown("")
    viewer.gui_legend_folder = gui.add_folder("Legend")
    with viewer.gui_legend_folder:
        # each tab's own legend comes first (tabs); then the terrain surface's color bar or class legend, once computed
        viewer.gui_terrain_legend = gui.add_image(swatch_image([("", (255, 255, 255))]), label=None, visible=False)
        viewer.gui_scale_bar = gui.add_html('<div id="evsemmap-scale-bar" style="font:12px sans-serif">scale: waiting for the camera</div>')
        viewer.gui_view_center = gui.add_markdown("under the screen's center: waiting for the camera")
    # filled by a drive's playback (drive.DrivePlayback) or a live map (live): kept next to the legend
    viewer.gui_drive_folder = gui.add_folder("Drive", visible=False)
    # the selection and the measuring tool are each browser tab's own (tabs.ClientView), made as it connects
    viewer.gui_selected_folder = gui.add_folder("Selected")


def _add_filters(viewer, gui) -> None:
    with gui.add_folder("Filters"):
        viewer.variance_unit, step, top, label = variance_slider_range(viewer.layers)
        viewer.gui_max_variance = gui.add_slider(label, min=0.0, max=top, step=step, initial_value=top)
        viewer.gui_show_free = gui.add_checkbox("Show FREE", initial_value=False)
        viewer.gui_show_unknown = gui.add_checkbox("Show UNKNOWN", initial_value=False)
        viewer.gui_show_below = gui.add_checkbox("Show below the evidence threshold", initial_value=False,
                                                 hint=f"voxels whose evidence sums to under min_evidence {viewer.min_evidence:g}: "
                                                      "kernel tails, whose class no point decided (docs/viewer.md)")
        viewer.gui_full_map = gui.add_checkbox("Full map (no decimation)", initial_value=False)
        viewer.gui_tile = None
        if viewer.stores:  # a store: its overview, and a tile in full detail, flown to
            tiles = ("(overview only)",) + tuple(viewer.tiles.choices)
            viewer.gui_tile = gui.add_dropdown("Store tile in full", options=tiles, initial_value=tiles[0])
            viewer.gui_tile.on_update(lambda _event: viewer.tiles.show(viewer.gui_tile.value))
    viewer.gui_classes_folder = gui.add_folder("Classes")
    with viewer.gui_classes_folder:
        viewer.gui_classes = {name: gui.add_checkbox(name, initial_value=True) for name in viewer.present_classes}


def add_class_toggles(viewer, names: list[str]) -> None:
    """Toggles for classes that maps hold from now on (a live map's, a store's as its tiles come in)."""
    with viewer.gui_classes_folder:
        for name in names:
            viewer.gui_classes[name] = viewer.server.gui.add_checkbox(name, initial_value=True)
            viewer.gui_classes[name].on_update(lambda _event: viewer.on_control())


def _connect(viewer) -> None:
    controls = [viewer.gui_map, viewer.gui_side_by_side, viewer.gui_max_variance, viewer.gui_show_free, viewer.gui_show_unknown,
                viewer.gui_show_below, viewer.gui_full_map, *viewer.gui_classes.values(), viewer.gui_terrain_show, viewer.gui_terrain_band,
                viewer.gui_terrain_mode]
    if viewer.gui_diff is not None:
        controls += [viewer.gui_diff, viewer.gui_diff_against]
    for handle in controls:
        handle.on_update(lambda _event: viewer.on_control())
    viewer.gui_grid.on_update(lambda _event: viewer.orientation.show_grid(viewer.gui_grid.value))
    viewer.gui_view.on_click(lambda event: viewer.cameras.set_view(event.target.value, event.client))
    viewer.gui_side_by_side.on_update(lambda event: viewer.cameras.frame_shown(event.client))
    viewer.gui_terrain_compute.on_click(lambda _event: viewer.terrain.compute_from_gui())
    viewer.gui_export_html.on_click(lambda event: export_from_gui(viewer, "html", event.client))
    viewer.gui_export_ply.on_click(lambda event: export_from_gui(viewer, "ply", event.client))

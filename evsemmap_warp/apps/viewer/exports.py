"""What the viewer writes: a standalone HTML page of the shared scene (positions relative to the local origin,
which the page states with the frame, beside the legend and a summary of the view) and a PLY point cloud of
the visible voxels (float64 world coordinates). Both hold the scene every tab shares, colored as the local
view (``MapViewer.gui_color_by`` without a browser) asks; the panel's buttons write it in the coloring of the
tab that clicks them."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ...files import write_bytes_atomically, write_text_atomically
from ...frames import describe_frame
from .comparison import DIFF_COLORS
from .map_layer import frame_label


def offset_note(viewer) -> str:
    """What an HTML export's positions are: relative to the local origin, given in world coordinates."""
    x, y, z = viewer.origin
    note = (f"positions are relative to the local origin at x={x:.3f} y={y:.3f} z={z:.3f} m in "
            f"{describe_frame(viewer.frame)}; add it for world coordinates")
    if len(viewer.comparison.shown_layers()) > 1:
        note += f"; side by side, map i is drawn shifted by a further i x {viewer.comparison.side_by_side_step:.3f} m along x"
    return note


def _image(array, alt: str) -> str:
    import base64
    from io import BytesIO

    from PIL import Image

    buffer = BytesIO()
    Image.fromarray(np.asarray(array, np.uint8)).save(buffer, format="PNG")
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img alt="{html.escape(alt, quote=True)}" src="data:image/png;base64,{data}" style="display:block;width:220px" />'


def legend_html(viewer) -> str:
    """The legend and a summary of the view as an HTML panel (``id="evsemmap-legend"``) for the HTML export:
    class swatches with names (or the color bar as an image), the terrain layer's bar when the surface is
    shown, the counter and the maps' frame."""
    shown = [viewer.layers[i] for i in viewer.comparison.shown_layers()]
    pair = viewer.comparison.pair()
    mode = viewer.tabs.local.color_by.value
    if pair is not None:
        title = f"{viewer.gui_diff.value}: {viewer.layers[pair[0]].name} against {viewer.layers[pair[1]].name}"
    else:
        title = f"color by {mode}"
    parts = [f'<div style="font-weight:bold">{html.escape(", ".join(layer.name for layer in shown))}</div>',
             f"<div>{html.escape(title)}</div>"]
    if pair is not None and viewer.gui_diff.value == "labels differ":
        entries = list(DIFF_COLORS.items())
    elif pair is None and mode == "semantic":
        entries = [(name, viewer.palette[name]) for name in viewer.present_classes]
    else:
        entries = None
    if entries is not None:
        for name, color in entries:
            rgb = ",".join(str(int(c)) for c in color)
            parts.append(f'<div class="evsemmap-legend-entry"><span style="display:inline-block;width:14px;height:14px;'
                         f'margin-right:6px;vertical-align:middle;border:1px solid #5a5a5a;background:rgb({rgb})"></span>'
                         f"{html.escape(name)}</div>")
    else:
        lo, hi = viewer.voxels.color_ranges.get("comparison" if pair is not None else mode) or (0.0, 1.0)
        parts.append(_image(viewer.voxels.legend_image(), f"color bar {lo:.3g} to {hi:.3g}"))
    if viewer.terrain.shown():
        parts.append(f"<div>terrain surface: {html.escape(viewer.gui_terrain_band.value)}</div>")
        parts.append(_image(viewer.gui_terrain_legend.image, f"terrain {viewer.gui_terrain_band.value}"))
    status = viewer.gui_status.content.replace("*", "")
    parts.append(f'<div style="color:#444">{html.escape(status)}</div>')
    parts.append(f'<div style="color:#444">frame: {html.escape(frame_label(viewer.frame))}; grid lines every '
                 f"{viewer.orientation.ground.section:g} m</div>")
    return ('<div id="evsemmap-legend" style="position:fixed;left:8px;top:8px;z-index:1000;max-width:260px;max-height:80vh;'
            'overflow:auto;font:12px sans-serif;background:rgba(255,255,255,0.92);padding:6px 8px;border-radius:4px;'
            'border:1px solid #ccc">' + "".join(parts) + "</div>")


def write_html(viewer, path) -> Path:
    """``MapViewer.export_html``: the shared scene as a standalone HTML file at ``path``."""
    x, y, z = viewer.origin
    note = offset_note(viewer)
    frame = viewer.frame
    metas = {"evsemmap-frame": frame.name if frame is not None else "none",
             "evsemmap-crs": (frame.crs if frame is not None else None) or "none",
             "evsemmap-local-origin": f"{x:.3f} {y:.3f} {z:.3f}",
             "evsemmap-coordinates": note}
    head = "".join(f'<meta name="{key}" content="{html.escape(value, quote=True)}" />' for key, value in metas.items())
    head += "<!-- evsemmap_warp map viewer export: " + note.replace("--", "- -") + " -->"
    visible = ('<div id="evsemmap-frame-note" style="position:fixed;left:8px;bottom:8px;z-index:1000;'
               'pointer-events:none;font:12px sans-serif;background:rgba(255,255,255,0.8);padding:2px 6px;'
               f'border-radius:4px">{html.escape(note, quote=False)}</div>') + legend_html(viewer)
    page = viewer.server.get_scene_serializer().as_html()
    at = page.find("<head>")
    page = page[: at + 6] + head + page[at + 6:] if at >= 0 else head + page
    at = page.rfind("</body>")
    page = page[:at] + visible + page[at:] if at >= 0 else page + visible
    return write_text_atomically(Path(path), page)  # whole or not at all, errors naming the path


def write_ply(viewer, path) -> Path:
    """``MapViewer.export_ply``: the visible voxels of the shown maps as a binary PLY at ``path`` (below the
    evidence threshold only while the viewer shows them; ``evidence``: each voxel's, summed over classes)."""
    parts = [(i, viewer.voxels.visible_rows[i]) for i in viewer.comparison.shown_layers()]
    colors = np.concatenate([viewer.voxels.colors(i, r) for i, r in parts])
    fields = {"label": "label", "state": "state", "variance": "variance", "observations": "hits", "evidence": "evidence_sum"}
    vertex = np.zeros(len(colors), [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1"), ("alpha", "u1")] + [(name, "<f4") for name in fields])
    centers = np.concatenate([np.asarray(viewer.layers[i].centers[r], np.float64) for i, r in parts])
    for k, axis in enumerate("xyz"):
        vertex[axis] = centers[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = colors[:, k]
    vertex["alpha"] = 255
    for name, attribute in fields.items():
        vertex[name] = np.concatenate([getattr(viewer.layers[i], attribute)[r] for i, r in parts])

    def one_line(text: str) -> str:
        return " ".join(str(text).splitlines())

    frame = viewer.frame
    types = {"<f8": "double", "|u1": "uchar", "<f4": "float"}
    header = ["ply", "format binary_little_endian 1.0",
              "comment evsemmap_warp map viewer export: voxel centers, float64 world coordinates (m) of the frame below",
              f"comment frame {one_line(frame.name) if frame is not None else 'none'}",
              f"comment crs {(frame.crs if frame is not None else None) or 'none'}",
              f"element vertex {len(vertex)}"]
    header += [f"property {types[vertex.dtype[name].str]} {name}" for name in vertex.dtype.names]
    header.append("end_header")
    return write_bytes_atomically(Path(path), ("\n".join(header) + "\n").encode("utf-8") + vertex.tobytes())


def export_from_gui(viewer, kind: str, client=None) -> None:
    """The *Export* folder's buttons: ``kind`` "html" or "ply", written beside the first map shown, in the coloring
    of the tab that clicked (``client``)."""
    stem = viewer.export_dir / f"{viewer.layers[viewer.comparison.shown_layers()[0]].name}_view"
    with viewer.tabs.scene_colored_as(viewer.tabs.view_of(client)):
        path = write_html(viewer, stem.with_suffix(".html")) if kind == "html" else write_ply(viewer, stem.with_suffix(".ply"))
    viewer.gui_export_status.content = f"written: `{path}`"

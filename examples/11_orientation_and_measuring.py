"""Orientation and measuring in the viewer: the ground grid under the map, its lines on round world
coordinates labelled in meters of the map's frame; the scale bar (meters per pixel at the orbit center
of each browser's camera); what lies under the screen's center, followed as the camera moves (viser sends
no pointer moves, so this stands in for coordinates on hover); a click reporting the world coordinates
of the point it hits; and *Measure*,
two clicks giving the distance, the horizontal distance and the height difference. Maps a synthetic
drive and opens it; the same as ``evsemmap view MAP`` (the *Orientation and measuring* folder).

    python examples/11_orientation_and_measuring.py [--world tiny] [--out measure_example] [--port 8080] [--no-serve]
"""

import argparse
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from evsemmap_warp.apps.cli import main as evsemmap
from evsemmap_warp.apps.viewer import MapViewer
from evsemmap_warp.apps.viewer.orientation import metres_per_pixel, scale_bar_html
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="tiny", help="the synthetic world preset")
    parser.add_argument("--out", type=Path, default=Path("measure_example"))
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--no-serve", action="store_true", help="click two voxels with Measure on, print what the viewer says, and exit")
    args = parser.parse_args()

    generate_sequence(load_preset(args.world), args.out / "sequence", progress=False, camera=False)
    map_file = args.out / "map.npz"
    assert evsemmap(["map", str(args.out / "sequence"), "rellis3d", "--method", "ebs", "--out", str(map_file), "--quiet"]) == 0

    viewer = MapViewer([map_file], port=args.port)
    if not args.no_serve:
        print(f"open {viewer.url}: click a voxel for its world coordinates; tick Measure and click two points (Ctrl-C to stop)")
        viewer.serve_forever()
        return

    grid = viewer.ground
    labels = [text for text, _ in grid.labels]
    print(f"ground grid at z={grid.z:.2f} m: x {grid.x0:g}..{grid.x1:g} m, y {grid.y0:g}..{grid.y1:g} m, lines every {grid.section:g} m "
          f"(finer every {grid.cell:g} m); labels: " + ", ".join(labels))
    # the scale bar a browser window 720 pixels tall gets at the viewer's initial camera
    camera = viewer.server.initial_camera
    m_per_px = metres_per_pixel(camera.position, camera.look_at, camera.fov, 720)
    _, meters, pixels = scale_bar_html(m_per_px)
    print(f"scale bar at the initial camera: {meters:g} m drawn {pixels:.0f} px long ({m_per_px * 1000:.1f} mm per pixel)")

    layer = viewer.layers[0]
    rows = viewer.visible_rows[0]
    top = rows[np.argmax(layer.centers[rows, 2])]
    # a browser's camera moved to 20 m above the highest voxel, looking down at it (display coordinates, relative
    # to the local origin): the legend names what lies under the screen's center, in world coordinates
    look_at = layer.centers[top] - viewer.origin
    viewer.cameras.report(SimpleNamespace(position=look_at + [0.0, -0.1, 20.0], look_at=look_at, fov=camera.fov, image_height=720))
    while viewer.center_hit is None:  # picked off the camera's callback, on the viewer's own thread
        time.sleep(0.05)
    print(viewer.gui_view_center.content)

    # two clicks straight down, as a browser sends them: on the highest voxel, and on the top of the voxel column
    # farthest from it across the map
    far = rows[np.argmax(np.linalg.norm(layer.centers[rows, :2] - layer.centers[top, :2], axis=1))]
    column = rows[np.all(layer.voxel_index[rows, :2] == layer.voxel_index[far, :2], axis=1)]
    far = column[np.argmax(layer.centers[column, 2])]  # the voxel of that column a ray from above meets first
    viewer.gui_measure.value = True
    for row in (top, far):
        viewer.picking.click(layer.centers[row] - viewer.origin + [0.0, 0.0, 10.0], (0.0, 0.0, -1.0))
        print(viewer.gui_selection.content.splitlines()[0])
    print(viewer.gui_measure_result.content.split("\n\n")[0].replace("**", ""))
    a, b = viewer.measure_points
    # with numpy: each click lands on the top face of its voxel
    expected = [layer.centers[row] + [0.0, 0.0, layer.resolution / 2] for row in (top, far)]
    print("checked against numpy:", bool(np.allclose(a, expected[0]) and np.allclose(b, expected[1])
                                         and np.isclose(np.linalg.norm(b - a), np.linalg.norm(expected[1] - expected[0]))
                                         and np.isclose(b[2] - a[2], layer.centers[far, 2] - layer.centers[top, 2])))
    viewer.close()


if __name__ == "__main__":
    main()

"""View maps in the browser: S-BKI and S-CSM of the toy scans, side by side.

Maps the S-BKI toy scans with both methods (sbki compatibility mode), writes the two map files and
serves them with the viser viewer on http://127.0.0.1:8080: switch maps or show them side by side,
color by class, variance, mean input uncertainty or observation count, hide classes, click a voxel.

    python examples/02_view_map.py [--device cpu] [--port 8080] [--out-dir .] [--no-serve]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from evsemmap_warp import Mapper, load_config, open_dataset
from evsemmap_warp.apps.viewer import MapViewer

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--out-dir", type=Path, default=Path("."))
    parser.add_argument("--no-serve", action="store_true", help="build the viewer, export a standalone HTML, exit")
    args = parser.parse_args()

    paths = []
    for method in ("s-bki", "s-csm"):
        run = load_config([REPO / "configs/datasets/sbki_toy.yaml"], method=method)
        dataset = open_dataset(run.dataset)
        mapper = Mapper.for_dataset(dataset, run.mapping, device=args.device)  # its classes, in its world frame
        for scan in dataset:
            mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
        paths.append(args.out_dir / f"toy_{method}.npz")
        mapper.save(paths[-1])

    viewer = MapViewer(paths, port=args.port, style="points")
    viewer.gui_side_by_side.value = True
    if args.no_serve:
        print(f"wrote {viewer.export_html(args.out_dir / 'toy_maps.html')}")
        viewer.server.stop()
        return
    print(f"open {viewer.url} (Ctrl-C to stop)")
    viewer.serve_forever()


if __name__ == "__main__":
    main()

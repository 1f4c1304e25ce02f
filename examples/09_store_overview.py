"""A map store in the viewer at two levels of detail: a synthetic drive mapped by ``evsemmap batch`` into a
store of small tiles, opened with a small overview budget. The first frame comes from the tiles in the
middle, the rest of the overview fills in behind it, and a tile is shown in full when a camera comes
near it or a click lands on it; what the server holds is the overview and those tiles, never the store.
The same as ``evsemmap view STORE``.

    python examples/09_store_overview.py [--world tiny] [--out store_example] [--max-voxels 2000] [--port 8080] [--no-serve]
"""

import argparse
import time
from pathlib import Path
from types import SimpleNamespace

from evsemmap_warp.apps.cli import main as evsemmap
from evsemmap_warp.apps.viewer import MapViewer
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="tiny", help="the synthetic world preset")
    parser.add_argument("--out", type=Path, default=Path("store_example"))
    parser.add_argument("--max-voxels", type=int, default=2000, help="the overview's size")
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--no-serve", action="store_true", help="come near one tile, print what is held, and exit")
    args = parser.parse_args()

    generate_sequence(load_preset(args.world), args.out / "sequence", progress=False, camera=False)
    store = args.out / "store"
    assert evsemmap(["batch", str(args.out / "sequence"), "rellis3d", "--method", "ebs", "--out", str(store), "--tile-voxels", "32",
                     "--workers", "1", "--quiet"]) == 0

    started = time.perf_counter()
    viewer = MapViewer([store], port=args.port, max_voxels=args.max_voxels, store_first_voxels=20_000)
    overview = viewer.stores[0]
    print(f"first frame ready in {time.perf_counter() - started:.2f} s: {len(overview.parts)} of {len(overview.store.tiles)} tiles "
          f"read, {overview.total_voxels:,} voxels in the store")
    while not overview.complete:
        time.sleep(0.05)
    print(f"overview complete after {time.perf_counter() - started:.2f} s: {overview.held_rows:,} rows held")
    if args.no_serve:
        # a camera 3 m above the middle of the store: the tile column below it in full
        layer = viewer.layers[0]
        middle = (overview.bounds[0] + overview.bounds[1]) / 2 - viewer.origin
        middle[2] = float(layer.centers[:, 2].min()) - viewer.origin[2]
        viewer.tiles.approach(SimpleNamespace(position=middle + [0, -1.0, 3.0], look_at=middle))
        while "tile(s) in full" not in viewer.gui_status.content:  # read and drawn on the viewer's loader thread
            time.sleep(0.05)
        print(f"near the middle: tiles {', '.join(overview.detail)} in full, {overview.held_rows:,} rows held")
        print(viewer.gui_status.content)
        viewer.close()
    else:
        print(f"open {viewer.url}: zoom in on a tile, or click one, to see it in full (Ctrl-C to stop)")
        viewer.serve_forever()


if __name__ == "__main__":  # batch's worker processes import this file
    main()

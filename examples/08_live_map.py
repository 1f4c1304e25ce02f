"""Watching a map being made: maps a synthetic drive while the viewer serves it, the map updated every few
scans on the viewer's own thread (mapping only copies the voxel tables between updates, and not while the
viewer is still busy), and shows the map exactly as written once done. The same as
``evsemmap map SEQUENCE --method ebs --out MAP --view``.

    python examples/08_live_map.py [--world tiny] [--frames 12] [--every 3] [--out live_example] [--port 8080] [--no-serve]
"""

import argparse
from pathlib import Path

import numpy as np

from evsemmap_warp import Mapper, load_config
from evsemmap_warp.apps.scan_sources import open_scan_source
from evsemmap_warp.apps.viewer import MapLayer, MapViewer
from evsemmap_warp.apps.viewer.live import LiveMap, map_live
from evsemmap_warp.core.mapper import read_map_arrays
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="tiny", help="the synthetic world preset")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--every", type=int, default=3, help="scans between updates of the map shown")
    parser.add_argument("--out", type=Path, default=Path("live_example"))
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--no-serve", action="store_true", help="map, check the map shown against the file written, and exit")
    args = parser.parse_args()

    generate_sequence(load_preset(args.world, trajectory__frames=args.frames), args.out / "sequence", progress=False, camera=False)
    run = load_config([str(args.out / "sequence"), "rellis3d"], method="ebs")
    source = open_scan_source(run)
    mapper = Mapper.for_dataset(source, run.mapping)
    map_file = args.out / "map.npz"
    viewer = MapViewer([MapLayer.from_mapper("map", map_file, mapper)], port=args.port)   # serving before the first scan
    live = LiveMap(viewer, mapper, name="map", path=map_file, scan_total=len(source))
    print(f"open {viewer.url} to watch the map being made")
    map_live(mapper, source, live, every=args.every)
    mapper.save(map_file)
    shown = live.show_final()
    written, _ = read_map_arrays(map_file)
    print(f"{live.updates} updates while mapping {len(source)} scans; the mapping thread copied for {live.copy_seconds:.3f} s in all")
    print("the map shown is the map written:", all(np.array_equal(getattr(shown, k), written[k]) for k in ("voxel_index", "alpha", "label")))
    if args.no_serve:
        live.close()
        viewer.close()
    else:
        print("Ctrl-C to stop")
        viewer.serve_forever()


if __name__ == "__main__":  # batch's worker processes import this file
    main()

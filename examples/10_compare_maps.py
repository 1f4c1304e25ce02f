"""Compare two maps of one drive in the viewer: where their labels differ, and which one the ground truth agrees with.
Maps a synthetic drive twice, once from the camera's labels (alpha files standing in for a network's) and
once from the LiDAR's, projects the camera's labels onto the LiDAR points as the ground truth, and opens
both maps in the viewer's *Compare maps* folder: the voxels whose labels differ, colored by which map
agrees with the truth, with the counts; or every voxel the maps share, colored by its variance
difference (blue: the first map is surer, red: the second). The same as
``evsemmap view CAMERA_MAP LIDAR_MAP --truth project/ground_truth.npz``.

    python examples/10_compare_maps.py [--world tiny] [--out compare_example] [--port 8080] [--no-serve]
"""

import argparse
from pathlib import Path

import numpy as np

from evsemmap_warp.apps.cli import main as evsemmap
from evsemmap_warp.apps.viewer import MapViewer
from evsemmap_warp.apps.viewer.comparison import DIFF_COLORS, load_truth
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence, write_stand_in_alpha


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="tiny", help="the synthetic world preset")
    parser.add_argument("--out", type=Path, default=Path("compare_example"))
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--no-serve", action="store_true", help="show both comparisons, print their counts, and exit")
    args = parser.parse_args()

    sequence = args.out / "sequence"
    generate_sequence(load_preset(args.world), sequence, progress=False)
    # Alpha files stand in for a network's (`evsemmap infer`): evidence on each pixel's true class, weak on the
    # left half of the image, so that the camera's map and the LiDAR's differ.
    write_stand_in_alpha(sequence, args.out / "alpha")
    camera_map, lidar_map = args.out / "camera_ebs.npz", args.out / "lidar_sbki.npz"
    assert evsemmap(["map", str(sequence), "rellis3d", "--method", "ebs", "--alpha-dir", str(args.out / "alpha"), "--bin-frames", "1",
                     "--out", str(camera_map), "--quiet"]) == 0
    assert evsemmap(["map", str(sequence), "rellis3d", "--method", "s-bki", "--out", str(lidar_map), "--quiet"]) == 0
    assert evsemmap(["project", str(sequence), "--out", str(args.out / "project"), "--overlays", "0"]) == 0
    truth = args.out / "project" / "ground_truth.npz"

    viewer = MapViewer([camera_map, lidar_map], port=args.port, truth=truth)
    viewer.gui_diff.value = "labels differ"  # the first map is the one chosen in "Map", the second in "Second map"
    if not args.no_serve:
        print(f"open {viewer.url}: the Compare maps folder's Show picks the comparison (Ctrl-C to stop)")
        viewer.serve_forever()
        return
    diff = viewer.comparison.diff()
    counts = diff.counts()
    print(f"{counts['compared']:,} voxels in both maps; labels differ in {counts['differ']:,}; "
          f"{len(viewer.visible_rows[0]):,} of them drawn (occupied and known in the first map)")
    for name in DIFF_COLORS:
        print(f"  {name}: {counts[name]:,}")
    print(f"where the truth says ({counts['with truth']:,} voxels): the camera's map is right in {counts['first map right']:,}, "
          f"the LiDAR's in {counts['second map right']:,}")
    # the same counts from the map files' arrays, with numpy
    first, second = viewer.layers
    at = second.voxel_at(first.centers)
    both = np.flatnonzero(at >= 0)
    a, b = first.label[both].astype(int), second.label[at[both]].astype(int)
    t = load_truth(truth, first, viewer.frame)[both]
    differ, known = a != b, t >= 0
    expected = [int((differ & known & (a == t)).sum()), int((differ & known & (b == t)).sum()),
                int((differ & known & (a != t) & (b != t)).sum()), int((differ & ~known).sum())]
    print("the counts checked against numpy:", expected == [counts[name] for name in DIFF_COLORS]
          and int(differ.sum()) == counts["differ"])

    viewer.gui_diff.value = "variance difference"
    difference = diff.variance_difference
    print(f"variance difference (first minus second) over {len(difference):,} voxels: the camera's map surer in "
          f"{int((difference < 0).sum()):,}, the LiDAR's in {int((difference > 0).sum()):,}; checked against numpy: "
          f"{bool(np.allclose(difference, first.variance[both] - second.variance[at[both]]))}")
    print(viewer.gui_diff_status.content.splitlines()[-1])
    viewer.close()


if __name__ == "__main__":
    main()

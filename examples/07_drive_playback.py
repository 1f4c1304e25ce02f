"""Drive playback: where a map's voxels came from. Maps a synthetic drive, then plays it back in the viewer:
a time slider over the scans, the robot's pose and the scan (by label or input uncertainty), the camera
image with the labels and uncertainty that labelled it, and the map as it stood after each scan (an
incremental replay of the integration, from snapshots every few scans). The same as
``evsemmap view MAP --drive SEQUENCE``.

    python examples/07_drive_playback.py [--world tiny] [--out playback_example] [--port 8080] [--no-serve]
"""

import argparse
from pathlib import Path

from evsemmap_warp.apps.cli import main as evsemmap
from evsemmap_warp.apps.viewer import MapViewer
from evsemmap_warp.apps.viewer.drive import DrivePlayback, open_drive
from evsemmap_warp.synthetic.preset import load_preset
from evsemmap_warp.synthetic.writer import generate_sequence, write_stand_in_alpha


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="tiny", help="the synthetic world preset")
    parser.add_argument("--out", type=Path, default=Path("playback_example"))
    parser.add_argument("--port", type=int, default=8080)
    parser.add_argument("--no-serve", action="store_true", help="step through the drive, print what each scan shows, and exit")
    args = parser.parse_args()

    sequence = args.out / "sequence"
    generate_sequence(load_preset(args.world), sequence, progress=False)
    # Alpha files stand in for a network's (`evsemmap infer`): evidence on each pixel's true class, weak on the
    # left half of the image, so that the uncertainty image and the scan's uncertainty show something.
    write_stand_in_alpha(sequence, args.out / "alpha")
    map_file = args.out / "map.npz"
    assert evsemmap(["map", str(sequence), "rellis3d", "--method", "ebs", "--alpha-dir", str(args.out / "alpha"), "--bin-frames", "1",
                     "--out", str(map_file), "--quiet"]) == 0

    drive, replay = open_drive(map_file, [sequence, "rellis3d"], alpha_dir=args.out / "alpha", bin_frames=1, snapshot_every=2)
    viewer = MapViewer([map_file], port=args.port)
    playback = DrivePlayback(viewer, drive, replay)
    if not args.no_serve:
        print(f"open {viewer.url}: the Drive folder's slider picks a scan (Ctrl-C to stop)")
        viewer.serve_forever()
    else:
        for scan in range(len(drive)):
            playback.show(scan)
            assert playback.wait_until_drawn(scan), playback.errors
            layer = viewer.layers[0]
            print(f"after scan {scan + 1} of {len(drive)}: {len(layer.state):,} voxels, the robot at "
                  + ", ".join(f"{v:.1f}" for v in drive.poses[scan][:3, 3]) + " m")
        playback.precompute = True
        while not playback.replay_check:
            playback.show(len(drive) - 1)
            playback.wait_until_drawn(len(drive) - 1)
        print(playback.replay_check)
        playback.close()
        viewer.close()


if __name__ == "__main__":  # batch's worker processes import this file
    main()

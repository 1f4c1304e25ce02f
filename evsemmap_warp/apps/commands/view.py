"""``evsemmap view``: inspect map files and map stores in a browser (viser)."""

from __future__ import annotations

import sys
from pathlib import Path

from .args import port, positive, positive_float


def add_parser(sub) -> None:
    """Add ``view`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("view", help="inspect map files and map stores in a browser (viser)")
    p.add_argument("maps", nargs="+", type=Path, help="map files or stores (a store: a decimated overview, any tile in full); several "
                                                      "are switchable or side by side, only when their world frames agree")
    p.add_argument("--same-frame", action="store_true", help="maps of one run frame (e.g. odom) whose runs differ or are unknown are "
                                                             "shown in one frame (docs/formats.md, the frame's run)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=port, default=8080)
    p.add_argument("--style", choices=("points", "boxes"), default="points", help="voxels as point sprites or instanced boxes")
    p.add_argument("--max-voxels", type=positive, default=500_000, help="decimate beyond this many visible voxels (the GUI can show all)")
    p.add_argument("--trajectory", type=Path, help="poses.txt (3x4 per line) or N x 3 positions (.txt/.npy), read as world "
                                                   "coordinates of the maps' frame")
    p.add_argument("--scan", type=Path, help="current scan's points (.pcd, .npy or KITTI .bin), read as world coordinates of "
                                             "the maps' frame (not the sensor frame)")
    p.add_argument("--export-html", type=Path, help="write a standalone HTML of the scene: positions relative to the local "
                                                    "origin, whose world coordinates and frame the page states")
    p.add_argument("--export-ply", type=Path, help="write the visible voxels as a PLY point cloud: float64 world coordinates "
                                                   "of the maps' frame, named in the header")
    p.add_argument("--export-dir", type=Path, help="folder for the GUI's export buttons (default: beside the first map)")
    p.add_argument("--layers", action="store_true", help="compute each map's terrain layers at start and draw one as a colored "
                                                         "height surface (the GUI's button does it on demand otherwise; docs/terrain.md)")
    p.add_argument("--layers-resolution-m", type=positive_float, default=None, help="terrain cell edge (m; default: the voxel size)")
    p.add_argument("--costs", type=Path, default=None, help="the terrain layers' cost table YAML (default: configs/terrain/costs_v3.yaml); "
                   "its layers.min_evidence is also the evidence threshold below which voxels are hidden")
    p.add_argument("--truth", type=Path, default=None, help="ground truth for comparing two maps: `evsemmap project`'s ground_truth.npz "
                                                            "(points, labels) or a map file; differing voxels are colored by which map "
                                                            "agrees with it")
    p.add_argument("--drive", nargs="+", metavar="SOURCE", help="play back the drive the map was made from: its sequence folder or "
                                                                  "robot log (with the presets it needs), labelled as when mapping "
                                                                  "(--checkpoint, --alpha-dir, --bin-frames); a time slider shows the pose, "
                                                                  "the scan, the camera and the map as it stood after each scan")
    p.add_argument("--checkpoint", type=Path, help="with --drive: the segmentation checkpoint that labelled the map's scans")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="with --drive: the folder of alpha files that labelled the map's scans")
    p.add_argument("--bin-frames", type=positive, default=None, help="with --drive and --checkpoint or --alpha-dir: frames per insertion, "
                                                                    "as when mapping")
    p.add_argument("--snapshot-every", type=positive, default=10, help="with --drive: keep a copy of the replayed map every N scans "
                                                                      "(a scrub replays at most N scans)")
    p.add_argument("--no-serve", action="store_true", help="export and exit instead of serving")
    p.set_defaults(func=run)


def _refuse_unreadable_tiles(viewer) -> None:
    """An export holds every tile of its stores or is not written: a tile the viewer could not read (serving, it says
    so in its status line and shows the rest) stops it, in the one line naming the tile that ``evsemmap export`` says."""
    from ...core.map_store import StoreError

    for overview in viewer.stores.values():
        for name, exc in overview.unreadable.items():
            viewer.close()
            if isinstance(exc, (ValueError, OSError)):  # the store's own refusals, and the OS's: they name the file
                raise exc
            raise StoreError(f"{overview.store.path}: tile {name} could not be read ({type(exc).__name__}: {exc})") from None


def run(args) -> int:
    """Serve map files and stores in a browser (viser), or export their scene (``--no-serve``)."""
    from ...files import check_not_inside
    from ...frames import describe_frame
    from ..viewer import MapViewer, check_address

    read = [*args.maps, *(args.drive or []), *(p for p in (args.truth, args.trajectory, args.scan, args.costs, args.checkpoint, args.alpha_dir)
                                               if p is not None)]
    for flag, path in (("--export-html", args.export_html), ("--export-ply", args.export_ply)):
        if path is not None:
            check_not_inside(path, read, f"view {flag}")  # never over a map given, nor inside a store
    drive = None
    if args.drive:
        from ...core.map_store import is_store
        from ..viewer.drive import open_drive

        if len(args.maps) != 1 or is_store(args.maps[0]):
            raise ValueError(f"--drive plays back the drive of one map file (.npz), got {' '.join(map(str, args.maps))}")
        check_address(args.host, args.port)  # before the drive is read and checked
        drive = open_drive(args.maps[0], args.drive, checkpoint=args.checkpoint, alpha_dir=args.alpha_dir, bin_frames=args.bin_frames,
                           snapshot_every=args.snapshot_every)
    else:
        for flag, value in (("--checkpoint", args.checkpoint), ("--alpha-dir", args.alpha_dir), ("--bin-frames", args.bin_frames)):
            if value is not None:
                raise ValueError(f"{flag} labels the scans of a --drive: give --drive too")
    from ...core.map_store import MapStore, is_store

    for path in args.maps:  # a folder that is not (yet) a store: MapStore names why, e.g. a batch run still writing it
        if path.is_dir() and not is_store(path):
            MapStore(path)
    viewer = MapViewer(args.maps, host=args.host, port=args.port, style=args.style, max_voxels=args.max_voxels,
                       trajectory=args.trajectory, scan=args.scan, export_dir=args.export_dir, terrain=args.layers,
                       terrain_resolution=args.layers_resolution_m, costs=args.costs, truth=args.truth, same_frame=args.same_frame)
    if args.export_html is not None or args.export_ply is not None:
        viewer.wait_for_stores()  # a store's whole overview, not its first frame's tiles
        _refuse_unreadable_tiles(viewer)
    for path, export in ((args.export_html, viewer.export_html), (args.export_ply, viewer.export_ply)):
        if path is not None:
            print(f"wrote {export(path)}", file=sys.stderr)
    if args.no_serve:
        viewer.close()
        return 0
    if drive is not None:
        from ..viewer.drive import DrivePlayback

        DrivePlayback(viewer, *drive)
    print(f"evsemmap viewer: open {viewer.url} in a browser (Ctrl-C to stop); maps in {describe_frame(viewer.frame)}, "
          f"local origin at {viewer.origin_text()}", file=sys.stderr)
    viewer.serve_forever()
    return 0

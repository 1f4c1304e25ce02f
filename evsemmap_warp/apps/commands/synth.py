"""``evsemmap synth``: generate a synthetic off-road sequence in the RELLIS-3D layout."""

from __future__ import annotations

import json
from pathlib import Path

from .args import positive


def add_parser(sub) -> None:
    """Add ``synth`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("synth", help="generate a synthetic off-road sequence in the RELLIS-3D layout")
    p.add_argument("--world", default="default", help="the world preset: tiny, demo, default, long (a 2 km drive) or a YAML file "
                                                      "(configs/synthetic/)")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to write")
    p.add_argument("--domain", default=None, help="appearance domain (summer, autumn, dusk); default: the preset's")
    p.add_argument("--seed", type=int, default=None, help="world seed; default: the preset's")
    p.add_argument("--frames", type=positive, default=None, help="number of frames; default: the preset's")
    p.add_argument("--device", default="cpu", help="Warp device for the ray casting")
    p.add_argument("--format", choices=("folder", "rosbag1", "rosbag2", "mcap"), default="folder",
                   help="folder: the RELLIS-3D layout (default); rosbag1: a ROS 1 .bag; rosbag2: a ROS 2 bag folder (sqlite3); "
                        "mcap: a bare .mcap file (logs need the [ros] extra)")
    p.add_argument("--no-camera", action="store_true", help="LiDAR scans with point labels and poses only: no images (fast)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """Generate a synthetic sequence in the RELLIS-3D layout, or as a robot log."""
    from ...synthetic.preset import load_preset
    from ...synthetic.writer import generate_sequence

    import shutil
    import tempfile

    from ...files import error_naming

    preset = load_preset(args.world, seed=args.seed, appearance__domain=args.domain, trajectory__frames=args.frames)
    if args.format == "folder":
        created = not args.out.exists()
        try:
            summary = generate_sequence(preset, args.out, device=args.device, progress=not args.quiet, camera=not args.no_camera)
        except OSError as exc:  # a full disk: numpy's short write names no file
            if created:  # no half-written sequence left behind
                shutil.rmtree(args.out, ignore_errors=True)
            raise error_naming(exc, args.out, "writing the sequence") from None
        print(json.dumps({"out": str(args.out), **summary}, indent=1))
        return 0

    from ...data.log_writer import write_log

    if args.out.exists():
        raise ValueError(f"{args.out} exists already; a log is written to a new path")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    # the frames are rendered in the folder layout beside the log, then streamed into it frame by frame
    staging = Path(tempfile.mkdtemp(prefix=f".{args.out.name}-frames-", dir=args.out.parent))
    try:
        summary = generate_sequence(preset, staging, device=args.device, progress=not args.quiet, camera=not args.no_camera)
        written = write_log(staging, args.out, args.format, progress=not args.quiet)
    except OSError as exc:  # name the log asked for, not the staging folder (write_log removed what it wrote)
        raise error_naming(exc, args.out, "writing the log") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(json.dumps({"out": str(args.out), **summary, **written}, indent=1))
    return 0

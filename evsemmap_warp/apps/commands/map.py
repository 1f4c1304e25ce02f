"""``evsemmap map``: map a dataset with a method and write the map file."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ...config import ConfigError, available_methods, load_config
from .args import MAX_MEMORY, MAX_MEMORY_HELP, add_frame_args, port, positive


def add_parser(sub) -> None:
    """Add ``map`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("map", help="map a dataset with a method and write the map file")
    p.add_argument("configs", nargs="+", help="dataset / preset YAML files, merged in order (later wins)")
    p.add_argument("--method", required=True, help=f"method name ({', '.join(available_methods())}) or a method YAML file")
    p.add_argument("--out", required=True, type=Path, help="map file to write (.npz)")
    p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--workers", type=positive, default=None, help="CPU threads, each scattering into its own map shard (default: up to 2 on the CPU)")
    p.add_argument("--max-memory", type=MAX_MEMORY, default=None, metavar="SIZE", help=MAX_MEMORY_HELP)
    p.add_argument("--checkpoint", type=Path, help="label the scans from the camera with this segmentation checkpoint "
                                                   "(evsemmap train-seg) instead of their per-point labels")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="label the scans from the camera with the per-image alpha files "
                                                                   "`evsemmap infer` wrote into this folder (NAME.npy per image, or "
                                                                   "NNNNNN.npy per frame)")
    p.add_argument("--bin-frames", type=positive, default=None, help="with --checkpoint or --alpha-dir: frames integrated together "
                                                                    "(default: the preset's pipeline.bin_frames, else 1)")
    p.add_argument("--batch-size", type=positive, default=4, help="with --checkpoint: images per inference batch")
    add_frame_args(p)
    p.add_argument("--view", action="store_true", help="serve the map in a browser while it is made (viser), updated every "
                                                      "--view-every scans, and the map as written once done (until Ctrl-C)")
    p.add_argument("--view-every", type=positive, default=None, help="with --view: scans between updates of the map shown (default 10)")
    p.add_argument("--host", default=None, help="with --view: address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=port, default=None, help="with --view: port to serve on (default 8080)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or start-up line")
    p.set_defaults(func=run)


def run(args) -> int:
    """Map a dataset with a method into a map file (``--view``: watch it being made); prints the run's JSON report."""
    from tqdm import tqdm

    from ...core.mapper import Mapper, VoxelState, save_map
    from ..scan_sources import map_scans, open_scan_source

    resolved = load_config(args.configs, method=args.method, frame=args.frame, crs=args.crs)
    if resolved.dataset is None:
        raise ConfigError(f"none of {list(args.configs)} has a 'dataset' section: name a dataset config, e.g. configs/datasets/sbki_toy.yaml")
    from ...files import check_not_inside

    data = resolved.dataset.resolve_logs() if resolved.dataset.kind == "bag" else [resolved.dataset.resolve_path()]
    # never over a log, a config file or a checkpoint, nor into a sequence folder or the alpha files
    read = [*resolved.sources, *data, *(p for p in (args.checkpoint, args.alpha_dir) if p is not None)]
    check_not_inside(args.out, read, "map --out")
    dataset = open_scan_source(resolved, checkpoint=args.checkpoint, alpha_dir=args.alpha_dir, bin_frames=args.bin_frames, batch_size=args.batch_size)
    mapper = Mapper.for_dataset(dataset, resolved.mapping, device=args.device, workers=args.workers, max_memory=args.max_memory)
    live = None
    if args.view:
        live = _live_viewer(args, mapper, len(dataset))
    elif (args.host, args.port, args.view_every) != (None, None, None):
        raise ConfigError("--host, --port and --view-every serve the map while it is made: give --view too")
    if not args.quiet:
        what = f"{len(dataset)} bins of camera-labelled frames" if args.checkpoint or args.alpha_dir else f"{len(dataset)} scans"
        print(f"mapping {what} with {resolved.mapping.method} ({resolved.mapping.compat.value} mode) on {mapper.device}, "
              f"{len(mapper.shards)} worker(s), in {dataset.frame.describe()}", file=sys.stderr)
    start = time.perf_counter()
    try:
        with tqdm(total=len(dataset), unit="scan", disable=args.quiet, dynamic_ncols=True) as bar:
            # Reading and host work of the next scans overlap this one's kernels; errors name their scan.
            if live is None:
                stats = map_scans(mapper, dataset, progress=lambda scan, _: bar.update(1))
            else:
                from ..viewer.live import map_live

                stats = map_live(mapper, dataset, live, every=args.view_every or 10, progress=lambda scan, _: bar.update(1))
    except BaseException:
        if live is not None:
            live.close()
            live.viewer.close()
        raise
    elapsed = time.perf_counter() - start
    points = sum(s.input_points for s in stats)
    save_map(args.out, mapper)
    counts = mapper.state_counts()
    summary = mapper.voxels().summary
    occupied = summary.state == VoxelState.OCCUPIED
    per_class = np.bincount(summary.label[occupied], minlength=mapper.num_classes)
    report = {
        "method": resolved.mapping.method,
        "frame": dataset.frame.as_dict(),
        "scans": len(dataset),
        "input_points": points,
        "voxels": mapper.voxel_count,
        "states": counts,
        "occupied_by_class": {name: int(c) for name, c in zip(mapper.class_names, per_class) if c},
        "mapping_seconds": round(elapsed, 3),  # reading the scans and mapping them (overlapped)
        "input_points_per_second": round(points / elapsed) if elapsed > 0 else None,
        "map_file": str(args.out),
    }
    print(json.dumps(report, indent=1))
    if live is not None:
        live.show_final()  # the map as written, read out as the file holds it
        print(f"evsemmap viewer: {live.viewer.url} shows the map as written to {args.out} (Ctrl-C to stop)", file=sys.stderr)
        live.viewer.serve_forever()
        live.close()
    return 0


def _live_viewer(args, mapper, scan_total: int):
    """The browser view of a map being made (``map --view``), serving before the first scan."""
    from ..viewer import MapLayer, MapViewer
    from ..viewer.live import LiveMap

    viewer = MapViewer([MapLayer.from_mapper(args.out.stem, args.out, mapper)], host=args.host or "127.0.0.1", port=args.port or 8080)
    live = LiveMap(viewer, mapper, name=args.out.stem, path=args.out, scan_total=scan_total)
    print(f"evsemmap viewer: open {viewer.url} in a browser to watch the map being made (updated every {args.view_every or 10} scans)",
          file=sys.stderr)
    return live

"""``evsemmap batch``: map long sequences on every core (or a Ray cluster) into a tiled map store; resumable."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ... import limits
from ...config import ConfigError, available_methods
from .args import CHUNK_FRAMES, MAX_MEMORY, MAX_MEMORY_HELP, TILE_VOXELS, add_frame_args, port, positive, positive_float


def add_parser(sub) -> None:
    """Add ``batch`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("batch", help="map long sequences on every core (or a Ray cluster) into a tiled map store; resumable")
    p.add_argument("configs", nargs="+", help="sequences (folders, robot logs, dataset configs: each one input, mapped in order into one map) "
                                              "and the presets / configs they share")
    p.add_argument("--method", required=True, help=f"method name ({', '.join(available_methods())}) or a method YAML file")
    p.add_argument("--out", required=True, type=Path, help="the map store (a folder) to write, or to finish when a run was interrupted")
    p.add_argument("--executor", choices=("local", "ray"), default="local", help="local: a process pool (default); ray: Ray tasks")
    p.add_argument("--workers", type=positive, default=None, help="worker processes (default: one per core; with ray: the cluster's CPUs)")
    p.add_argument("--fold-workers", type=positive, default=None, help="tiles folded at once, each tile's chunks still in order (default: "
                   "one lane per 6 workers, threads of the driver; with ray, when given or more than one: lanes on the nodes, each "
                   "holding the tiles dealt to it)")
    p.add_argument("--max-memory", type=MAX_MEMORY, default=None, metavar="SIZE", help=MAX_MEMORY_HELP)
    p.add_argument("--chunk-frames", type=CHUNK_FRAMES, default=None,
                   help="frames per task, rounded to whole bins (default: automatic, from the inputs' total frames only: "
                        "ceil(frames / 16), at most 100: at least 16 chunks when the frames allow, two per worker up to 8 workers; "
                        "never from the worker count, so stores are the same for any; the JSON summary gives the value and rule)")
    p.add_argument("--ray-address", default=None, help="an existing Ray cluster: auto, ray://host:port, or its head's host:port (with RAY_AUTH_MODE=token for token authentication, Ray's default; default: a local Ray instance)")
    p.add_argument("--ray-connect-timeout-s", type=positive_float, default=limits.RAY_CONNECT_TIMEOUT_S, metavar="S",
                   help="with --ray-address host:port: seconds it may take to accept a connection before the run is refused "
                        f"(default {limits.RAY_CONNECT_TIMEOUT_S:g})")
    p.add_argument("--same-frame", action="store_true", help="the inputs' run frames (e.g. odom) are one run's, a drive cut into several "
                                                             "logs: runs that differ or are unknown are mapped together (docs/formats.md)")
    p.add_argument("--chunk-timeout-s", type=positive_float, default=limits.CHUNK_TIMEOUT_S, metavar="S",
                   help=f"stop when no chunk finishes for this long, as a stuck worker or node (default {limits.CHUNK_TIMEOUT_S:g}; "
                        "the chunks mapped are kept)")
    p.add_argument("--checkpoint", type=Path, help="label the scans from the camera with this segmentation checkpoint (inference in each task)")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="label the scans from the camera with the alpha files of `evsemmap infer` "
                                                                   "in this folder")
    p.add_argument("--bin-frames", type=positive, default=None, help="with --checkpoint or --alpha-dir: frames per insertion (default: the preset's)")
    p.add_argument("--batch-size", type=positive, default=4, help="with --checkpoint: images per inference batch")
    p.add_argument("--tile-voxels", type=TILE_VOXELS, default=256, help=f"tile edge in voxels, 1..{limits.MAX_TILE_VOXELS} (default 256: 51.2 m at 0.2 m)")
    p.add_argument("--discard-partials", action="store_true", help="delete STORE/work (the run's plan and chunk records; partial maps are deleted as they are folded) at the end: a rerun then starts over")
    add_frame_args(p)
    p.add_argument("--view", action="store_true", help="serve the store's overview in a browser while it is made (viser): tiles fill in "
                                                      "as chunks finish; then the overview as written (until Ctrl-C)")
    p.add_argument("--host", default=None, help="with --view: address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=port, default=None, help="with --view: port to serve on (default 8080)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress messages (errors are still reported); the JSON summary still goes to stdout")
    p.set_defaults(func=run)


def run(args) -> int:
    """Map the inputs into a map store on every core or a Ray cluster (``--view``: watch its tiles fill in); prints the run's JSON summary."""
    from ..batch import BatchOptions, run_batch

    options = BatchOptions(method=args.method, out=args.out, executor=args.executor, workers=args.workers, chunk_frames=args.chunk_frames,
                           ray_address=args.ray_address, checkpoint=args.checkpoint, alpha=args.alpha_dir, bin_frames=args.bin_frames,
                           batch_size=args.batch_size, tile_voxels=args.tile_voxels, discard_partials=args.discard_partials,
                           progress=not args.quiet, frame=args.frame, crs=args.crs, max_memory=args.max_memory,
                           ray_connect_timeout_s=args.ray_connect_timeout_s, chunk_timeout_s=args.chunk_timeout_s,
                           same_frame=args.same_frame, fold_workers=args.fold_workers)
    if args.ray_address and args.executor != "ray":
        raise ConfigError("--ray-address needs --executor ray")
    if not args.view and (args.host, args.port) != (None, None):
        raise ConfigError("--host and --port serve the store while it is made: give --view too")
    live = _live_tiles(args, options) if args.view else None
    try:
        summary = run_batch(list(args.configs), options, log=(lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr)),
                            on_tile=live)
    except BaseException:
        if live is not None:
            live.close()
            live.viewer.close()
        raise
    print(json.dumps(summary, indent=1))
    if live is not None:
        live.wait_idle()
        print(f"evsemmap viewer: {live.viewer.url} shows the store's overview as written to {args.out} (Ctrl-C to stop; "
              f"`evsemmap view {args.out}` shows any tile in full)", file=sys.stderr)
        live.viewer.serve_forever()
        live.close()
    return 0


def _live_tiles(args, options):
    """The browser view of a store being made (``batch --view``): its tiles fill in as chunks are folded into them."""
    from ...core.mapper import Mapper
    from ..batch import plan_batch
    from ..viewer import MapLayer, MapViewer
    from ..viewer.live import LiveTiles

    _, sources, config, _, _ = plan_batch(list(args.configs), options)  # the store's classes, frame and parameters
    template = Mapper.for_dataset(sources[0], config, workers=1)
    viewer = MapViewer([MapLayer.from_mapper(args.out.name, args.out, template)], host=args.host or "127.0.0.1", port=args.port or 8080)
    live = LiveTiles(viewer, template, name=args.out.name, path=args.out, max_voxels=500_000)
    print(f"evsemmap viewer: open {viewer.url} in a browser to watch the store's tiles fill in", file=sys.stderr)
    return live

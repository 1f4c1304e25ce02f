"""``evsemmap live`` and ``evsemmap replay``: their flags and what they run (docs/robot.md)."""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path

from ..config import ConfigError, available_methods, load_config
from .ros2_wire import KEY_FORMATS
from .session import ZenohOptions


def _zenoh_args(p) -> None:
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="a Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (the robot's router or a peer); repeatable")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="a Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7448; repeatable")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE", help="a Zenoh config file (JSON5); the flags above go on top")
    p.add_argument("--mode", choices=("peer", "client"), default="peer", help="Zenoh session mode (default peer)")
    p.add_argument("--multicast", action="store_true", help="find peers by UDP multicast scouting (off by default: it reaches the whole network segment)")
    p.add_argument("--domain-id", type=int, default=0, help="the ROS domain id (ROS_DOMAIN_ID; default 0)")


def add_parsers(sub, *, positive, positive_float, port) -> None:
    """Add ``live`` and ``replay`` to the ``evsemmap`` subparsers (``positive`` ...: the command line's argument types)."""
    p = sub.add_parser("live", help="map a ROS 2 robot's scans as they arrive over Zenoh (rmw_zenoh, or a DDS robot's Zenoh bridge) and "
                                    "publish the map back")
    p.add_argument("configs", nargs="+", help="dataset configs or presets that name the topics and frames, as for a log (e.g. rellis3d rellis3d-bag)")
    p.add_argument("--method", required=True, help=f"method name ({', '.join(available_methods())}) or a method YAML file")
    p.add_argument("--out", type=Path, required=True, help="map file (.npz) written when the run ends (Ctrl-C, --duration, --max-scans, --idle-exit)")
    _zenoh_args(p)
    p.add_argument("--key-format", choices=("auto",) + KEY_FORMATS, default="auto",
                   help="rmw_zenoh (<domain>/<topic>/<type>/<hash>), bridge (zenoh-bridge-ros2dds: the topic name alone) or auto "
                        "(default: both subscribed, the first sample decides; the map is published back in that format)")
    p.add_argument("--queue", type=positive, default=8, help="scans waiting to be mapped; when full, the oldest is dropped and counted (default 8)")
    p.add_argument("--tf-wait", type=float, default=0.5, metavar="S", help="how long a scan waits for its pose before it is dropped (default 0.5 s)")
    p.add_argument("--topic-timeout", type=positive_float, default=5.0, metavar="S", help="say which topics are silent after this long (default 5 s)")
    p.add_argument("--on-time-jump", choices=("refuse", "reset"), default="refuse",
                   help="time running back (a looping replay, a restarted robot): refuse (drop the older scans, default) or reset "
                        "(write the map so far as OUT.N.npz and start a new one)")
    p.add_argument("--max-cloud-mb", type=positive_float, default=256.0, help="a larger cloud is dropped before it is queued (default 256)")
    p.add_argument("--map-period", type=float, default=1.0, metavar="S", help="publish the map cloud every S seconds (0: never; default 1)")
    p.add_argument("--grid-period", type=float, default=2.0, metavar="S", help="publish GridMap and OccupancyGrid every S seconds (0: never; default 2)")
    p.add_argument("--window", type=positive_float, default=40.0, metavar="M", help="side of the terrain layers' square around the robot (default 40 m)")
    p.add_argument("--no-publish", action="store_true", help="map only: publish nothing back")
    p.add_argument("--max-scans", type=positive, default=None, help="stop after this many scans mapped")
    p.add_argument("--idle-exit", type=positive_float, default=None, metavar="S", help="stop when no scan came for S seconds, once one was mapped")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--workers", type=positive, default=None, help="CPU threads scattering into map shards (default: up to 2 on the CPU)")
    p.add_argument("--checkpoint", type=Path, default=None, help="label the scans from the camera with this segmentation checkpoint, as "
                                                                 "evsemmap map --checkpoint does (dataset.bag.image_topic, camera_info_topic)")
    p.add_argument("--bin-frames", type=positive, default=None, help="with --checkpoint: frames integrated together (default: the preset's "
                                                                     "pipeline.bin_frames, else 1)")
    p.add_argument("--store", type=Path, default=None, metavar="DIR", help="keep the map as a map store (the batch format) in DIR, "
                   "rewritten every --store-every seconds and at the end (Ctrl-C too); an existing store is resumed")
    p.add_argument("--store-every", type=positive_float, default=30.0, metavar="S", help="with --store: seconds between writes (default 30)")
    p.add_argument("--report", type=Path, default=None, help="also write the final report (counts, latencies) to this JSON file")
    p.add_argument("--view", action="store_true", help="show the map in a browser while it is made (the live viewer)")
    p.add_argument("--view-every", type=positive, default=10, help="with --view: scans between updates (default 10)")
    p.add_argument("--host", default="127.0.0.1", help="with --view: address to serve on (default 127.0.0.1)")
    p.add_argument("--port", type=port, default=8080, help="with --view: port (default 8080)")
    p.set_defaults(func=run_live)

    p = sub.add_parser("replay", help="publish a recorded log (ROS 1, ROS 2, MCAP) over Zenoh as its robot would, with /clock")
    p.add_argument("logs", nargs="+", type=Path, help="the log: a .bag, .mcap or .db3 file, or a ROS 2 bag folder")
    _zenoh_args(p)
    p.add_argument("--key-format", choices=KEY_FORMATS, default="rmw_zenoh", help="rmw_zenoh (default, with liveliness tokens) or bridge")
    p.add_argument("--rate", type=float, default=1.0, help="a factor of the recorded rate (default 1; 0: as fast as possible)")
    p.add_argument("--loops", type=positive, default=1, help="play the log this many times (its time jumps back each time)")
    p.add_argument("--topics", nargs="+", default=(), help="publish only these topics (default all)")
    p.add_argument("--wait-subscribers", type=float, default=3.0, metavar="S", help="wait up to S seconds for subscribers before the "
                                                                                  "first message (default 3; 0: start at once)")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run_replay)


def _options(args) -> ZenohOptions:
    return ZenohOptions(connect=list(args.connect), listen=list(args.listen), config_file=args.zenoh_config, mode=args.mode,
                        multicast=args.multicast)


def _stop_on_signals(stop: threading.Event):
    """Ctrl-C (SIGINT) and SIGTERM end a run after the scan being mapped (never halfway through one), and the map is
    written; a second Ctrl-C interrupts at once. Returns what puts the previous handlers back."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def ending(signum, frame):
        if stop.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop.set()

    previous = {sig: signal.signal(sig, ending) for sig in (signal.SIGTERM, signal.SIGINT)}
    return lambda: [signal.signal(sig, handler) for sig, handler in previous.items()]


def run_replay(args) -> int:
    """``evsemmap replay``."""
    from .replay import replay_log
    from .session import open_session

    if args.domain_id < 0:
        raise ConfigError(f"--domain-id {args.domain_id}: a ROS domain id is >= 0")
    session = open_session(_options(args))
    stop = threading.Event()
    restore_signals = _stop_on_signals(stop)
    try:
        stats = replay_log(session, args.logs, rate=args.rate, topics=tuple(args.topics), key_format=args.key_format,
                           domain_id=args.domain_id, loops=args.loops, clock=not args.no_clock, stop=stop,
                           wait_for_subscribers_s=max(args.wait_subscribers, 0.0))
    finally:
        restore_signals()
        session.close()
    if not args.quiet:
        print(json.dumps({"messages": stats.messages, "log_seconds": round(stats.log_seconds, 3), "wall_seconds": round(stats.wall_seconds, 3),
                          "late_seconds_max": round(stats.late_seconds_max, 3)}, indent=1))
    return 0


def _live_run(args):
    """(the run config, the LiveSettings) of ``evsemmap live``'s arguments; ConfigError for what they cannot be."""
    from ..files import check_not_inside
    from .mapping import LiveSettings

    run = load_config(list(args.configs), method=args.method)
    if run.dataset is None or run.dataset.kind != "bag":
        raise ConfigError(f"{' '.join(args.configs)}: live mapping reads a robot's topics as a log's: name a dataset config or preset of kind "
                          f"bag (e.g. rellis3d-bag) that says them")
    if args.domain_id < 0:
        raise ConfigError(f"--domain-id {args.domain_id}: a ROS domain id is >= 0")
    settings = LiveSettings(tf_wait_s=args.tf_wait, topic_timeout_s=args.topic_timeout, on_time_jump=args.on_time_jump,
                            max_scans=args.max_scans, idle_exit_s=args.idle_exit, duration_s=args.duration)
    check_not_inside(args.out, list(run.sources), "live --out")
    if args.store is not None:
        check_not_inside(args.store, list(run.sources), "live --store")
    return run, settings


def _labeller(args, run, store):
    """The camera labeller of ``--checkpoint``, or None."""
    if args.checkpoint is not None:
        from .camera import CameraLabeller

        return CameraLabeller(args.checkpoint, run.dataset.bag, store, bin_frames_=args.bin_frames or run.bin_frames)
    if args.bin_frames is not None:
        raise ConfigError("--bin-frames applies to camera-labelled scans (--checkpoint)")
    return None


class _FollowingView:
    """``--view``: the browser viewer of the live map, offered every ``--view-every``-th mapped scan (``on_mapped``)."""

    def __init__(self, args):
        self.args, self.live_view = args, None

    def on_mapped(self, mapping, scan) -> None:
        if not self.args.view:
            return
        if self.live_view is None or self.live_view.mapper is not mapping.mapper:
            self.close()  # a new map (time ran back, --on-time-jump reset): the old map's server ends, its port freed
            self.live_view = _live_view(self.args, mapping.mapper)
        if mapping.stats.mapped % self.args.view_every == 0:
            self.live_view.offer(mapping.stats.mapped, scan)

    def close(self) -> None:
        if self.live_view is not None:
            self.live_view.close()
            self.live_view.viewer.close()
            self.live_view = None


def _mapping(args, run, settings, session, feed, queue, store, view: _FollowingView, labeller):
    """The LiveMapping of the run, publishing unless ``--no-publish``, writing ``--store`` when given."""
    from .mapping import LiveMapping
    from .node import Ros2Node
    from .publish import MapPublisher
    from .store import LiveStore

    def node(detected_format: str):
        return Ros2Node(session, "evsemmap_live", key_format=detected_format if args.key_format == "auto" else args.key_format,
                        domain_id=args.domain_id, store=store)

    def publisher(mapper, node):
        return MapPublisher(node, mapper, map_period_s=args.map_period, grid_period_s=args.grid_period, window_m=args.window)

    live_store = None if args.store is None else LiveStore(args.store, every_s=args.store_every, sources=list(args.configs))
    try:
        return LiveMapping(run, feed, queue, settings, out=args.out, device=args.device, workers=args.workers,
                           node_factory=None if args.no_publish else node, publisher_factory=None if args.no_publish else publisher,
                           on_mapped=view.on_mapped, store=live_store, labeller=labeller)
    except BaseException:
        if live_store is not None:
            live_store.close()
        raise


def _map_until_stopped(mapping, stop: threading.Event):
    """Map until ``stop`` or the run's end, then write the map: what ``LiveMapping.finish`` wrote (None: no scan).
    A run stopped by an error (a memory budget that no longer holds) writes the map made so far, then raises."""
    from .feed import say

    try:
        mapping.run_until_stopped(stop)
    except Exception as exc:
        if mapping.mapper is not None:
            say(f"stopped: {exc}; writing the map made so far")
            mapping.finish()
        raise
    if stop.is_set():
        say("interrupted: writing the map")
    return mapping.finish()


def run_live(args) -> int:
    """``evsemmap live``."""
    from .feed import RobotFeed, say
    from .ros2_wire import typestore
    from .scan_queue import ScanQueue
    from .session import open_session, zenoh_module

    zenoh_module()  # the install line before anything else
    run, settings = _live_run(args)
    store = typestore()
    session = open_session(_options(args))
    stop = threading.Event()
    restore_signals = _stop_on_signals(stop)
    queue = ScanQueue(args.queue)
    view = _FollowingView(args)
    feed = mapping = None
    try:
        labeller = _labeller(args, run, store)
        feed = RobotFeed(session, run.dataset.bag, queue, store, key_format=args.key_format, domain_id=args.domain_id,
                         max_cloud_bytes=int(args.max_cloud_mb * 2**20), labeller=labeller)
        mapping = _mapping(args, run, settings, session, feed, queue, store, view, labeller)
        topics = ", ".join(f"{t} ({s.msgtype.rsplit('/', 1)[-1]})" for t, s in feed.topics.items())
        say(f"listening for {topics} on domain {args.domain_id} ({args.key_format} keys); Ctrl-C ends the run and writes {args.out}")
        written = _map_until_stopped(mapping, stop)
    finally:
        if mapping is not None:
            mapping.close()
        view.close()
        if feed is not None:
            feed.close()
        if mapping is not None and mapping.node is not None:
            mapping.node.close()
        session.close()
        restore_signals()
    _report(args, run, mapping, None if mapping is None else mapping.store)
    if written is None:
        say(f"no scan was mapped, so no map was written to {args.out}")
        return 1
    return 0


def _report(args, run, mapping, live_store) -> None:
    """The run's final report (counts, latencies, files) on stdout, and in ``--report`` when given."""
    from ..core.mapper import VoxelState

    report = mapping.diagnostics() | {"method": run.mapping.method, "map_files": [str(p) for p in mapping.maps_written],
                                      "store": None if live_store is None else str(live_store.path),
                                      "mapping_seconds": round(mapping.stats.mapping_s, 3)}
    if mapping.mapper is not None:
        report["voxels"] = mapping.mapper.voxel_count
        report["occupied"] = int((mapping.mapper.voxels().summary.state == VoxelState.OCCUPIED).sum())
    print(json.dumps(report, indent=1))
    if args.report is not None:
        args.report.write_text(json.dumps(report, indent=1) + "\n")


def _live_view(args, mapper):
    from ..apps.viewer import MapLayer, MapViewer
    from ..apps.viewer.live import LiveMap

    viewer = MapViewer([MapLayer.from_mapper(args.out.stem, args.out, mapper)], host=args.host, port=args.port)
    print(f"evsemmap viewer: open {viewer.url} in a browser to watch the live map", file=sys.stderr)
    return LiveMap(viewer, mapper, name=args.out.stem, path=args.out)

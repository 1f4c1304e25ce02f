"""``evsemmap live``'s mapping loop: scans from the ``ScanQueue``, posed by the TF tree the ``RobotFeed``
fills, labelled and placed as the log source does (``logs.cloud_points``, ``datasets.labelled_scan``), in
the world frame a log gets (the root of the LiDAR's TF tree, or ``dataset.bag.fixed_frame``), integrated
one at a time; the map published back (``MapPublisher``), written to ``--out`` at the end.

What a robot does to a mapper, each said in one line and counted in the diagnostics:

- a scan whose pose is not known yet (TF late) waits up to ``tf_wait_s``, then is dropped (``no_pose``);
  a scan older than the first transform is dropped at once;
- time jumping back (a looping replay, a restarted robot): ``refuse`` drops the scans stamped before the
  last one mapped (``time_jump``); ``reset`` writes the map so far next to ``--out`` (``NAME.1.npz``, ...),
  forgets the moving transforms stamped after the scan (the old timeline's) and starts a new map;
- a cloud that does not decode (``malformed``), is too large (``too_large``, before queueing), or a message
  of another type on a topic (refused by the feed);
- mapping falling behind: the queue drops its oldest scans (``queue_full``);
- a topic nothing arrives on within ``topic_timeout_s``: said, and waited for (the robot may start later).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import ConfigError, RunConfig
from ..core.mapper import Mapper, save_map
from ..data.datasets import label_table, labelled_scan
from ..data.logs import CLOUD_TYPE, cloud_points
from ..data.ros_messages import header_stamp_ns
from ..data.sequences import DataError, remap_point_labels
from ..frames import WorldFrame, is_run_frame_name, run_id
from ..geometry.transform_tree import TransformError, format_stamp
from .feed import RobotFeed, say
from .scan_queue import ReceivedScan, ScanQueue

DROP_REASONS = ("queue_full", "no_pose", "no_image", "time_jump", "malformed", "too_large")
TIME_JUMP_POLICIES = ("refuse", "reset")


@dataclass
class LiveSettings:
    """How long to wait for what, and when to stop (None: never; Ctrl-C ends a run too)."""

    tf_wait_s: float = 0.5
    topic_timeout_s: float = 5.0
    on_time_jump: str = "refuse"
    max_scans: int | None = None  # stop after this many scans mapped
    idle_exit_s: float | None = None  # stop when no scan came for this long, once one was mapped
    duration_s: float | None = None
    diagnostics_period_s: float = 1.0

    def __post_init__(self) -> None:
        if self.on_time_jump not in TIME_JUMP_POLICIES:
            raise ConfigError(f"--on-time-jump {self.on_time_jump!r}: {' or '.join(TIME_JUMP_POLICIES)}")
        if not (self.tf_wait_s >= 0 and self.topic_timeout_s > 0):
            raise ConfigError(f"--tf-wait {self.tf_wait_s} must be >= 0 and --topic-timeout {self.topic_timeout_s} > 0 (seconds)")


def percentiles(values_ms: list[float]) -> dict[str, float | None]:
    """p50, p95, p99 and max of latencies (ms), None when there are none."""
    if not values_ms:
        return {"p50": None, "p95": None, "p99": None, "max": None}
    a = np.asarray(values_ms, np.float64)
    return {"p50": round(float(np.percentile(a, 50)), 2), "p95": round(float(np.percentile(a, 95)), 2),
            "p99": round(float(np.percentile(a, 99)), 2), "max": round(float(a.max()), 2)}


@dataclass
class LiveStats:
    """Counts and latencies of a run: integrated = sent -> in the map; published = sent -> first map message holding it."""

    mapped: int = 0
    dropped: dict[str, int] = field(default_factory=lambda: {r: 0 for r in DROP_REASONS})
    integrated_ms: list[float] = field(default_factory=list)
    published_ms: list[float] = field(default_factory=list)
    mapping_s: float = 0.0  # time spent decoding, posing and integrating (not waiting)
    # where a mapped scan's time goes (ms): decode (CDR -> points and labels), place (pose lookup, into the world
    # frame), integrate (the Mapper); waiting for its pose is not in them
    stage_ms: dict[str, list[float]] = field(default_factory=lambda: {"decode": [], "place": [], "integrate": []})


class LiveMapping:
    """Maps what ``feed`` receives with ``run``'s mapping method into a Mapper (made at the first posed scan,
    in its world frame); ``node_factory(key_format)`` gives the ROS 2 node publishing back in the robot's key
    format, ``publisher_factory(mapper, node)`` the MapPublisher (None: publish nothing)."""

    def __init__(self, run: RunConfig, feed: RobotFeed, queue: ScanQueue, settings: LiveSettings, *, out: Path | None = None,
                 device: str = "cpu", workers: int | None = None, node_factory=None, publisher_factory=None, on_mapped=None, store=None,
                 labeller=None):
        dataset = run.dataset
        if dataset.frame == "first-scan":
            raise ConfigError("dataset.frame: first-scan is a frame of a log's first scan; a live map is made in the robot's fixed frame "
                              "(dataset.bag.fixed_frame, default the root of the LiDAR's TF tree)")
        if dataset.bag.lidar_extrinsic or dataset.bag.camera_extrinsic:
            raise ConfigError("dataset.bag.lidar_extrinsic / camera_extrinsic: live mapping takes the mounts from the robot's /tf_static")
        self.run, self.feed, self.queue, self.settings, self.out = run, feed, queue, settings, out
        self.bag = dataset.bag
        self.labeller = labeller  # a camera.CameraLabeller (--checkpoint), or None: the clouds' own labels
        if labeller is not None:
            self.table, self.class_names, self.num_classes = None, labeller.class_names, labeller.num_classes
        else:
            self.table, names = label_table(self.bag.label_ontology, dataset.num_classes)
            self.class_names = dataset.class_names or names
            self.num_classes = dataset.num_classes or len(self.class_names)
        self.device, self.workers = device, workers
        # node_factory(key_format) -> Ros2Node: made once the robot's key format is known (or the topics' wait is over)
        self.node, self._node_factory = None, node_factory
        self.publisher_factory, self.on_mapped = publisher_factory, on_mapped
        self.store = store  # a LiveStore (--store), or None
        self.resumed = store.resume(run) if store is not None else None
        self.stats = LiveStats()
        self.mapper: Mapper | None = None
        self.publisher = None
        self.frame: WorldFrame | None = None
        self.lidar_frame = self.bag.lidar_frame
        self.last_stamp: int | None = None
        self.robot_xy = np.zeros(2)
        self.maps_written: list[Path] = []
        self._pending: list[int] = []  # origin_ns of scans mapped but not yet in a published map
        self._binned: list[int] = []  # origin_ns of scans taken but not integrated yet (a bin still filling)
        self._pending_lock = threading.Lock()
        self._jump_said = False
        queue.on_drop = self._queue_drop

    # Dropping -------------------------------------------------------------------------------------
    def _queue_drop(self, scan: ReceivedScan, total: int) -> None:
        self.stats.dropped["queue_full"] = total
        if total == 1 or total % 100 == 0:
            say(f"mapping falls behind: the queue of {self.queue.capacity} scans is full, the oldest scan was dropped "
                f"({total} dropped so far)")

    def _drop(self, reason: str, text: str | None) -> None:
        self.stats.dropped[reason] += 1
        if text is not None:
            say(f"{text}; dropped ({self.stats.dropped[reason]} {reason.replace('_', ' ')} so far)")

    # Posing ---------------------------------------------------------------------------------------
    def _pose(self, stamp: int) -> tuple[str, np.ndarray | str]:
        """("ok", pose) / ("wait", why) / ("never", why) for a scan stamped ``stamp``."""
        with self.feed.tree_lock:
            tree = self.feed.tree
            if self.lidar_frame not in tree.frames:
                return "wait", f"the LiDAR frame {self.lidar_frame!r} is in no TF tree yet (frames so far: {sorted(tree.frames) or 'none'})"
            fixed = self.frame.name if self.frame is not None else (self.bag.fixed_frame or tree.root(self.lidar_frame))
            try:
                up_lidar, up_fixed = tree.chain(fixed, self.lidar_frame)
            except TransformError as exc:
                return "wait", str(exc)
            moving = [f for f in up_lidar[:-1] + up_fixed[:-1] if tree.is_timed(f)]
            if not moving and self.frame is None:
                return "wait", (f"the LiDAR's chain {' -> '.join(reversed(up_lidar))} holds no moving transform yet (a pose source: "
                                f"{self.bag.tf_topic!r} or the odometry)")
            for f in moving:
                start, end = tree.time_range(f)
                if stamp < start:
                    return "never", f"the transform {tree.parent(f)!r} -> {f!r} starts at {format_stamp(start)}, after the scan"
                if stamp > end:
                    return "wait", f"the transform {tree.parent(f)!r} -> {f!r} is known up to {format_stamp(end)} only"
            if self.frame is None:
                self.frame = self._world_frame(fixed)
            return "ok", tree.lookup(fixed, self.lidar_frame, stamp)

    def _world_frame(self, fixed: str) -> WorldFrame:
        tree = self.feed.tree
        moving = is_run_frame_name(fixed) or fixed in self.feed.odometry_frames or any(tree.is_timed(f) for f in tree.path_to_root(fixed)[:-1])
        return WorldFrame(fixed, self.run.dataset.crs or None, self._first_run_id if moving else None)

    def _wait_for_pose(self, stamp: int, where: str) -> np.ndarray | None:
        deadline = time.monotonic() + self.settings.tf_wait_s
        while True:
            status, value = self._pose(stamp)
            if status == "ok":
                return value
            if status == "never" or time.monotonic() >= deadline:
                late = "" if status == "never" else f" after waiting {self.settings.tf_wait_s:g} s (--tf-wait)"
                self._drop("no_pose", f"{where}: no pose in the fixed frame{late}: {value}")
                return None
            time.sleep(0.002)

    # Mapping --------------------------------------------------------------------------------------
    def _check_time(self, stamp: int, where: str) -> bool:
        """False when the scan is to be dropped for time running back; a reset starts a new map here."""
        if self.last_stamp is None or stamp > self.last_stamp:
            self._jump_said = False
            return True
        back = (self.last_stamp - stamp) / 1e9
        if self.settings.on_time_jump == "reset" and self.mapper is not None:
            written = self._finish_map(reset=True)
            self.feed.trim(after_ns=stamp)  # the old timeline's transforms
            say(f"{where}: time jumped back {back:.3f} s (a looping replay or a restarted robot): the map so far is written to "
                f"{written}, a new map starts (--on-time-jump reset)")
            return True
        text = None
        if not self._jump_said:
            text = (f"{where}: time jumped back {back:.3f} s from the last scan mapped ({format_stamp(self.last_stamp)}; a looping "
                    f"replay or a restarted robot): scans stamped before it are dropped (--on-time-jump refuse); restart evsemmap live, "
                    f"or give --on-time-jump reset, to map the new run")
            self._jump_said = True
        self._drop("time_jump", text)
        return False

    def map_scan(self, item: ReceivedScan) -> bool:
        """Decode, pose, label and integrate one received cloud; returns whether it was mapped (with --checkpoint:
        taken into the bin being filled, integrated when the bin is full)."""
        started = time.perf_counter()
        decoded = self._decode(item)
        if decoded is None:
            return False
        stamp, where, scan, labels = decoded
        wait_started = time.perf_counter()
        pose = self._wait_for_pose(stamp, where)
        if pose is None:
            return False
        pose_wait = time.perf_counter() - wait_started
        placed, image_wait = self._label_and_place(stamp, where, scan, labels, pose)
        if placed is False:
            return False
        waited = pose_wait + image_wait
        placed_at = time.perf_counter()
        with self._pending_lock:
            self._binned.append(item.origin_ns)
        if placed is not None:
            self._integrate(placed)
        stages = self.stats.stage_ms
        stages["decode"].append((wait_started - started) * 1e3)
        stages["place"].append((placed_at - wait_started - waited) * 1e3)
        stages["integrate"].append((time.perf_counter() - placed_at) * 1e3)
        self.last_stamp = stamp
        self.feed.trim(before_ns=stamp)
        self.stats.mapped += 1
        self.stats.mapping_s += time.perf_counter() - started - waited
        return True

    def _decode(self, item: ReceivedScan):
        """(stamp, name, scan [N, 4], class labels or None) of a received cloud; None when it is dropped."""
        topic = self.bag.cloud_topic
        try:
            stamp = header_stamp_ns(item.cdr, True) if len(item.cdr) >= 12 else None
            msg = self.feed.store.deserialize_cdr(item.cdr, CLOUD_TYPE)
        except Exception as exc:  # noqa: BLE001 - rosbags raises assorted errors for bytes that are no PointCloud2
            self._drop("malformed", f"{topic}: a message that is no PointCloud2 ({type(exc).__name__}: {exc})")
            return None
        where = f"{topic} scan at {format_stamp(stamp)}"
        if not self._check_time(stamp, where):
            return None
        if not self.lidar_frame:
            self.lidar_frame = msg.header.frame_id
        if self.mapper is None:
            self._first_run_id = run_id(str(stamp), item.cdr)
        try:
            if self.labeller is not None:
                return stamp, where, cloud_points(msg, None, where)[0], None
            scan, raw_labels = cloud_points(msg, self.bag.label_field, where)
            return stamp, where, scan, remap_point_labels(raw_labels, self.table, f"{where} field {self.bag.label_field!r}")
        except (DataError, ConfigError) as exc:
            self._drop("malformed", str(exc))
            return None

    def _label_and_place(self, stamp: int, where: str, scan, labels, pose):
        """(the insertion for the map, or None while a bin fills, or False when the scan is dropped; the seconds spent
        waiting for its image)."""
        if self.mapper is None:
            self._start_map()
        if self.labeller is None:
            return labelled_scan(where, scan, labels, pose), 0.0
        image_wait = time.perf_counter()
        try:
            paired = self.labeller.image_for(stamp, time.monotonic() + self.settings.tf_wait_s)
        except DataError as exc:  # an image that does not decode: this scan goes, not the run
            self._drop("no_image", f"{where}: {exc}")
            return False, time.perf_counter() - image_wait
        waited = time.perf_counter() - image_wait
        if paired is None:
            self._drop("no_image", f"{where}: no image on {self.bag.image_topic!r} within {self.bag.image_tolerance_s:g} s "
                                   f"(dataset.bag.image_tolerance_s)")
            return False, waited
        try:
            with self.feed.tree_lock:
                camera, lidar_to_camera = self.labeller.camera(self.feed.tree, self.lidar_frame, stamp)
        except DataError as exc:
            self._drop("no_image", f"{where}: {exc}")
            return False, waited
        return self.labeller.add_frame(where, scan, pose, paired[0], camera, lidar_to_camera), waited

    def _integrate(self, placed) -> None:
        """Integrate one insertion (a scan, or a bin of camera-labelled frames); its scans' latencies counted."""
        self.mapper.integrate_many([placed])
        done_ns = time.time_ns()
        self.robot_xy = placed.sensor_origin[:2]
        with self._pending_lock:
            binned, self._binned = self._binned, []
            self._pending += binned
        self.stats.integrated_ms += [(done_ns - origin) / 1e6 for origin in binned]
        if self.on_mapped is not None:
            self.on_mapped(self, placed)

    def _start_map(self) -> None:
        resumed, self.resumed = self.resumed, None
        if resumed is not None:
            if resumed.frame is None or resumed.frame.name != self.frame.name:
                raise ConfigError(f"--store {self.store.path}: a map in {resumed.frame.describe() if resumed.frame else 'no frame'}, the "
                                  f"robot's is {self.frame.describe()}; give a new folder")
            self.frame = resumed.frame  # resuming continues the store's drive: its run too
        self.mapper = Mapper.for_dataset(self, self.run.mapping, device=self.device, workers=self.workers)
        if resumed is not None:
            self.mapper.load_voxels(resumed.voxels().arrays, origin_index=resumed.origin_index)
            self.mapper.scans_integrated, self.mapper.points_integrated = resumed.scans_integrated, resumed.points_integrated
            self.mapper.scan_ids = resumed.scan_ids
            say(f"resuming the store {self.store.path}: {resumed.scans_integrated} scans, {resumed.voxel_count} voxels")
        say(f"mapping {self.bag.cloud_topic} with {self.run.mapping.method} in {self.frame.describe()} (the LiDAR frame "
            f"{self.lidar_frame!r})")
        if self.publisher_factory is not None:
            if self.publisher is not None:
                self.publisher.close()
            self.publisher = self.publisher_factory(self.mapper, self.ensure_node(force=True))
            self.publisher.on_published = self._published

    def _published(self, kind: str, scans: int, wall_ns: int) -> None:
        if kind != "map":
            return
        with self._pending_lock:
            done, self._pending = self._pending[:scans], self._pending[scans:]
        self.stats.published_ms += [(wall_ns - origin) / 1e6 for origin in done]

    def _offer(self, *, force: bool = False) -> None:
        if self.store is not None:
            self.store.offer(self.mapper, force=force)
        if self.publisher is not None and self.mapper is not None:
            with self._pending_lock:
                pending = len(self._pending)
            self.publisher.offer(self.mapper, self.robot_xy, self.last_stamp or 0, pending, force=force)

    # The loop -------------------------------------------------------------------------------------
    def diagnostics(self) -> dict:
        """What the diagnostics message and the final report say."""
        s = self.stats
        return {"scans_received": self.queue.received + self.feed.too_large, "scans_mapped": s.mapped,
                "scans_dropped": sum(s.dropped.values()) + self.feed.too_large - s.dropped["too_large"],
                **{f"dropped_{r}": (self.feed.too_large if r == "too_large" else n) for r, n in s.dropped.items()},
                "queued": len(self.queue), **{f"integrated_latency_ms_{k}": v for k, v in percentiles(s.integrated_ms).items()},
                **{f"published_latency_ms_{k}": v for k, v in percentiles(s.published_ms).items()},
                **{f"{stage}_ms_p50": percentiles(times)["p50"] for stage, times in s.stage_ms.items()},
                "refused_messages": sum(t.refused for t in self.feed.topics.values()) - self.feed.too_large,
                "key_format": self.feed.detected_format or "none yet", "frame": self.frame.name if self.frame else "none yet"}

    def run_until_stopped(self, stop: threading.Event) -> None:
        """Map until ``stop`` is set, or a limit of the settings is reached; Ctrl-C ends it as well."""
        s = self.settings
        started = last_scan = time.monotonic()
        next_diagnostics, silence_said = started, False
        while not stop.is_set():
            now = time.monotonic()
            if s.duration_s is not None and now - started >= s.duration_s:
                break
            if now >= next_diagnostics and self.ensure_node(force=now - started >= s.topic_timeout_s) is not None:
                self._publish_diagnostics()
                next_diagnostics = now + s.diagnostics_period_s
            item = self.queue.get(timeout=0.05)
            if item is None:
                silent = self.feed.silent_topics()
                if silent and not silence_said and now - started >= s.topic_timeout_s:
                    known = self._topics_seen()
                    say(f"nothing on {silent} after {s.topic_timeout_s:g} s (--topic-timeout){known}; waiting for the robot "
                        f"(check the topic names, --domain-id, --key-format and the endpoints)")
                    silence_said = True
                if s.idle_exit_s is not None and self.stats.mapped and now - last_scan >= s.idle_exit_s:
                    break
                self._offer()
                continue
            last_scan = now
            self.map_scan(item)
            self._offer()
            if s.max_scans is not None and self.stats.mapped >= s.max_scans:
                break

    def _topics_seen(self) -> str:
        session = getattr(self.feed, "session", None)
        if session is None:
            return ""
        from .ros2_wire import ADMIN_SPACE, parse_token

        topics = set()
        try:
            for reply in session.liveliness().get(f"{ADMIN_SPACE}/{self.feed.domain_id}/**", timeout=1.0):
                token = parse_token(str(reply.ok.key_expr)) if reply.ok is not None else None
                if token is not None and token["kind"] == "MP" and token["node"] != "evsemmap_live":  # not what this run publishes
                    topics.add(f"{token['topic']} ({token['msgtype']})")
        except Exception:  # noqa: BLE001 - listing the graph is a courtesy; the line above says what is missing either way
            return ""
        return f"; topics published on domain {self.feed.domain_id}: {sorted(topics) or 'none'}"

    def ensure_node(self, *, force: bool = False):
        """The node publishing back, made in the key format the robot speaks (``force``: rmw_zenoh's when that is
        not known yet); None without a node_factory, or while the format is not known and not ``force``."""
        if self.node is None and self._node_factory is not None and (self.feed.detected_format or force):
            self.node = self._node_factory(self.feed.detected_format or "rmw_zenoh")
        return self.node

    def _publish_diagnostics(self) -> None:
        from .publish import DIAGNOSTICS_TOPIC, diagnostics_message

        values = self.diagnostics()
        level = 1 if values["scans_dropped"] or self.feed.silent_topics() else 0
        message = "mapping" if self.stats.mapped else "waiting for " + ", ".join(self.feed.silent_topics() or ["a posed scan"])
        self.node.publish_message(DIAGNOSTICS_TOPIC, diagnostics_message(self.feed.store, values, time.time_ns(), level=level, message=message))

    def finish(self) -> Path | None:
        """After the loop: the last map published, the map written to ``out``; returns its path (None: no scan mapped)."""
        if self.ensure_node(force=True) is not None:
            self._publish_diagnostics()
        return self._finish_map(reset=False)

    def _finish_map(self, *, reset: bool) -> Path | None:
        if self.mapper is None:
            return None
        last_bin = self.labeller.flush() if self.labeller is not None else None
        if last_bin is not None:  # the frames of a bin not full yet: integrated as the log's last, short bin is
            self._integrate(last_bin)
        workers = [w for w in (self.publisher, self.store) if w is not None]
        for worker in workers:
            worker.wait_idle(timeout=60.0)
        self._offer(force=True)
        for worker in workers:
            if not worker.wait_idle(timeout=600.0):
                say(f"{type(worker).__name__}: still busy after 600 s; ending without it")
        path = None
        if self.out is not None:
            path = self.out.with_name(f"{self.out.stem}.{len(self.maps_written) + 1}{self.out.suffix}") if reset else self.out
            save_map(path, self.mapper)
            self.maps_written.append(path)
        if reset:
            self.mapper, self.frame, self.last_stamp = None, None, None
        return path

    def close(self) -> None:
        """Stop the publishing and store threads."""
        for worker in (self.publisher, self.store):
            if worker is not None:
                worker.close()

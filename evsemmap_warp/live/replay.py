"""``evsemmap replay LOG``: a recorded log published over Zenoh as its robot would, at its recorded rate
(or a factor of it), with ``/clock`` (the log time), so that ``evsemmap live`` (or any ROS 2 tool on
Zenoh) can be tried without a robot. ROS 2 logs (bag folders, .db3, .mcap) are forwarded byte for byte;
a ROS 1 bag's messages are rewritten as their ROS 2 types (the header's ``seq`` dropped, CameraInfo's
``K`` as ``k``, ...)."""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from pathlib import Path

from ..config import ConfigError
from ..data.logs import open_reader
from ..data.sequences import DataError
from .node import Ros2Node
from .ros2_wire import is_latched, typestore

CLOCK_TOPIC = "/clock"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"


def ros2_message(msg, store):
    """A ROS 1 message (as rosbags decodes it) as the ROS 2 message of the same type in ``store``: fields taken
    by name (or its upper-case ROS 1 spelling), the ones ROS 2 dropped left out."""
    if not hasattr(msg, "__msgtype__"):
        return [ros2_message(v, store) for v in msg] if isinstance(msg, list) else msg
    cls = store.types[msg.__msgtype__]
    values = {}
    for f in dataclasses.fields(cls):
        if f.name.startswith("__") or f.name == "structure_needs_at_least_one_member":
            continue
        value = getattr(msg, f.name) if hasattr(msg, f.name) else getattr(msg, f.name.upper())
        values[f.name] = ros2_message(value, store)
    return cls(**values)


@dataclasses.dataclass
class ReplayStats:
    """What a replay sent: messages per topic, the log time covered, and how far behind its schedule it fell."""

    messages: dict[str, int]
    log_seconds: float
    wall_seconds: float
    late_seconds_max: float


def replay_log(session, logs, *, rate: float = 1.0, topics: tuple[str, ...] = (), key_format: str = "rmw_zenoh", domain_id: int = 0,
               loops: int = 1, clock: bool = True, stop: threading.Event | None = None, on_message=None,
               wait_for_subscribers_s: float = 0.0, linger_s: float = 0.3) -> ReplayStats:
    """Publish the messages of ``logs`` on ``session`` in log-time order, ``rate`` times as fast as recorded
    (0: as fast as possible), ``loops`` times over (the log time jumping back each time, as a looping replay
    does); ``topics``: only these (default all). ``on_message(topic, log_time_ns)`` after each message.
    Samples wait for the network rather than being dropped. ``wait_for_subscribers_s``: wait up to this long for
    subscribers first (``Ros2Node.wait_for_subscribers``); ``linger_s``: after the last message, before the
    publishers go, for the network to deliver it."""
    if rate < 0:
        raise ConfigError(f"--rate {rate}: a factor of the recorded rate, >= 0 (0: as fast as possible)")
    logs = [Path(p) for p in logs]
    reader = open_reader(logs)
    store = typestore()
    node = Ros2Node(session, "evsemmap_replay", key_format=key_format, domain_id=domain_id, store=store, block=True)
    try:
        connections = [c for c in reader.connections if not topics or c.topic in topics]
        missing = sorted(set(topics) - {c.topic for c in connections})
        if missing:
            raise DataError(f"{', '.join(map(str, logs))}: no topic {missing} in the log; its topics: {sorted({c.topic for c in reader.connections})}")
        unknown = sorted({c.msgtype for c in connections if c.msgtype not in store.types})
        if unknown:
            print(f"evsemmap replay: not published (types unknown to rosbags' ROS 2 store): {unknown}", file=sys.stderr)
            connections = [c for c in connections if c.msgtype in store.types]
        for c in connections:
            node.advertise(c.topic, c.msgtype, latched=is_latched(c.topic))
        if clock:
            node.advertise(CLOCK_TOPIC, CLOCK_TYPE)
        counts = {c.topic: 0 for c in connections}
        if wait_for_subscribers_s > 0 and not node.wait_for_subscribers(wait_for_subscribers_s):
            print(f"evsemmap replay: no subscriber after {wait_for_subscribers_s:g} s (--wait-subscribers); publishing anyway", file=sys.stderr)
        started, late = time.perf_counter(), 0.0
        first = last = None
        for _ in range(loops):
            if stop is not None and stop.is_set():
                break
            first_this_loop, loop_start = None, time.perf_counter()
            for connection, log_time, raw in reader.messages(connections=connections):
                if stop is not None and stop.is_set():
                    break
                first_this_loop = log_time if first_this_loop is None else first_this_loop
                first = log_time if first is None else first
                last = log_time
                if rate > 0:
                    due = loop_start + (log_time - first_this_loop) / 1e9 / rate
                    wait = due - time.perf_counter()
                    if wait > 0:
                        if stop is not None and stop.wait(wait):  # Ctrl-C within a long gap of the log ends it now
                            break
                        if stop is None:
                            time.sleep(wait)
                    else:
                        late = max(late, -wait)
                if clock:
                    stamp = store.types["builtin_interfaces/msg/Time"](sec=log_time // 10**9, nanosec=log_time % 10**9)
                    node.publish_message(CLOCK_TOPIC, store.types[CLOCK_TYPE](clock=stamp))
                if reader.is2:
                    node.publish(connection.topic, bytes(raw), connection.msgtype)
                else:
                    node.publish_message(connection.topic, ros2_message(reader.deserialize(raw, connection.msgtype), store))
                counts[connection.topic] += 1
                if on_message is not None:
                    on_message(connection.topic, log_time)
        wall = time.perf_counter() - started
        time.sleep(linger_s)
        return ReplayStats(counts, 0.0 if first is None else (last - first) / 1e9, wall, late)
    finally:
        node.close()
        reader.close()

"""Live mapping benchmark on this machine: a synthetic drive (LiDAR only, point labels), written as a ROS 2 bag,
replayed at its recorded rate (10 Hz) or a factor of it and mapped live with ``--method ebs`` on the CPU.

Runs, each a fresh ``evsemmap live`` in this process and, for the network ones, ``evsemmap replay`` in a second
process (the robot), both Zenoh peers on 127.0.0.1 (explicit endpoints, no multicast):

1. ``network+publish``: the drive at 10 Hz over Zenoh, the map cloud published every second and the terrain
   layers every two (the defaults); ``network+publish/5s``: both every five seconds;
2. ``network``: the same without publishing back;
3. ``direct``: no network: the bag's messages handed to the subscriber callback on the recorded schedule;
4. ``sweep``: the network run at other rates (``--sweep`` factors of the recorded rate), for the highest rate
   mapped with no scan dropped and the drop share above it.

Per run: scans received, mapped and dropped; latency from a scan's sending to its integration in the map (p50,
p95, p99) and, when publishing, to the first map message holding it; where a scan's time goes (decode, place,
integrate: median ms); the busy share of the scan period (mapping time per scan / period: above 1 it cannot keep
up). The figures go to a run record (docs/bench/bench_live-<UTC>.json, tools/bench_record.py); the record says
the machine's load when it started: other work on the same cores slows mapping down.

    python tools/bench_live.py [--world default] [--sweep 0.25 0.5 0.75 1.5]
    python tools/bench_live.py --markdown docs/bench/bench_live-<UTC>.json   # a record's table, for the docs
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_record import write_record  # noqa: E402

from evsemmap_warp.apps.cli import main  # noqa: E402
from evsemmap_warp.config import load_config  # noqa: E402
from evsemmap_warp.data.log_writer import write_log  # noqa: E402
from evsemmap_warp.data.logs import open_reader  # noqa: E402
from evsemmap_warp.live.feed import RobotFeed  # noqa: E402
from evsemmap_warp.live.mapping import LiveMapping, LiveSettings  # noqa: E402
from evsemmap_warp.live.ros2_wire import encode_attachment, topic_key, typestore  # noqa: E402
from evsemmap_warp.live.scan_queue import ScanQueue  # noqa: E402
from evsemmap_warp.synthetic.preset import load_preset  # noqa: E402
from evsemmap_warp.synthetic.writer import generate_sequence  # noqa: E402

PRESETS = ["rellis3d", "rellis3d-bag"]
PERIOD_S = 0.1  # the synthetic drive's LiDAR rate: 10 Hz
KEYS = ("scans_received", "scans_mapped", "scans_dropped", "integrated_latency_ms_p50", "integrated_latency_ms_p95",
        "integrated_latency_ms_p99", "published_latency_ms_p50", "published_latency_ms_p95", "published_latency_ms_p99",
        "decode_ms_p50", "place_ms_p50", "integrate_ms_p50", "mapping_seconds")


def markdown(record_path: Path) -> str:
    """The docs' table of a run record (docs/robot.md shows it as printed here)."""
    record = json.loads(Path(record_path).read_text())
    results = record["results"]
    rows = [(name, run) for name, run in results["runs"].items()] + [("network", run) for run in results["sweep"]]
    lines = [f"<!-- record: docs/bench/{Path(record_path).name} -->",
             "| run | rate (Hz) | mapped of received | integrated p50 / p95 / p99 (ms) | published p99 (ms) "
             "| decode / place / integrate, median (ms) | busy share of the period |",
             "|---|---|---|---|---|---|---|"]
    for name, run in sorted(rows, key=lambda r: (not r[0].startswith("network+publish"), r[0] != "direct", r[1]["rate_hz"], r[0])):
        published = run["published_latency_ms_p99"] if run["published_latency_ms_p99"] is not None else "-"
        lines.append(f"| {name} | {run['rate_hz']:g} | {run['scans_mapped']} of {run['scans_received']} | {run['integrated_latency_ms_p50']} / "
                     f"{run['integrated_latency_ms_p95']} / {run['integrated_latency_ms_p99']} | {published} | {run['decode_ms_p50']} / "
                     f"{run['place_ms_p50']} / {run['integrate_ms_p50']} | {run['busy_share_of_period']} |")
    return "\n".join(lines)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def summary(report: dict, rate_factor: float) -> dict:
    out = {k: report.get(k) for k in KEYS}
    out["rate_hz"] = round(1 / PERIOD_S * rate_factor, 2)
    mapped = max(report["scans_mapped"], 1)
    out["busy_share_of_period"] = round(report["mapping_seconds"] / mapped / (PERIOD_S / rate_factor), 3)
    out["drop_share"] = round(report["scans_dropped"] / max(report["scans_received"], 1), 3)
    return out


def network_run(log: Path, folder: Path, rate_factor: float, publish: bool, period_s: float | None = None) -> dict:
    """``evsemmap live`` here, ``evsemmap replay`` in a second process; ``period_s``: the map's and the layers' period
    (None: the defaults)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    report = folder / f"live-{rate_factor}-{publish}-{period_s}.json"
    periods = [] if period_s is None else ["--map-period", str(period_s), "--grid-period", str(period_s)]
    argv = ["live", *PRESETS, "--method", "ebs", "--out", str(folder / "live.npz"), "--listen", endpoint, "--idle-exit", "3",
            "--report", str(report), *([] if publish else ["--no-publish"]), *periods]
    live = threading.Thread(target=main, args=(argv,), daemon=True)
    live.start()
    env = os.environ | {"PYTHONPATH": str(REPO)}
    robot = subprocess.run([sys.executable, "-m", "evsemmap_warp.apps.cli", "replay", str(log), "--connect", endpoint, "--rate",
                            str(rate_factor), "--quiet", "--wait-subscribers", "20"], env=env, capture_output=True, text=True, timeout=600)
    if robot.returncode:
        raise RuntimeError(f"replay failed: {robot.stderr[-2000:]}")
    live.join(600)
    return summary(json.loads(report.read_text()), rate_factor)


class _Bytes:
    def __init__(self, data):
        self.data = data

    def to_bytes(self):
        return self.data


class _Sample:
    def __init__(self, key, payload, attachment):
        self.key_expr, self.payload, self.attachment = key, _Bytes(payload), _Bytes(attachment)


class _NoNetwork:
    def declare_subscriber(self, key, callback):
        return type("Subscriber", (), {"undeclare": lambda self: None})()


def direct_run(log: Path, folder: Path, rate_factor: float) -> dict:
    """The mapping loop fed by the subscriber callback on the recorded schedule, with no network."""
    run = load_config(PRESETS, method="ebs")
    store = typestore()
    queue = ScanQueue(8)
    feed = RobotFeed(_NoNetwork(), run.dataset.bag, queue, store, key_format="rmw_zenoh")
    mapping = LiveMapping(run, feed, queue, LiveSettings(idle_exit_s=3.0), out=folder / "direct.npz")
    reader = open_reader([log])
    messages = [(c.topic, c.msgtype, bytes(raw), t) for c, t, raw in reader.messages() if c.topic in feed.topics]
    reader.close()

    def robot():
        start, first = time.perf_counter(), messages[0][3]
        for n, (topic, msgtype, raw, t) in enumerate(messages):
            time.sleep(max(0.0, start + (t - first) / 1e9 / rate_factor - time.perf_counter()))
            key = topic_key(topic, key_format="rmw_zenoh", msgtype=msgtype, type_hash=store.hash_rihs01(msgtype))
            feed.on_sample(topic, _Sample(key, raw, encode_attachment(n, time.time_ns(), b"\0" * 16)))

    threading.Thread(target=robot, daemon=True).start()
    mapping.run_until_stopped(threading.Event())
    mapping.finish()
    return summary(mapping.diagnostics() | {"mapping_seconds": mapping.stats.mapping_s}, rate_factor)


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", default="default")
    parser.add_argument("--sweep", type=float, nargs="*", default=[0.25, 0.5, 0.75, 1.5], help="factors of the recorded rate")
    parser.add_argument("--markdown", type=Path, default=None, metavar="RECORD", help="print a record's table and exit")
    args = parser.parse_args()
    if args.markdown is not None:
        print(markdown(args.markdown))
        return
    started = time.time()
    load_at_start = list(os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="bench_live-") as tmp:
        folder = Path(tmp)
        generate_sequence(load_preset(args.world), folder / "drive", progress=False, camera=False)
        log = folder / "drive_ros2"
        write_log(folder / "drive", log, "rosbag2")
        results = {"world": args.world, "method": "ebs", "device": "cpu", "recorded_rate_hz": 1 / PERIOD_S, "load_average_at_start": load_at_start,
                   "runs": {}}
        results["runs"]["network+publish"] = network_run(log, folder, 1.0, publish=True)
        results["runs"]["network+publish/5s"] = network_run(log, folder, 1.0, publish=True, period_s=5.0)
        results["runs"]["network"] = network_run(log, folder, 1.0, publish=False)
        results["runs"]["direct"] = direct_run(log, folder, 1.0)
        results["sweep"] = [network_run(log, folder, factor, publish=False) for factor in sorted(args.sweep)]
        kept = [r["rate_hz"] for r in results["sweep"] + [results["runs"]["network"]] if r["scans_dropped"] == 0]
        results["highest_rate_hz_without_drops"] = max(kept) if kept else None
        results["load_average_at_end"] = list(os.getloadavg())
    print(json.dumps(results, indent=1))
    print(write_record("bench_live", results, started=started))


if __name__ == "__main__":
    main_bench()

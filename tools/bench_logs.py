"""Robot-log reading benchmark on this CPU: the same synthetic drive as a folder and as a ROS 1 bag, a
ROS 2 sqlite3 bag and a bare MCAP file, read in one run.

For each log format:
1. index: opening the log (``LogSequence``: header stamps of every cloud and image, TF, odometry,
   camera info), seconds;
2. read: a sequential pass decoding every cloud (PointCloud2 -> points, labels) and every raw image,
   in messages/s and MB/s of serialised messages; beside it the floor of ``rosbags`` itself (the same
   messages iterated, not decoded);
3. map: ``evsemmap map LOG rellis3d-bag --method ebs`` as the library runs it (read + integrate),
   input points/s, against the same drive from its folder in the same run.

Warm-up pass first, then the median of ``--repeats``. The figures go to a run record
(docs/bench/bench_logs-<UTC>.json, tools/bench_record.py): the last line printed is its path, the line
before it the figures as one JSON object.

    python tools/bench_logs.py [--world default] [--frames 30] [--repeats 3]
    python tools/bench_logs.py --markdown docs/bench/bench_logs-<UTC>.json   # a record's table, for the docs
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_record import write_record  # noqa: E402

from evsemmap_warp.config import load_config  # noqa: E402
from evsemmap_warp.core.mapper import Mapper  # noqa: E402
from evsemmap_warp.data.datasets import open_dataset  # noqa: E402
from evsemmap_warp.data.log_writer import LOG_FORMATS, write_log  # noqa: E402
from evsemmap_warp.data.logs import LogSequence, open_reader  # noqa: E402
from evsemmap_warp.synthetic.preset import load_preset  # noqa: E402
from evsemmap_warp.synthetic.writer import generate_sequence  # noqa: E402

SUFFIX = {"rosbag1": "drive.bag", "rosbag2": "drive_ros2", "mcap": "drive.mcap"}
FORMAT_NAMES = {"rosbag1": "ROS 1 bag", "rosbag2": "ROS 2 sqlite3", "mcap": "MCAP"}


def markdown(record_path: Path) -> str:
    """The docs' table of a run record (docs/performance.md shows it as printed here)."""
    results = json.loads(Path(record_path).read_text())["results"]
    lines = [f"<!-- record: docs/bench/{Path(record_path).name} -->",
             "| log format | size | index | read + decode (clouds and raw images) | `rosbags` iterating the same messages | `map --method ebs` "
             "| vs the folder |",
             "|---|---|---|---|---|---|---|"]
    for fmt, row in results["formats"].items():
        lines.append(f"| {FORMAT_NAMES.get(fmt, fmt)} | {row['log_mb']} MB | {row['index_s']} s | {row['read_messages_per_s']} msgs/s, "
                     f"{row['read_mb_per_s']} MB/s | {row['rosbags_floor_mb_per_s']} MB/s | {row['map_input_points_per_s'] / 1e3:.0f} k points/s "
                     f"| {row['map_vs_folder']}x |")
    return "\n".join(lines)


def median_time(fn, repeats: int) -> tuple[float, object]:
    fn()  # warm-up: page cache, kernel compilation, imports
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def raw_pass(log: Path, topics: set[str]) -> tuple[int, int]:
    reader = open_reader([log])
    try:
        connections = [c for c in reader.connections if c.topic in topics]
        count = size = 0
        for _, _, raw in reader.messages(connections=connections):
            count += 1
            size += len(raw)
        return count, size
    finally:
        reader.close()


def decode_pass(log: Path) -> int:
    config = load_config([str(log), "rellis3d-bag"]).dataset.bag
    seq = LogSequence([log], config)
    try:
        points = 0
        for frame in seq.frames:
            points += len(seq.read_scan(frame))
            seq.read_point_labels(frame)
            if frame.image is not None:
                seq.read_image(frame)
        return points
    finally:
        seq.close()


def map_pass(sources: list[str]) -> int:
    run = load_config(sources, method="ebs")
    dataset = open_dataset(run.dataset)
    mapper = Mapper(run.mapping, dataset.num_classes, class_names=dataset.class_names)
    points = 0
    for scan in dataset:
        mapper.integrate(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)
        points += len(scan.points)
    return points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="default")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--markdown", type=Path, metavar="RECORD", help="print the docs' table of a run record and exit")
    args = parser.parse_args()
    if args.markdown:
        print(markdown(args.markdown))
        return
    results = {"preset": args.world, "frames": args.frames, "repeats": args.repeats, "formats": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "folder"
        generate_sequence(load_preset(args.world, trajectory__frames=args.frames), folder, progress=False)
        start = time.perf_counter()
        folder_map_s, folder_points = median_time(lambda: map_pass([str(folder), "rellis3d"]), args.repeats)
        results["folder_map"] = {"seconds": round(folder_map_s, 3), "input_points_per_s": round(folder_points / folder_map_s)}
        print(f"folder: map {folder_map_s:.2f} s, {folder_points / folder_map_s / 1e3:.0f} k input points/s")
        for fmt in LOG_FORMATS:
            log = Path(tmp) / SUFFIX[fmt]
            start = time.perf_counter()
            write_log(folder, log, fmt)
            write_s = time.perf_counter() - start
            size = sum(f.stat().st_size for f in ([log] if log.is_file() else log.rglob("*")) if f.is_file())
            topics = {"/os1_cloud_node/points", "/pylon_camera_node/image_raw"}
            index_s, _ = median_time(lambda: LogSequence([log], load_config([str(log), "rellis3d-bag"]).dataset.bag).close(), args.repeats)
            raw_s, (messages, raw_bytes) = median_time(lambda: raw_pass(log, topics), args.repeats)
            read_s, _ = median_time(lambda: decode_pass(log), args.repeats)
            map_s, points = median_time(lambda: map_pass([str(log), "rellis3d", "rellis3d-bag"]), args.repeats)
            row = {
                "log_mb": round(size / 1e6, 1), "write_s": round(write_s, 2), "index_s": round(index_s, 3),
                "read_messages_per_s": round(messages / read_s), "read_mb_per_s": round(raw_bytes / read_s / 1e6, 1),
                "rosbags_floor_messages_per_s": round(messages / raw_s), "rosbags_floor_mb_per_s": round(raw_bytes / raw_s / 1e6, 1),
                "map_input_points_per_s": round(points / map_s), "map_vs_folder": round(folder_map_s / map_s, 3),
                # per frame (a cloud and an image): reading it against mapping it
                "read_ms_per_frame": round(1e3 * read_s / args.frames, 1), "map_ms_per_frame": round(1e3 * map_s / args.frames, 1),
            }
            results["formats"][fmt] = row
            print(f"{fmt:8s}: {row['log_mb']} MB, index {index_s:.2f} s, read+decode {row['read_messages_per_s']} msg/s "
                  f"{row['read_mb_per_s']} MB/s (rosbags alone {row['rosbags_floor_mb_per_s']} MB/s), map "
                  f"{points / map_s / 1e3:.0f} k points/s ({row['map_vs_folder']:.2f}x the folder)")
    print(json.dumps(results))
    print(write_record("bench_logs", results))


if __name__ == "__main__":
    main()

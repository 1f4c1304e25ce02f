"""``evsemmap project``: project a sequence's 2D labels onto its LiDAR points (3D ground truth + overlays)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .args import add_frame_args, non_negative, positive


def add_parser(sub) -> None:
    """Add ``project`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("project", help="project a sequence's 2D labels onto its LiDAR points (3D ground truth + overlays)")
    p.add_argument("sequence", nargs="+", help="a RELLIS-3D-layout folder, or robot logs with the configs or presets that say their "
                                               "topics (e.g. drive.bag rellis3d-bag)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--zbuffer", action="store_true", help="drop points hidden behind nearer points")
    p.add_argument("--overlays", type=non_negative, default=3, help="overlay images to write")
    p.add_argument("--color-by", choices=("label", "depth"), default="label", help="overlay points in their label's color or by range")
    p.add_argument("--max-frames", type=positive, default=None)
    add_frame_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """Project a sequence's 2D labels onto its scans: 3D ground truth, agreement with the per-point
    labels where the sequence has them, and overlay images."""
    from ...classes import class_set, original_to_v3_table
    from ...geometry.projection import ProjectionConfig, depth_colors, label_map_for, project_frames, save_overlay
    from ...data.datasets import open_sequence
    from ...data.sequences import remap_point_labels
    from ...files import savez_atomically

    seq = open_sequence(args.sequence, frame=args.frame, crs=args.crs)
    from ...files import check_not_inside

    check_not_inside(args.out, getattr(seq, "logs", None) or [seq.root], "project --out")  # never into the sequence it reads
    config = ProjectionConfig(zbuffer=args.zbuffer)
    frames = [f for f in seq.frames if f.label_image is not None][: args.max_frames]
    if not frames:
        raise ValueError(f"{' '.join(args.sequence)}: no frame has a 2D label image")
    args.out.mkdir(parents=True, exist_ok=True)
    table = original_to_v3_table()
    colors = class_set("remap_v3").colors
    by_index = {f.index: f for f in frames}
    points, labels, agree, compared = [], [], 0, 0
    for n, item in enumerate(project_frames(seq, frames, label_map_for(seq), config, seq.world)):
        points.append(item.points)
        labels.append(item.values)
        frame = by_index[item.frame_index]
        if frame.point_labels is not None:
            own = remap_point_labels(seq.read_point_labels(frame), table, frame.point_labels)[item.scan_rows]
            agree += int((own == item.values).sum())
            compared += len(own)
        if n < args.overlays:
            depth = np.linalg.norm(item.points - item.sensor_origin, axis=1)
            shown = depth_colors(depth) if args.color_by == "depth" else colors[item.values]
            save_overlay(args.out / f"overlay_{frame.index:06d}.png", seq.read_image(frame), item.pixel, shown)
    savez_atomically(args.out / "ground_truth.npz", compressed=True, points=np.concatenate(points), labels=np.concatenate(labels),
                     frame=np.array(json.dumps(seq.world.frame.as_dict())))  # the world frame the points are in
    report = {"frames": len(frames), "points": int(sum(len(p) for p in points)), "frame": seq.world.frame.as_dict(), "out": str(args.out)}
    if compared:
        report["agreement_with_point_labels_v3"] = round(agree / compared, 4)
    print(json.dumps(report, indent=1))
    return 0

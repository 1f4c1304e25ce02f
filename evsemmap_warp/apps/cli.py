"""``evsemmap``: a thin command line over the library (flags -> configs -> pipeline calls)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import yaml

from .. import limits
from ..config import ConfigError, available_methods, load_config, warn_deprecated


def _cmd_map(args) -> int:
    from tqdm import tqdm

    from ..core.mapper import Mapper, VoxelState, save_map
    from .scan_sources import map_scans, open_scan_source

    run = load_config(args.configs, method=args.method, frame=args.frame, crs=args.crs)
    if run.dataset is None:
        raise ConfigError(f"none of {list(args.configs)} has a 'dataset' section: name a dataset config, e.g. configs/datasets/sbki_toy.yaml")
    from ..files import check_not_inside

    data = run.dataset.resolve_logs() if run.dataset.kind == "bag" else [run.dataset.resolve_path()]
    # never over a log, a config file or a checkpoint, nor into a sequence folder or the alpha files
    read = [*run.sources, *data, *(p for p in (args.checkpoint, args.alpha_dir) if p is not None)]
    check_not_inside(args.out, read, "map --out")
    dataset = open_scan_source(run, checkpoint=args.checkpoint, alpha_dir=args.alpha_dir, bin_frames=args.bin_frames, batch_size=args.batch_size)
    mapper = Mapper.for_dataset(dataset, run.mapping, device=args.device, workers=args.workers, max_memory=args.max_memory)
    live = None
    if args.view:
        live = _live_viewer(args, mapper, len(dataset))
    elif (args.host, args.port, args.view_every) != (None, None, None):
        raise ConfigError("--host, --port and --view-every serve the map while it is made: give --view too")
    if not args.quiet:
        what = f"{len(dataset)} bins of camera-labelled frames" if args.checkpoint or args.alpha_dir else f"{len(dataset)} scans"
        print(f"mapping {what} with {run.mapping.method} ({run.mapping.compat.value} mode) on {mapper.device}, "
              f"{len(mapper.shards)} worker(s), in {dataset.frame.describe()}", file=sys.stderr)
    start = time.perf_counter()
    try:
        with tqdm(total=len(dataset), unit="scan", disable=args.quiet, dynamic_ncols=True) as bar:
            # Reading and host work of the next scans overlap this one's kernels; errors name their scan.
            if live is None:
                stats = map_scans(mapper, dataset, progress=lambda scan, _: bar.update(1))
            else:
                from .viewer.live import map_live

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
        "method": run.mapping.method,
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
    from .viewer import MapLayer, MapViewer
    from .viewer.live import LiveMap

    viewer = MapViewer([MapLayer.from_mapper(args.out.stem, args.out, mapper)], host=args.host or "127.0.0.1", port=args.port or 8080)
    live = LiveMap(viewer, mapper, name=args.out.stem, path=args.out, scan_total=scan_total)
    print(f"evsemmap viewer: open {viewer.url} in a browser to watch the map being made (updated every {args.view_every or 10} scans)",
          file=sys.stderr)
    return live


def _cmd_batch(args) -> int:
    from .batch import BatchOptions, run_batch

    options = BatchOptions(method=args.method, out=args.out, executor=args.executor, workers=args.workers, chunk_frames=args.chunk_frames,
                           ray_address=args.ray_address, checkpoint=args.checkpoint, alpha=args.alpha_dir, bin_frames=args.bin_frames,
                           batch_size=args.batch_size, tile_voxels=args.tile_voxels, discard_partials=args.discard_partials,
                           progress=not args.quiet, frame=args.frame, crs=args.crs, max_memory=args.max_memory,
                           ray_connect_timeout_s=args.ray_connect_timeout_s, chunk_timeout_s=args.chunk_timeout_s,
                           same_frame=args.same_frame)
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
    from ..core.mapper import Mapper
    from .batch import plan_batch
    from .viewer import MapLayer, MapViewer
    from .viewer.live import LiveTiles

    _, sources, config, _, _ = plan_batch(list(args.configs), options)  # the store's classes, frame and parameters
    template = Mapper.for_dataset(sources[0], config, workers=1)
    viewer = MapViewer([MapLayer.from_mapper(args.out.name, args.out, template)], host=args.host or "127.0.0.1", port=args.port or 8080)
    live = LiveTiles(viewer, template, name=args.out.name, path=args.out, max_voxels=500_000)
    print(f"evsemmap viewer: open {viewer.url} in a browser to watch the store's tiles fill in", file=sys.stderr)
    return live


def _load_map_or_store(path: Path):
    """A map file as a Mapper, or a store (whole) as one."""
    from ..core.map_store import MapStore, is_store
    from ..core.mapper import load_map

    # a folder is a store, or one not written yet (MapStore names why it is not one)
    return MapStore(path).to_mapper() if is_store(path) or Path(path).is_dir() else load_map(path)


def _cmd_export(args) -> int:
    from ..core.map_store import MapStore
    from ..core.mapper import save_map

    from ..core.map_store import check_bounds
    from ..files import check_not_inside

    check_not_inside(args.out, [args.store], "export --out")  # never over the store's own files
    store = MapStore(args.store)
    bounds = None
    if args.bounds is not None:
        bounds = np.stack(check_bounds(args.bounds, "--bounds"))
    mapper = store.to_mapper(bounds)
    save_map(args.out, mapper)
    print(json.dumps({"store": str(args.store), "out": str(args.out), "voxels": mapper.voxel_count, "tiles_read": store.tiles_loaded}, indent=1))
    return 0


def _cmd_layers(args) -> int:
    """2.5-D terrain layers of a map file or store: GeoTIFF, npz, PNG previews, a ROS bag (docs/terrain.md)."""
    from ..terrain.pipeline import write_layers

    log = None if args.quiet else (lambda m: print(m, file=sys.stderr))
    summary = write_layers(args.map, args.out, resolution_m=args.resolution_m, bounds=args.bounds, costs=args.costs, device=args.device,
                           previews=not args.no_previews, bag=not args.no_bag, log=log)
    summary.pop("files", None)
    print(json.dumps(summary, indent=1))
    return 0


def _cmd_merge(args) -> int:
    """Maps and stores of disjoint scan sets (several drives or robots over one area) into one."""
    from ..core.mapper import save_map

    if len(args.inputs) < 2:
        raise ValueError(f"merge: give at least two maps or stores, got {len(args.inputs)}")
    from ..files import check_not_inside
    from ..frames import check_same_frame

    resolved = [p.resolve() for p in args.inputs]
    for i, path in enumerate(resolved):
        if path in resolved[:i]:  # its evidence would count twice
            raise ValueError(f"merge: {args.inputs[i]} is given twice; merge each map or store once")
    check_not_inside(args.out, args.inputs, "merge --out")

    merged = None
    for path in args.inputs:
        part = _load_map_or_store(path)
        if merged is not None:  # refused before anything is added, naming both inputs and both frames
            check_same_frame("merge", (str(args.inputs[0]), merged.frame), (str(path), part.frame), same_frame=args.same_frame)
        try:
            merged = part if merged is None else merged.merge(part, same_frame=args.same_frame)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    if args.out.suffix == ".npz":
        save_map(args.out, merged)
    else:
        from .batch import write_store_from_mapper

        write_store_from_mapper(merged, args.out, args.tile_voxels, [str(p) for p in args.inputs])
    print(json.dumps({"inputs": [str(p) for p in args.inputs], "out": str(args.out), "voxels": merged.voxel_count}, indent=1))
    return 0


def _cmd_info(args) -> int:
    from ..core.map_file import read_map_file
    from ..core.mapper import reader_mapper
    from ..core.map_store import MapStore, is_store, voxel_bounds

    if is_store(args.map) or (args.map.is_dir() and (args.map / "work").is_dir()):
        print(json.dumps(MapStore(args.map).summary(), indent=1))
        return 0

    contents = read_map_file(args.map)  # the sums; the states are read out below, the rest of the read-out is not needed
    meta, reader = contents.meta, reader_mapper(contents)
    state = reader.summarize(contents.evidence, contents.touched).state
    print(json.dumps({
        "file": str(args.map),
        "method": meta["method"],
        "classes": meta["classes"],
        "format_version": meta["format_version"],
        "resolution_m": contents.resolution,
        "origin_m": contents.origin.tolist(),
        "frame": meta.get("frame"),  # None: written before maps recorded their world frame
        "voxels": int(len(state)),
        "bounds_m": voxel_bounds(reader, contents.index),  # [[x0, y0, z0], [x1, y1, z1]] in the frame, None when empty
        "states": {"UNKNOWN": int((state == 0).sum()), "FREE": int((state == 1).sum()), "OCCUPIED": int((state == 2).sum())},
        "scans_integrated": meta.get("scans_integrated"),
        "mapping": meta["mapping"],
    }, indent=1))
    return 0


def _cmd_view(args) -> int:
    from ..files import check_not_inside
    from ..frames import describe_frame
    from .viewer import MapViewer, check_address

    read = [*args.maps, *(args.drive or []), *(p for p in (args.truth, args.trajectory, args.scan, args.costs, args.checkpoint, args.alpha_dir)
                                               if p is not None)]
    for flag, path in (("--export-html", args.export_html), ("--export-ply", args.export_ply)):
        if path is not None:
            check_not_inside(path, read, f"view {flag}")  # never over a map given, nor inside a store
    drive = None
    if args.drive:
        from ..core.map_store import is_store
        from .viewer.drive import open_drive

        if len(args.maps) != 1 or is_store(args.maps[0]):
            raise ValueError(f"--drive plays back the drive of one map file (.npz), got {' '.join(map(str, args.maps))}")
        check_address(args.host, args.port)  # before the drive is read and checked
        drive = open_drive(args.maps[0], args.drive, checkpoint=args.checkpoint, alpha_dir=args.alpha_dir, bin_frames=args.bin_frames,
                           snapshot_every=args.snapshot_every)
    else:
        for flag, value in (("--checkpoint", args.checkpoint), ("--alpha-dir", args.alpha_dir), ("--bin-frames", args.bin_frames)):
            if value is not None:
                raise ValueError(f"{flag} labels the scans of a --drive: give --drive too")
    from ..core.map_store import MapStore, is_store

    for path in args.maps:  # a folder that is not (yet) a store: MapStore names why, e.g. a batch run still writing it
        if path.is_dir() and not is_store(path):
            MapStore(path)
    viewer = MapViewer(args.maps, host=args.host, port=args.port, style=args.style, max_voxels=args.max_voxels,
                       trajectory=args.trajectory, scan=args.scan, export_dir=args.export_dir, terrain=args.layers,
                       terrain_resolution=args.layers_resolution_m, costs=args.costs, truth=args.truth, same_frame=args.same_frame)
    if args.export_html is not None or args.export_ply is not None:
        viewer.wait_for_stores()  # a store's whole overview, not its first frame's tiles
    for path, export in ((args.export_html, viewer.export_html), (args.export_ply, viewer.export_ply)):
        if path is not None:
            print(f"wrote {export(path)}", file=sys.stderr)
    if args.no_serve:
        viewer.close()
        return 0
    if drive is not None:
        from .viewer.drive import DrivePlayback

        DrivePlayback(viewer, *drive)
    print(f"evsemmap viewer: open {viewer.url} in a browser (Ctrl-C to stop); maps in {describe_frame(viewer.frame)}, "
          f"local origin at {viewer.origin_text()}", file=sys.stderr)
    viewer.serve_forever()
    return 0


def _segmentation_source(args):
    from ..segmentation.data import Rellis3DImages, RugdImages, SyntheticOffroad

    if args.dataset == "synthetic":
        return SyntheticOffroad(args.synthetic_frames, tuple(args.input_size), domain=args.domain, seed=args.seed)
    if args.data is None:
        raise ValueError(f"--data DIR is needed for the {args.dataset} dataset")
    return (Rellis3DImages if args.dataset == "rellis3d" else RugdImages)(args.data)


def _cmd_train_seg(args) -> int:
    from ..classes import class_set
    from ..segmentation.config import ModelConfig
    from ..segmentation.train import TrainConfig, train

    classes = class_set()
    config = TrainConfig(
        model=ModelConfig(arch=args.arch, num_classes=len(classes), width=args.width, aspp_channels=args.aspp_channels),
        head=args.head, input_size=tuple(args.input_size), epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
        kl_schedule=args.kl_schedule, val_fraction=args.val_fraction, seed=args.seed, time_budget_s=args.time_budget_s,
        logit_clamp=args.logit_clamp, normalization=args.normalization,
        backbone_weights=str(args.backbone_weights) if args.backbone_weights else None,
    )
    summary = train(_segmentation_source(args), classes.names, config, args.out, resume=args.resume, progress=not args.quiet)
    print(json.dumps(summary, indent=1))
    return 0


def _cmd_eval_seg(args) -> int:
    from ..segmentation.train import evaluate_checkpoint

    summary = evaluate_checkpoint(args.checkpoint, _segmentation_source(args), args.out)
    print(json.dumps(summary, indent=1))
    return 0


def _cmd_infer(args) -> int:
    from PIL import Image
    from tqdm import tqdm

    from ..files import save_npy_atomically
    from ..segmentation.train import infer_alpha, load_checkpoint

    model, config, meta, _ = load_checkpoint(args.checkpoint)
    paths = sorted(p for p in args.images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")) if args.images.is_dir() else [args.images]
    if not paths:
        raise ValueError(f"{args.images}: no .jpg or .png images")
    args.out.mkdir(parents=True, exist_ok=True)

    def images():
        for path in paths:
            with Image.open(path) as img:
                if img.mode != "RGB":
                    raise ValueError(f"{path}: expected an RGB image, got mode {img.mode}")
                yield np.asarray(img)

    outputs = infer_alpha(model, config, meta, images(), batch_size=args.batch_size)
    for path, (alpha, _) in tqdm(zip(paths, outputs), total=len(paths), unit="img", disable=args.quiet):
        save_npy_atomically(args.out / f"{path.stem}.npy", alpha)
    print(f"wrote {len(paths)} {'alpha' if config.head == 'evidential' else 'probability'} maps "
          f"[{config.model.num_classes}, {config.input_size[0]}, {config.input_size[1]}] float16 to {args.out}", file=sys.stderr)
    return 0


def _cmd_synth(args) -> int:
    from ..synthetic.preset import load_preset
    from ..synthetic.writer import generate_sequence

    import shutil
    import tempfile

    from ..files import error_naming

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

    from ..data.log_writer import write_log

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


def _bag_config(logs, configs):
    """The dataset.bag settings of the given config files and preset names (defaults without any)."""
    run = load_config([str(p) for p in logs] + list(configs))
    return run.dataset.bag


def _cmd_check_data(args) -> int:
    from ..config import is_robot_log
    from ..data.logs import check_log
    from ..data.sequences import check_sequence

    logs = [p for p in args.paths if is_robot_log(p)]
    # configs: YAML files and preset names (a bare word); a missing path is a folder to report, never a preset
    configs = [str(p) for p in args.paths if not is_robot_log(p) and (p.suffix in (".yaml", ".yml") or
                                                                     (not p.exists() and p.suffix == "" and len(p.parts) == 1))]
    folders = [p for p in args.paths if p not in logs and str(p) not in configs]
    if not logs and not folders:
        raise ValueError(f"check-data: none of {[str(p) for p in args.paths]} is a sequence folder or a robot log (configs and presets "
                         f"only say how to read logs)")
    reports = [check_sequence(d) for d in folders]
    if logs:
        reports.append(check_log(logs, _bag_config(logs, configs)))
    for report in reports:
        print(report.text())
    return 0 if all(r.ok for r in reports) else 1


def _cmd_project(args) -> int:
    """Project a sequence's 2D labels onto its scans: 3D ground truth, agreement with the per-point
    labels where the sequence has them, and overlay images."""
    from ..classes import class_set, original_to_v3_table
    from ..geometry.projection import ProjectionConfig, depth_colors, label_map_for, project_frames, save_overlay
    from ..data.datasets import open_sequence
    from ..data.sequences import remap_point_labels
    from ..files import savez_atomically

    seq = open_sequence(args.sequence, frame=args.frame, crs=args.crs)
    from ..files import check_not_inside

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


def _cmd_train_convbki(args) -> int:
    from ..methods import convbki
    from ..classes import class_set
    from ..geometry.projection import ProjectionConfig
    from ..data.sequences import Rellis3DSequence

    if args.alpha_dir is None:  # not argparse's required=True, which would refuse its old name --alpha
        raise ConfigError("train-convbki: --alpha-dir DIR is required (the folder of per-frame alpha .npy `evsemmap infer` wrote)")
    seq = Rellis3DSequence(args.sequence)

    def alpha_for_frame(frame):
        for name in (f"{frame.index:06d}.npy", f"{frame.image.stem}.npy"):  # experiment cache or `evsemmap infer` names
            if (args.alpha_dir / name).exists():
                return np.load(args.alpha_dir / name).astype(np.float32)
        return None

    windows = convbki.training_windows(seq, alpha_for_frame, ProjectionConfig(), window_scans=args.window_scans,
                                       queries_per_window=args.queries)
    if not windows:
        raise ValueError(f"{args.sequence}: no window of {args.window_scans} scans with alpha in {args.alpha_dir} and per-point labels")
    lengths, history = convbki.train_lengths(windows, len(class_set().names), args.resolution_m, epochs=args.epochs, progress=not args.quiet)
    convbki.save_lengths(args.out, lengths)
    print(json.dumps({"out": str(args.out), "windows": len(windows), "loss": [round(h, 4) for h in history]} | lengths.as_dict(), indent=1))
    return 0


def _cmd_experiment(args) -> int:
    from .experiment import Experiment, load_experiment

    config, path = load_experiment(args.config, quick=getattr(args, "quick", False))
    out = args.out or Path(f"results_{config.name}" + ("_quick" if getattr(args, "quick", False) else ""))
    started = time.perf_counter()
    Experiment(config, out, cache=getattr(args, "cache", None), device=args.device, progress=not args.quiet,
               log=lambda m: print(m, file=sys.stderr)).run()
    print((out / "results.md").read_text())
    maps = out / "maps" / next(iter(config.conditions))
    print(f"{config.name}: {time.perf_counter() - started:.0f} s; results, plots and maps in {out}/\n"
          f"view a map: evsemmap view {maps}/{config.methods[-1]}.npz --trajectory {maps}/trajectory.txt")
    return 0


def _cmd_demo(args) -> int:
    args.config = "demo"
    return _cmd_experiment(args)


def _cmd_dump_config(args) -> int:
    run = load_config(args.configs, method=args.method)
    out = {"mapping": run.mapping.as_dict()}
    if run.dataset is not None:
        def plain(value):
            if dataclasses.is_dataclass(value):
                return {k: plain(v) for k, v in vars(value).items()}
            return list(value) if isinstance(value, tuple) else getattr(value, "value", value)

        out["dataset"] = {k: plain(v) for k, v in vars(run.dataset).items() if k != "bag" or run.dataset.kind == "bag"}
    if run.bin_frames != 1:
        out["pipeline"] = {"bin_frames": run.bin_frames}
    from ..terrain import load_terrain_config

    terrain = load_terrain_config(args.costs)
    out["terrain"] = {"source": terrain.source, "layers": _plain_dataclass(terrain.layers), "costs": _plain_dataclass(terrain.costs)}
    print(yaml.safe_dump(out, sort_keys=False), end="")
    return 0


def _plain_dataclass(value) -> dict:
    """A settings dataclass as YAML-ready values (tuples as lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(value).items()}


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's error form: one line naming the flag and value, exit code 2."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # argparse takes "-inf" or "-1e3" for a flag; these are numbers (no flag of ours looks like one)
        self._negative_number_matcher = re.compile(r"^-(?:\d+\.?\d*(?:e[-+]?\d+)?|\.\d+(?:e[-+]?\d+)?|inf(?:inity)?|nan)$", re.IGNORECASE)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _RenamedFlag(argparse.Action):
    """A flag renamed in this release: still read one release long, into the new flag's value, with a
    one-line warning on stderr."""

    def __init__(self, option_strings, dest, new_flag: str = "", **kwargs):
        self.new_flag = new_flag
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        warn_deprecated(option_string, self.new_flag)
        setattr(namespace, self.dest, values)


def _renamed_flag(parser, old: str, new: str, **kwargs) -> None:
    """Let ``parser`` read the old flag ``old`` as ``new`` (hidden from --help)."""
    parser.add_argument(old, dest=new.lstrip("-").replace("-", "_"), action=_RenamedFlag, new_flag=new, help=argparse.SUPPRESS,
                        default=argparse.SUPPRESS, **kwargs)


def _port(text: str) -> int:
    value = _int(text)
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port {value} is outside 1..65535")
    return value


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def _non_negative(text: str) -> int:
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative")
    return value


def _positive(text: str) -> int:
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be at least 1")
    return value


def _limit_type(check, flag: str):
    """An argparse type from a ``limits`` check: the flag's value as the check returns it, or argparse's
    one-line usage error with the check's message (the same limit the writers and readers hold to)."""
    def parse(text: str):
        try:
            return check(text if check is limits.parse_memory_size else _int(text), flag)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return parse


_TILE_VOXELS = _limit_type(limits.check_tile_voxels, "--tile-voxels")
_CHUNK_FRAMES = _limit_type(limits.check_chunk_frames, "--chunk-frames")
_MAX_MEMORY = _limit_type(limits.parse_memory_size, "--max-memory")
_MAX_MEMORY_HELP = ("the memory the map's voxel table may take (512M, 4G; with batch: each worker's); a scan that would grow it "
                    "further is refused (default: the memory available when the table grows)")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be a finite number > 0")
    return value


def _add_frame_args(p) -> None:
    p.add_argument("--frame", default=None, help="the world frame to map in (dataset.frame): by default the data's own (a log's fixed "
                                                 "frame, a folder's poses.txt frame, point files' frame); a NAME names a folder's poses "
                                                 "frame (a log's must be its fixed frame); first-scan: relative to the first scan's pose")
    p.add_argument("--crs", default=None, help="EPSG code of georeferenced coordinates, e.g. EPSG:32617 (dataset.crs); exports carry it")


def build_parser() -> argparse.ArgumentParser:
    """The ``evsemmap`` argument parser: one subcommand per task, each with its flags and help."""
    from ..segmentation.config import ModelConfig

    parser = _Parser(prog="evsemmap", description="Evidential semantic mapping on Warp kernels.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("map", help="map a dataset with a method and write the map file")
    p.add_argument("configs", nargs="+", help="dataset / preset YAML files, merged in order (later wins)")
    p.add_argument("--method", required=True, help=f"method name ({', '.join(available_methods())}) or a method YAML file")
    p.add_argument("--out", required=True, type=Path, help="map file to write (.npz)")
    p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--workers", type=_positive, default=None, help="CPU threads, each scattering into its own map shard (default: up to 2 on the CPU)")
    p.add_argument("--max-memory", type=_MAX_MEMORY, default=None, metavar="SIZE", help=_MAX_MEMORY_HELP)
    p.add_argument("--checkpoint", type=Path, help="label the scans from the camera with this segmentation checkpoint "
                                                   "(evsemmap train-seg) instead of their per-point labels")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="label the scans from the camera with the per-image alpha files "
                                                                   "`evsemmap infer` wrote into this folder (NAME.npy per image, or "
                                                                   "NNNNNN.npy per frame)")
    _renamed_flag(p, "--alpha", "--alpha-dir", type=Path)
    p.add_argument("--bin-frames", type=_positive, default=None, help="with --checkpoint or --alpha-dir: frames integrated together "
                                                                    "(default: the preset's pipeline.bin_frames, else 1)")
    p.add_argument("--batch-size", type=_positive, default=4, help="with --checkpoint: images per inference batch")
    _add_frame_args(p)
    p.add_argument("--view", action="store_true", help="serve the map in a browser while it is made (viser), updated every "
                                                      "--view-every scans, and the map as written once done (until Ctrl-C)")
    p.add_argument("--view-every", type=_positive, default=None, help="with --view: scans between updates of the map shown (default 10)")
    p.add_argument("--host", default=None, help="with --view: address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_port, default=None, help="with --view: port to serve on (default 8080)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or start-up line")
    p.set_defaults(func=_cmd_map)

    p = sub.add_parser("batch", help="map long sequences on every core (or a Ray cluster) into a tiled map store; resumable")
    p.add_argument("configs", nargs="+", help="sequences (folders, robot logs, dataset configs: each one input, mapped in order into one map) "
                                              "and the presets / configs they share")
    p.add_argument("--method", required=True, help=f"method name ({', '.join(available_methods())}) or a method YAML file")
    p.add_argument("--out", required=True, type=Path, help="the map store (a folder) to write, or to finish when a run was interrupted")
    p.add_argument("--executor", choices=("local", "ray"), default="local", help="local: a process pool (default); ray: Ray tasks")
    p.add_argument("--workers", type=_positive, default=None, help="worker processes (default: one per core; with ray: the cluster's CPUs)")
    p.add_argument("--max-memory", type=_MAX_MEMORY, default=None, metavar="SIZE", help=_MAX_MEMORY_HELP)
    p.add_argument("--chunk-frames", type=_CHUNK_FRAMES, default=None,
                   help="frames per task, rounded to whole bins (default: automatic, from the inputs' total frames only: "
                        "ceil(frames / 16), at most 100: at least 16 chunks when the frames allow, two per worker up to 8 workers; "
                        "never from the worker count, so stores are the same for any; the JSON summary gives the value and rule)")
    p.add_argument("--ray-address", default=None, help="an existing Ray cluster: auto, ray://host:port, or its head's host:port (with RAY_AUTH_MODE=token for token authentication, Ray's default; default: a local Ray instance)")
    p.add_argument("--ray-connect-timeout-s", type=_positive_float, default=30.0, metavar="S",
                   help="with --ray-address host:port: seconds it may take to accept a connection before the run is refused (default 30)")
    p.add_argument("--same-frame", action="store_true", help="the inputs' run frames (e.g. odom) are one run's, a drive cut into several "
                                                             "logs: runs that differ or are unknown are mapped together (docs/formats.md)")
    p.add_argument("--chunk-timeout-s", type=_positive_float, default=3600.0, metavar="S",
                   help="stop when no chunk finishes for this long, as a stuck worker or node (default 3600; the chunks mapped are kept)")
    p.add_argument("--checkpoint", type=Path, help="label the scans from the camera with this segmentation checkpoint (inference in each task)")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="label the scans from the camera with the alpha files of `evsemmap infer` "
                                                                   "in this folder")
    _renamed_flag(p, "--alpha", "--alpha-dir", type=Path)
    p.add_argument("--bin-frames", type=_positive, default=None, help="with --checkpoint or --alpha-dir: frames per insertion (default: the preset's)")
    p.add_argument("--batch-size", type=_positive, default=4, help="with --checkpoint: images per inference batch")
    p.add_argument("--tile-voxels", type=_TILE_VOXELS, default=256, help=f"tile edge in voxels, 1..{limits.MAX_TILE_VOXELS} (default 256: 51.2 m at 0.2 m)")
    p.add_argument("--discard-partials", action="store_true", help="delete STORE/work (the run's plan and chunk records; partial maps are deleted as they are folded) at the end: a rerun then starts over")
    _add_frame_args(p)
    p.add_argument("--view", action="store_true", help="serve the store's overview in a browser while it is made (viser): tiles fill in "
                                                      "as chunks finish; then the overview as written (until Ctrl-C)")
    p.add_argument("--host", default=None, help="with --view: address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_port, default=None, help="with --view: port to serve on (default 8080)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or progress messages (errors are still reported); the JSON summary still goes to stdout")
    p.set_defaults(func=_cmd_batch)

    p = sub.add_parser("export", help="a map store (or the part of it inside --bounds) as one map file")
    p.add_argument("store", type=Path)
    p.add_argument("--bounds", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), help="keep voxels whose centers lie in this box (m)")
    p.add_argument("--out", type=Path, required=True, help="map file to write (.npz)")
    p.set_defaults(func=_cmd_export)

    p = sub.add_parser("layers", help="2.5-D terrain layers (elevation, slope, step, class, uncertainty, cost) of a map or store as a "
                                      "GeoTIFF, an npz, PNG previews and a ROS bag (grid_map, OccupancyGrid)")
    p.add_argument("map", type=Path, help="a map file (.npz) or a map store (a folder)")
    p.add_argument("--out", type=Path, required=True, help="folder to write layers.tif, layers.npz (a store: tiles/X_Y.npz), "
                                                           "layers.bag, previews/ and layers.json into")
    p.add_argument("--resolution-m", type=float, default=None, help="cell edge (m; default: the map's voxel size; a store's must divide its tiles)")
    _renamed_flag(p, "--resolution", "--resolution-m", type=float)
    p.add_argument("--bounds", type=float, nargs="+", metavar="M", help="the region: X0 Y0 X1 Y1, or X0 Y0 Z0 X1 Y1 Z1 to count only "
                                                                        "voxels whose centers lie between Z0 and Z1 (m, the map's world frame)")
    p.add_argument("--costs", type=Path, default=None, help="surface classes and cost table YAML (default: configs/terrain/costs_v3.yaml, "
                                                           "for the remap-v3 / RELLIS-3D classes)")
    p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    p.add_argument("--no-bag", action="store_true", help="skip the ROS bag")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=_cmd_layers)

    p = sub.add_parser("merge", help="add up maps or stores of disjoint scan sets (several drives over one area) into one")
    p.add_argument("inputs", nargs="+", type=Path, help="map files (.npz) and map stores, at least two")
    p.add_argument("--out", type=Path, required=True, help="a map file (.npz) or a map store (a folder)")
    p.add_argument("--tile-voxels", type=_TILE_VOXELS, default=256, help=f"tile edge in voxels when writing a store, 1..{limits.MAX_TILE_VOXELS}")
    p.add_argument("--same-frame", action="store_true", help="the inputs' frames of one run (e.g. odom) are one frame: runs that differ or "
                                                             "are unknown are merged (docs/formats.md, the frame's run)")
    p.set_defaults(func=_cmd_merge)

    p = sub.add_parser("view", help="inspect map files and map stores in a browser (viser)")
    p.add_argument("maps", nargs="+", type=Path, help="map files or stores (a store: a decimated overview, any tile in full); several "
                                                      "are switchable or side by side, only when their world frames agree")
    p.add_argument("--same-frame", action="store_true", help="maps of one run frame (e.g. odom) whose runs differ or are unknown are "
                                                             "shown in one frame (docs/formats.md, the frame's run)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_port, default=8080)
    p.add_argument("--style", choices=("points", "boxes"), default="points", help="voxels as point sprites or instanced boxes")
    p.add_argument("--max-voxels", type=_positive, default=500_000, help="decimate beyond this many visible voxels (the GUI can show all)")
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
    p.add_argument("--layers-resolution-m", type=_positive_float, default=None, help="terrain cell edge (m; default: the voxel size)")
    p.add_argument("--costs", type=Path, default=None, help="the terrain layers' cost table YAML (default: configs/terrain/costs_v3.yaml)")
    p.add_argument("--truth", type=Path, default=None, help="ground truth for comparing two maps: `evsemmap project`'s ground_truth.npz "
                                                            "(points, labels) or a map file; differing voxels are colored by which map "
                                                            "agrees with it")
    p.add_argument("--drive", nargs="+", metavar="SOURCE", help="play back the drive the map was made from: its sequence folder or "
                                                                  "robot log (with the presets it needs), labelled as when mapping "
                                                                  "(--checkpoint, --alpha-dir, --bin-frames); a time slider shows the pose, "
                                                                  "the scan, the camera and the map as it stood after each scan")
    p.add_argument("--checkpoint", type=Path, help="with --drive: the segmentation checkpoint that labelled the map's scans")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="with --drive: the folder of alpha files that labelled the map's scans")
    _renamed_flag(p, "--alpha", "--alpha-dir", type=Path)
    p.add_argument("--bin-frames", type=_positive, default=None, help="with --drive and --checkpoint or --alpha-dir: frames per insertion, "
                                                                    "as when mapping")
    p.add_argument("--snapshot-every", type=_positive, default=10, help="with --drive: keep a copy of the replayed map every N scans "
                                                                      "(a scrub replays at most N scans)")
    p.add_argument("--no-serve", action="store_true", help="export and exit instead of serving")
    p.set_defaults(func=_cmd_view)

    def add_dataset_args(p, frames: int, seed: int, size_help: str) -> None:
        p.add_argument("--dataset", choices=("synthetic", "rellis3d", "rugd"), default="synthetic")
        p.add_argument("--data", type=Path, help="dataset root (RELLIS-3D sequences folder or RUGD root)")
        p.add_argument("--synthetic-frames", type=_positive, default=frames)
        p.add_argument("--input-size", type=_positive, nargs=2, default=[128, 256], metavar=("H", "W"), help=size_help)
        p.add_argument("--domain", default="summer", help="synthetic appearance domain: summer, autumn, dusk")
        p.add_argument("--seed", type=int, default=seed, help="seed of the split, the initialisation and synthetic frames")

    p = sub.add_parser("train-seg", help="train the evidential segmentation network")
    add_dataset_args(p, 400, 1, "network input size (and synthetic frame size)")
    p.add_argument("--out", type=Path, required=True, help="folder for checkpoints, history, metrics and plots")
    p.add_argument("--arch", default=ModelConfig.arch, help="r18-os16 (CPU default), r50-os8 (full size) or torchvision-r50")
    p.add_argument("--width", type=_positive, default=ModelConfig.width, help="channels of the first ResNet stage (64 = standard)")
    p.add_argument("--aspp-channels", type=_positive, default=ModelConfig.aspp_channels)
    p.add_argument("--head", choices=("evidential", "softmax"), default="evidential")
    p.add_argument("--epochs", type=_positive, default=20)
    p.add_argument("--batch-size", type=_positive, default=8)
    p.add_argument("--lr", type=_positive_float, default=2e-3)
    p.add_argument("--kl-schedule", choices=("paper", "release"), default="paper")
    p.add_argument("--val-fraction", type=float, default=0.1)
    p.add_argument("--time-budget-s", type=_positive_float, default=None, help="stop after the epoch that passes this many seconds")
    _renamed_flag(p, "--time-budget", "--time-budget-s", type=_positive_float)
    p.add_argument("--logit-clamp", type=_positive_float, default=10.0, help="evidence = exp(clamp(logit, -c, c))")
    p.add_argument("--normalization", choices=("imagenet", "caffe"), default="imagenet")
    p.add_argument("--backbone-weights", type=Path, help="backbone state dict to start from (nothing is downloaded)")
    p.add_argument("--resume", type=Path, help="checkpoint to continue from")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train_seg)

    p = sub.add_parser("eval-seg", help="2D metrics and calibration plots of a checkpoint on a dataset")
    p.add_argument("checkpoint", type=Path)
    # seed 2: other synthetic frames than training saw (seed 1)
    add_dataset_args(p, 100, 2, "synthetic frame size (the network resizes to its own)")
    p.add_argument("--out", type=Path, help="folder for metrics.json and the plots")
    p.set_defaults(func=_cmd_eval_seg)

    p = sub.add_parser("infer", help="per-frame Dirichlet alpha (float16 .npy) from a trained checkpoint")
    p.add_argument("checkpoint", type=Path)
    p.add_argument("images", type=Path, help="an image or a folder of .jpg/.png images")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batch-size", type=_positive, default=4)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_infer)

    p = sub.add_parser("synth", help="generate a synthetic off-road sequence in the RELLIS-3D layout")
    p.add_argument("--world", default="default", help="the world preset: tiny, demo, default, long (a 2 km drive) or a YAML file "
                                                      "(configs/synthetic/)")
    _renamed_flag(p, "--preset", "--world")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to write")
    p.add_argument("--domain", default=None, help="appearance domain (summer, autumn, dusk); default: the preset's")
    p.add_argument("--seed", type=int, default=None, help="world seed; default: the preset's")
    p.add_argument("--frames", type=_positive, default=None, help="number of frames; default: the preset's")
    p.add_argument("--device", default="cpu", help="Warp device for the ray casting")
    p.add_argument("--format", choices=("folder", "rosbag1", "rosbag2", "mcap"), default="folder",
                   help="folder: the RELLIS-3D layout (default); rosbag1: a ROS 1 .bag; rosbag2: a ROS 2 bag folder (sqlite3); "
                        "mcap: a bare .mcap file (logs need the [ros] extra)")
    p.add_argument("--no-camera", action="store_true", help="LiDAR scans with point labels and poses only: no images (fast)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("check-data", help="report what is missing or inconsistent in sequence folders or robot logs (exit 1 on problems)")
    p.add_argument("paths", nargs="+", type=Path,
                   help="RELLIS-3D-layout folders, or robot logs (.bag, .mcap, .db3, ROS 2 bag folders; read as one sequence) "
                        "with the dataset configs or presets that say their topics (e.g. rellis3d-bag)")
    p.set_defaults(func=_cmd_check_data)

    p = sub.add_parser("project", help="project a sequence's 2D labels onto its LiDAR points (3D ground truth + overlays)")
    p.add_argument("sequence", nargs="+", help="a RELLIS-3D-layout folder, or robot logs with the configs or presets that say their "
                                               "topics (e.g. drive.bag rellis3d-bag)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--zbuffer", action="store_true", help="drop points hidden behind nearer points")
    p.add_argument("--overlays", type=_non_negative, default=3, help="overlay images to write")
    p.add_argument("--color-by", choices=("label", "depth"), default="label", help="overlay points in their label's color or by range")
    _renamed_flag(p, "--colour-by", "--color-by", choices=("label", "depth"))
    p.add_argument("--max-frames", type=_positive, default=None)
    _add_frame_args(p)
    p.set_defaults(func=_cmd_project)

    p = sub.add_parser("train-convbki", help="learn ConvBKI's per-class length scales from a projected, labelled sequence")
    p.add_argument("sequence", type=Path, help="RELLIS-3D-layout sequence with per-point labels")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="folder of per-frame alpha .npy (evsemmap infer output; required)")
    _renamed_flag(p, "--alpha", "--alpha-dir", type=Path)
    p.add_argument("--out", type=Path, required=True, help="length-scale file to write (.json; use as mapping.convbki.lengths_file)")
    p.add_argument("--resolution-m", type=_positive_float, default=0.3, help="voxel size of the map it will be used with (m)")
    _renamed_flag(p, "--resolution", "--resolution-m", type=_positive_float)
    p.add_argument("--epochs", type=_positive, default=15)
    p.add_argument("--window-scans", type=_positive, default=10)
    p.add_argument("--queries", type=_positive, default=4000, help="ground-truth points scored per window")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_train_convbki)

    p = sub.add_parser("experiment", help="run a study from a config: data, network, maps, scores, tables (cached, resumable)")
    p.add_argument("config", help="experiment YAML, or a built-in name (demo, paper-main, paper-robustness, paper-ablation, paper-unseen)")
    p.add_argument("--out", type=Path, default=None, help="results folder (default: results_<name>)")
    p.add_argument("--cache", type=Path, default=None, help="stage cache shared between studies (default: OUT/cache)")
    p.add_argument("--quick", action="store_true", help="the study scaled down by its config's quick section: checks that it runs (CI), numbers not for reading")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_experiment)

    p = sub.add_parser("demo", help="the small study on the synthetic world: from nothing to a comparison table and maps")
    p.add_argument("--out", type=Path, default=Path("evsemmap_demo"), help="results folder (default: evsemmap_demo)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_demo)

    from ..live.commands import add_parsers as add_live_parsers  # evsemmap live, evsemmap replay (imports no zenoh)

    add_live_parsers(sub, positive=_positive, positive_float=_positive_float, port=_port)

    p = sub.add_parser("info", help="summarise a map file or a map store")
    p.add_argument("map", type=Path)
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("dump-config", help="print the resolved configuration (mapping, dataset, terrain layers and costs)")
    p.add_argument("configs", nargs="*")
    p.add_argument("--method", default=None)
    p.add_argument("--costs", type=Path, default=None, help="a terrain cost file laid over the default table (as evsemmap layers --costs)")
    p.set_defaults(func=_cmd_dump_config)
    return parser


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    # A command's user wants what is wrong in one line, not the source line that noticed it; tqdm.write keeps
    # a progress bar on screen intact.
    from tqdm import tqdm

    tqdm.write(f"evsemmap: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run ``evsemmap`` with ``argv`` (default: the process's arguments); returns the exit code. A
    ConfigError, ValueError or OSError ends in one line on stderr naming the file, key or value, with exit
    code 2; Ctrl-C in 130. A warning is one line, ``evsemmap: warning: ...``."""
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings():
        warnings.showwarning = _warning_line
        return _run(args)


def _run(args) -> int:
    try:
        return args.func(args)
    except (ConfigError, ValueError, OSError) as exc:  # OSError: missing or unreadable files, named by the OS
        # One line, even for messages that carry their own line breaks (YAML parser errors).
        text = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        print(f"evsemmap: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("evsemmap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

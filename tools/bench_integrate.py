"""Integration benchmark on the fixed workload ../shared/data/bench/rellis_like_30scans.npz.

Times Mapper.integrate over all 30 scans (1.8M points) for each method, next to the vectorised numpy
implementation (evsemmap_warp/reference/scatter.py driven by the same per-scan rules) run in the same
process, and next to the original C++ figures: those stored with the workload (its .json), or, with
--cpp-timings, the originals timed on this machine beside this tool (docs/cpp_side_by_side.json):

* ``ebs``, ``s-bki``: the clean algorithm with the RELLIS-3D preset (paper Table I);
* ``convbki``, ``see-csom``, ``dempster``: the comparison methods in the same engine, same preset
  (ConvBKI with its initial 0.5 m lengths on the 5x5x5 stencil);
* ``s-bki-compat@frF``: the sbki compatibility mode with the C++ S-BKI benchmark parameters
  (r 0.2, block depth 2, ell 0.3, sf2 10, prior 0.001, VoxelGrid 0.1, free_resolution F) and the
  workload's S-BKI input labels (its ``label`` array, which the C++ runs read): the same map semantics
  as the C++ rows, so the ratio against them is like for like;
* ``ebs-release``, ``dempster-release``: the release mode (configs/presets/release.yaml)
  against the released EvSemMap C++ (its counts after the cut, after "ds" and its cells are checked).

The like-for-like rows run at 1 and 2 worker threads (``@1t``, ``@2t``): ``@1t`` is compared with the
C++ on 1 thread, ``@2t`` with the C++ at its best thread count (1 or 2; its 2-thread runs are often
slower). ``@1t`` rows call ``Mapper.integrate`` scan by scan, throughput = input points / summed wall
time of those calls; ``@2t`` rows and the clean rows (2 workers) map through ``Mapper.integrate_many``
(the next scans' host work overlaps this scan's kernels), throughput = input points / its wall time.
Scans are in memory (loading excluded); median of --repeats fresh maps after one warm-up (kernel
compile); the numpy twin likewise, at one thread (numpy's scatter does not thread). The rows run in
rounds, one repeat of every row per round (``time_rows``). The map's read-out that a query needs
(``Mapper.voxels()``: the shards merged, the summary) is timed apart, after each repeat
(``summary_seconds``). A C++ rate is input points / the median of its runs' summed insert
times. The cell counts, and the release's counts after the cut and after "ds", must equal the C++'s, or
the tool exits 1 (after writing its record, which lists the mismatch).

The run's record (docs/bench/bench_integrate-<UTC>.json, tools/bench_record.py) holds every row's
repeats, counts, rates and ratios and the C++ rates they were set against; ``python tools/perf_records.py
table RECORD`` writes docs/performance.md's table from it. The last line printed is one JSON object: row
name -> input points per second. ``--scans N`` maps the first N scans only (a trial of the tool: its
counts cannot match the C++'s; ``--record-dir`` then keeps its record out of docs/bench).

    python tools/bench_integrate.py [--repeats 3] [--device cpu] [--plot bench.png] [--cpp-timings docs/cpp_side_by_side.json]
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evsemmap_warp.config import Compat, Kernel, MappingConfig, Media, SbkiSettings, load_config  # noqa: E402
from evsemmap_warp.data.datasets import open_dataset  # noqa: E402
from evsemmap_warp.core.integrators import uncertainty_quantile_mask  # noqa: E402
from evsemmap_warp.kernels import scatter as sc  # noqa: E402
from evsemmap_warp.core.mapper import Mapper  # noqa: E402
from evsemmap_warp.reference import scatter as ref  # noqa: E402

sys.path.insert(0, str(REPO / "tools"))
from bench_record import RECORDS, write_record  # noqa: E402

DATASET = REPO / "configs/datasets/bench_rellis_like.yaml"
PRESET = REPO / "configs/presets/rellis3d.yaml"
CPP_SBKI = {"0.5": "fr0.5", "4": "fr4.0", "100": "fr100"}  # + "_t1" / "_t2" in the workload's .json


def load_scans():
    run = load_config([PRESET, DATASET], method="ebs")
    dataset = open_dataset(run.dataset)
    scans = list(dataset)
    return dataset, scans


def sbki_labels(dataset) -> list[np.ndarray]:
    """The workload's S-BKI input labels per scan: its ``label`` array, the classes the C++ S-BKI runs
    were given. (The argmax of the evidential alphas differs from it for 1.8 % of the points, where the
    second class's evidence is the larger.)"""
    offsets = dataset.offsets
    return [dataset.data["label"][offsets[i]:offsets[i + 1]].astype(np.int64) for i in range(len(dataset))]


def read_cpp_figures(path: Path) -> tuple[dict, dict, str]:
    """(S-BKI results, EvSemMap results, where they come from) from the workload's .json or a file in its
    layout; a missing or malformed file gives one line naming it and exit code 2."""
    try:
        cpp = json.loads(path.read_text())
        sbki, evsemmap = cpp["sbki_original"]["results"], cpp["evsemmap"]["results"]
        for results, keys in ((sbki, [f"{k}_t{t}" for k in CPP_SBKI.values() for t in (1, 2)]),
                              (evsemmap, [f"{m}_t{t}" for m in RELEASE_METHODS for t in (1, 2)])):
            for key in keys:
                if not results[key]["totals"] or min(results[key]["totals"]) <= 0 or results[key]["cells"] <= 0:
                    raise ValueError(f"{key}: totals and cells must be positive")
        for method in RELEASE_METHODS:  # the release rows' counts, which the run is checked against
            if min(evsemmap[f"{method}_t1"]["after_unc"], evsemmap[f"{method}_t1"]["after_ds"]) <= 0:
                raise ValueError(f"{method}_t1: after_unc and after_ds must be positive")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not the originals' timings in the workload .json's layout ({type(exc).__name__}: {exc})") from None
    source = cpp.get("measured", {}).get("summary", f"the figures stored with the workload ({path.name})")
    return sbki, evsemmap, source


def compat_config(free_resolution: float) -> MappingConfig:
    return MappingConfig(
        method="s-bki", kernel=Kernel.SPARSE, media=Media.ONEHOT, adaptive_length=False, uncertainty_threshold=False,
        compat=Compat.SBKI, resolution_m=0.2, length_m=0.3, sigma0=10.0, prior=0.001,
        sbki=SbkiSettings(block_depth=2, ds_resolution_m=0.1, free_resolution_m=free_resolution, max_range_m=None),
    )


# The paper's method, its baselines in this engine, and the Dempster-Shafer variant, same workload.
METHODS = ("ebs", "s-bki", "convbki", "see-csom", "dempster")
RELEASE_PRESET = REPO / "configs/presets/release.yaml"
RELEASE_METHODS = ("ebs", "dempster")


def release_counts(config: MappingConfig, scans) -> int:
    """Points after the release's uncertainty cut, summed over the scans (untimed; a check)."""
    from evsemmap_warp.core.integrators import ReleaseCompatIntegrator
    from evsemmap_warp.core.mapper import prepare_payload

    integrator = ReleaseCompatIntegrator(config)
    return sum(integrator.training_points(prepare_payload(s.points, s.payload, "alpha", 9), s.sensor_origin)[1]["after_cut"] for s in scans)


class MapperRow:
    """One mapper row of the table: ``warm_up`` once (kernel compile), then each ``run`` times one repeat on
    a fresh map, ``result`` their median (``time_rows`` runs the rows in rounds)."""

    def __init__(self, config: MappingConfig, scans, payloads, payload_type, device, workers=None, pipelined=False):
        self.config, self.scans, self.payloads, self.payload_type = config, scans, payloads, payload_type
        self.device, self.workers, self.pipelined = device, workers, pipelined
        self.runs, self.summaries, self.first = [], [], None

    def warm_up(self) -> None:
        scan, payload = self.scans[0], self.payloads[0]
        warm = Mapper(self.config, 9, device=self.device, workers=self.workers)
        warm.integrate(scan.points[:1000], payload[:1000], payload_type=self.payload_type, sensor_origin=scan.sensor_origin)

    def run(self, progress) -> None:
        mapper = Mapper(self.config, 9, device=self.device, workers=self.workers)
        if self.pipelined:
            items = [SimpleNamespace(points=s.points, payload=p, payload_type=self.payload_type, sensor_origin=s.sensor_origin)
                     for s, p in zip(self.scans, self.payloads)]
            start = time.perf_counter()
            all_stats = mapper.integrate_many(items, progress=lambda scan, _: progress.update(len(scan.points)))
            elapsed = time.perf_counter() - start
        else:
            elapsed, all_stats = 0.0, []
            for scan, payload in zip(self.scans, self.payloads):
                start = time.perf_counter()
                all_stats.append(mapper.integrate(scan.points, payload, payload_type=self.payload_type, sensor_origin=scan.sensor_origin))
                elapsed += time.perf_counter() - start
                progress.update(len(scan.points))
        self.runs.append(elapsed)
        start = time.perf_counter()
        mapper.voxels()
        self.summaries.append(time.perf_counter() - start)
        if self.first is None:
            counts = mapper.state_counts()
            self.first = {
                "voxel_updates": sum(s.voxel_updates for s in all_stats), "kept_or_training_points": sum(s.kept_points for s in all_stats),
                "voxels": mapper.voxel_count, "free": counts["FREE"], "occupied": counts["OCCUPIED"],
                "bytes_per_voxel": round(mapper.device_bytes / max(mapper.voxel_count, 1), 1), "workers": len(mapper.shards),
            }
        # Each map is released before the next one is made: memory the process has not touched before
        # faults in more slowly, which would make every repeat after the first slower than the first.
        del mapper, all_stats
        gc.collect()

    def result(self) -> dict:
        return self.first | {"seconds": statistics.median(self.runs), "all_seconds": [round(r, 3) for r in self.runs],
                             "summary_seconds": statistics.median(self.summaries), "all_summary_seconds": [round(r, 4) for r in self.summaries]}


class NumpyRow:
    """The numpy twin's row, timed like a ``MapperRow``: a warm-up on one scan, then one repeat per ``run``."""

    def __init__(self, config: MappingConfig, scans, payloads):
        self.config, self.scans, self.payloads = config, scans, payloads
        self.runs = []

    def warm_up(self) -> None:
        numpy_run(self.config, [self.scans[0]], [self.payloads[0]])

    def run(self, progress) -> None:
        self.runs.append(numpy_run(self.config, self.scans, self.payloads))
        progress.update(sum(len(s.points) for s in self.scans))

    def result(self) -> dict:
        return self.runs[0] | {"seconds": statistics.median(r["seconds"] for r in self.runs), "all_seconds": [round(r["seconds"], 3) for r in self.runs]}


def time_rows(rows: dict, repeats: int, progress) -> dict:
    """Each row (name -> ``MapperRow`` or ``NumpyRow``) warmed up, then ``repeats`` rounds, each running every
    row once in order; name -> its ``result``. In rounds rather than row by row: a shared VM's slower stretch
    (minutes long on this project's VMs) then falls on a repeat of every row, which the medians drop,
    rather than on all of one row's repeats."""
    for row in rows.values():
        row.warm_up()
    for _ in range(repeats):
        for row in rows.values():
            row.run(progress)
    return {name: row.result() for name, row in rows.items()}


def numpy_run(config: MappingConfig, scans, payloads):
    """The same clean-mode rules in vectorised numpy: threshold, lengths, scatter, one final merge."""
    start = time.perf_counter()
    parts_index, parts_evidence, updates = [], [], 0
    for scan, alpha in zip(scans, payloads):
        total = alpha.sum(axis=1, dtype=np.float64)
        u, p = 9.0 / total, alpha / total[:, None]
        keep = uncertainty_quantile_mask(u, config.keep_quantile)[0] if config.uncertainty_threshold else np.ones(len(u), bool)
        lengths = config.length_m * config.beta * np.exp(1 - config.gamma * u) if config.adaptive_length else np.full(len(u), config.length_m)
        onehot = config.media is Media.ONEHOT
        res = ref.scatter_points(scan.points[keep], np.argmax(alpha[keep], 1) if onehot else None, None if onehot else p[keep],
                                 lengths[keep], u[keep], None, sc.MODE_RADIUS, config.resolution_m, 0.0, config.sigma0, 1, 9)
        parts_index.append(res.voxel_index)
        parts_evidence.append(res.alpha_increment)
        updates += res.update_count
    uniq, inverse = ref.unique_rows(np.concatenate(parts_index))
    stacked = np.concatenate(parts_evidence)
    evidence = np.stack([np.bincount(inverse, weights=stacked[:, k], minlength=len(uniq)) for k in range(9)], axis=1)
    return {"seconds": time.perf_counter() - start, "voxel_updates": updates, "voxels": len(uniq)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--free-resolutions", nargs="*", default=["100", "4", "0.5"], help="S-BKI compat free_resolution values (C++ has 0.5, 4, 100)")
    parser.add_argument("--skip-numpy", action="store_true")
    parser.add_argument("--plot", type=Path, default=None, help="write a bar chart of the throughputs (needs matplotlib)")
    parser.add_argument("--cpp-timings", type=Path, default=None,
                        help="the originals' timings measured on this machine, in the layout of the workload's .json "
                             "(e.g. docs/cpp_side_by_side.json), instead of the workload's stored figures")
    parser.add_argument("--scans", type=int, default=None, help="map the first N scans only (a trial: the counts cannot match the C++'s)")
    parser.add_argument("--record-dir", type=Path, default=RECORDS, help="where the run's record goes (default docs/bench)")
    args = parser.parse_args()
    started = time.time()

    if not DATASET.exists() or not (REPO.parent / "shared/data/bench/rellis_like_30scans.npz").exists():
        print("the benchmark workload ../shared/data/bench/rellis_like_30scans.npz is absent; nothing to measure", file=sys.stderr)
        return 1
    dataset, scans = load_scans()
    labels = sbki_labels(dataset)
    if args.scans is not None:
        scans, labels = scans[:args.scans], labels[:args.scans]
    n_points = sum(len(s.points) for s in scans)
    cpp_path = args.cpp_timings or dataset.path.with_suffix(".json")
    try:
        sbki, evsemmap, cpp_source = read_cpp_figures(cpp_path)
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    thread_counts = (1, 2) if args.device == "cpu" else (1,)
    like_for_like = [f"s-bki-compat@fr{fr}" for fr in args.free_resolutions] + [f"{m}-release" for m in RELEASE_METHODS]
    timed = table_rows(args, scans, labels, thread_counts)
    with tqdm(total=len(timed) * args.repeats * n_points, unit="pt", unit_scale=True, desc="integrating", file=sys.stderr) as progress:
        rows = time_rows(timed, args.repeats, progress)
        release_after_cut = {m: release_counts(load_config([RELEASE_PRESET], method=m).mapping, scans) for m in RELEASE_METHODS}

    cpp_rate, cpp_row = cpp_rates(sbki, evsemmap, n_points)
    print(f"{n_points:,} input points in {len(scans)} scans, device {args.device}, median of {args.repeats}")
    print(f"C++ figures: {cpp_source}")
    print(f"{'row':28s} {'s':>7s} {'input pts/s':>12s} {'voxel upd/s':>12s} {'voxels':>9s} {'B/voxel':>8s}  vs numpy  "
          f"vs C++ (@1t: C++ 1 thread; @2t and others: C++ at its best of 1/2 threads)")
    references = compare_rows(rows, n_points, cpp_rate)
    throughput = {name: round(row["input_points_per_s"]) for name, row in rows.items()}
    for name, row in rows.items():
        vs_numpy = f"x{row['vs_numpy']:.1f}" if "vs_numpy" in row else ""
        vs_cpp = f"x{row['vs_cpp']:.1f} ({row['cpp_points_per_s'] / 1e3:.0f}k)" if "vs_cpp" in row else ""
        if name == "ebs":
            vs_cpp += " other map semantics"
        print(f"{name:28s} {row['seconds']:7.2f} {row['input_points_per_s']:12,.0f} {row['voxel_updates_per_s']:12,.0f} "
              f"{row['voxels']:9,d} {row.get('bytes_per_voxel', float('nan')):8.1f}  {vs_numpy:8s}  {vs_cpp}")
    problems = [problem for name in like_for_like
                for problem in check_counts(name, rows[f"{name}@{thread_counts[-1]}t"], cpp_row[name], release_after_cut)]
    print("details: " + json.dumps(rows, default=lambda o: None))
    if args.plot:
        plot(throughput, references, args.plot)
    results = integration_results(rows, scans=len(scans), n_points=n_points, device=args.device, repeats=args.repeats,
                                  free_resolutions=args.free_resolutions, thread_counts=thread_counts, like_for_like=like_for_like,
                                  cpp_path=cpp_path, cpp_source=cpp_source, cpp_rate=cpp_rate, release_after_cut=release_after_cut,
                                  problems=problems)
    print(write_record("bench_integrate", results, started=started, folder=args.record_dir))
    print(json.dumps(throughput))
    if problems:
        print("MISMATCH: " + "; ".join(problems), file=sys.stderr)
        return 1
    return 0


def table_rows(args, scans, labels, thread_counts) -> dict:
    """Name -> the row that times it: each method with the RELLIS-3D preset (and the numpy twin of the radius
    rules unless --skip-numpy), then the like-for-like modes at each thread count."""
    alphas = [s.payload for s in scans]
    timed = {}
    for method in METHODS:
        cfg = load_config([PRESET], method=method).mapping
        timed[method] = MapperRow(cfg, scans, alphas, "alpha", args.device, pipelined=True)
        if not args.skip_numpy and method in ("ebs", "s-bki"):  # the numpy twin times the radius rules
            timed[f"numpy:{method}"] = NumpyRow(cfg, scans, alphas)
    for threads in thread_counts:
        for fr in args.free_resolutions:
            timed[f"s-bki-compat@fr{fr}@{threads}t"] = MapperRow(compat_config(float(fr)), scans, labels, "label", args.device, workers=threads,
                                                                 pipelined=threads > 1)
        for method in RELEASE_METHODS:
            timed[f"{method}-release@{threads}t"] = MapperRow(load_config([RELEASE_PRESET], method=method).mapping, scans, alphas, "alpha",
                                                              args.device, workers=threads, pipelined=threads > 1)
    return timed


def cpp_rates(sbki: dict, evsemmap: dict, n_points: int) -> tuple[dict, dict]:
    """(the C++ rates, (row, threads) -> input points / the median summed insert time, at 1 and 2 threads;
    row -> the C++'s 1-thread results, whose counts the run is checked against)."""
    cpp_rate, cpp_row = {}, {}
    for name, results, key in [(f"{m}-release", evsemmap, m) for m in RELEASE_METHODS] + [(f"s-bki-compat@fr{fr}", sbki, k) for fr, k in CPP_SBKI.items()]:
        for t in (1, 2):
            cpp_rate[(name, t)] = n_points / statistics.median(results[f"{key}_t{t}"]["totals"])
        cpp_row[name] = results[f"{key}_t1"]
    cpp_rate[("ebs", 2)] = max(cpp_rate[("ebs-release", 1)], cpp_rate[("ebs-release", 2)])  # other map semantics
    return cpp_rate, cpp_row


def check_counts(name: str, row: dict, want_row: dict, release_after_cut: dict) -> list[str]:
    """Print a like-for-like row's counts beside the C++'s; the mismatches, one line each."""
    problems = []
    line = f"{name}: {row['voxels']:,} cells (C++ {want_row['cells']:,}), FREE {row['free']:,}, OCCUPIED {row['occupied']:,}"
    if "free" in want_row:
        line += f" (C++ {want_row['free']:,} and {want_row['occupied']:,})"
    if name.endswith("-release"):
        want = (want_row["after_unc"], want_row["after_ds"])
        got = (release_after_cut[name.removesuffix("-release")], row["kept_or_training_points"])
        line += f"; after the cut {got[0]:,} (C++ {want[0]:,}), after ds {got[1]:,} (C++ {want[1]:,})"
        if got != want:
            problems.append(f"{name}: counts {got} differ from the C++'s {want}")
    if row["voxels"] != want_row["cells"]:
        problems.append(f"{name}: {row['voxels']:,} cells, the C++ has {want_row['cells']:,}")
    print(line)
    return problems


def compare_rows(rows: dict, n_points: int, cpp_rate: dict) -> dict:
    """Add to each row its rates (input points/s, voxel updates/s) and its comparisons: with the numpy
    twin's row of the same method (``vs_numpy``, a time ratio) and with the C++ (``cpp_points_per_s``,
    ``vs_cpp``, ``cpp_threads``): an @1t row against the C++ on 1 thread, the others against the C++ at its
    best of 1 and 2 threads (``cpp_rate``: (row name without @, threads) -> input points/s; the clean
    ``ebs`` is set beside the release's, ``cpp_semantics`` "other"). Returns row -> the C++ rate it was
    set against."""
    best_threads = {name: max((1, 2), key=lambda t: cpp_rate.get((name, t), 0)) for name, _ in cpp_rate}
    if "ebs-release" in best_threads:
        best_threads["ebs"] = best_threads["ebs-release"]
    references = {}
    for name, row in rows.items():
        row["input_points_per_s"] = n_points / row["seconds"]
        row["voxel_updates_per_s"] = row["voxel_updates"] / row["seconds"]
        if f"numpy:{name}" in rows:
            row["vs_numpy"] = rows[f"numpy:{name}"]["seconds"] / row["seconds"]
        base, _, threads = name.rpartition("@")
        if threads == "1t":
            reference, label = cpp_rate.get((base, 1)), "1 thread"
        else:
            base = base if threads == "2t" else name
            reference = max(cpp_rate.get((base, 1), 0), cpp_rate.get((base, 2), 0)) or None
            best = best_threads.get(base, 1)
            label = f"its best: {best} thread{'s' if best > 1 else ''}"
        if reference:
            references[name] = reference
            row["cpp_points_per_s"], row["vs_cpp"], row["cpp_threads"] = reference, row["input_points_per_s"] / reference, label
            if name == "ebs":
                row["cpp_semantics"] = "other"  # the release's rate, for scale: not the same map
    return references


def integration_results(rows: dict, *, scans: int, n_points: int, device: str, repeats: int, free_resolutions, thread_counts,
                        like_for_like, cpp_path: Path, cpp_source: str, cpp_rate: dict, release_after_cut: dict, problems: list) -> dict:
    """The results part of a run's record: the workload, the run's settings, the rows (as ``compare_rows``
    left them), the C++ rates and where they come from, the release's counts after its cut, and the
    mismatches against the C++'s counts."""
    cpp_file = cpp_path.resolve().relative_to(REPO).as_posix() if cpp_path.resolve().is_relative_to(REPO) else str(cpp_path)
    return {
        "workload": {"file": "../shared/data/bench/rellis_like_30scans.npz", "scans": scans, "input_points": n_points},
        "device": device, "repeats": repeats, "order": "rounds: one repeat of every row per round",
        "free_resolutions": list(free_resolutions), "thread_counts": list(thread_counts),
        "methods": list(METHODS), "like_for_like": list(like_for_like),
        "cpp": {"file": cpp_file, "summary": cpp_source, "points_per_s": {f"{name}@{t}t": rate for (name, t), rate in cpp_rate.items()}},
        "release_after_cut": release_after_cut, "rows": rows, "problems": problems,
    }


def plot(throughput, baselines, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(throughput)
    fig, ax = plt.subplots(figsize=(9, 6))
    ax.barh(names, [throughput[n] / 1e6 for n in names], color=["#3b7dd8" if not n.startswith("numpy") else "#999999" for n in names], label="evsemmap_warp / numpy")
    cpp_names = [n for n in names if n in baselines]
    ax.scatter([baselines[n] / 1e6 for n in cpp_names], cpp_names, color="#d83b3b", zorder=3, label="original C++ (1 thread for @1t rows, else its best)")
    ax.set_xlabel("input points per second (millions)")
    ax.set_title("Integration throughput on rellis_like_30scans (1.8M points)")
    ax.legend(loc="center right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())

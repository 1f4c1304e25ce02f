"""The kernel-level performance study: writes docs/kernel_study.md and its plots (docs/kernel_study/).

    python tools/kernel_study.py [--device cpu|cuda] [--quick] [--out docs]

Everything in the report comes from this one run (no hand-edited numbers): warm-up launch first,
then the median of --repeats. Its conclusions are computed from the run's figures (a sentence that the
figures do not support is not written). The run's record (every row, the figures derived from them and
the machine; tools/bench_record.py) goes to <out>/bench/kernel_study-<UTC>.json, docs/bench by
default, and the report names it. Workload: the shared benchmark scans (../shared/data/bench) when
present, else LiDAR-like synthetic scans (rings of points on a ground plane with a few walls) made here.

1. Integration strategies, each an engine backend with the same map out (the tool checks that and
   exits 1 otherwise): the atomic scatter, sort-then-reduce and the gather through ``wp.HashGrid``
   (``mapping.clean.scatter_strategy``), and for the release mode its block gather; baselines in the same
   run: the numpy twin and torch's ``index_add_`` reduction of the same expanded (voxel,
   contribution) pairs (both one thread).
2. The compatibility modes' gather kernels form by form (branch-free or per-cell branches, both
   compiled to vector code over a block's cells; prefetch on or off).
3. Microbenchmarks: hash insert and find at load factors 0.25-0.95 with uniform and LiDAR-like keys;
   keyed row adds in float32 vs float64; a streaming copy (the bandwidth roof).
4. Scaling: points per scan, classes K, kernel length / resolution, worker threads.
5. A roofline estimate per strategy: modelled bytes per voxel update x achieved update rate against
   the streaming bandwidth.
``--quick`` uses small sizes and one repeat (under a minute; the test suite runs it).

``--index-forms`` times, instead, the radix sort's scatter pass in its four index forms (``while`` or range
loop, indices through the sign-bit mask ``kernels.indexing.nonnegative`` or as read; rounds interleaved,
ns per value) and prints them: the one-thread host kernels' form is a choice per CPU model.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from evsemmap_warp.config import CleanSettings, ScatterStrategy, load_config  # noqa: E402
from evsemmap_warp.core.mapper import Mapper  # noqa: E402
from evsemmap_warp.core.warp_runtime import init_warp, resolve_device  # noqa: E402
from evsemmap_warp.reference import scatter as ref  # noqa: E402
from evsemmap_warp.voxel_keys import pack_voxel_keys  # noqa: E402

wp = init_warp()
from bench_record import machine, write_record  # noqa: E402

from evsemmap_warp.kernels import hash_table as ht  # noqa: E402
from evsemmap_warp.kernels import microbench as mb  # noqa: E402

PRESET = REPO / "configs/presets/rellis3d.yaml"
RELEASE = REPO / "configs/presets/release.yaml"
STRATEGIES = ("atomic", "sorted", "gather")
BENCH = REPO / "configs/datasets/bench_rellis_like.yaml"


def timed(fn, repeats: int) -> float:
    fn()  # warm-up (compiles, first-touch allocations)
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - start)
    return statistics.median(runs)


def synthetic_scans(n_scans: int, points_per_scan: int, num_classes: int = 9, seed: int = 0):
    """LiDAR-like scans: 64 rings on a ground plane 1.2 m below the sensor, walls beyond 15 m."""
    rng = np.random.default_rng(seed)
    scans = []
    for s in range(n_scans):
        origin = np.array([0.8 * s, 0.0, 1.2])
        az = rng.uniform(0, 2 * np.pi, points_per_scan)
        el = np.deg2rad(rng.uniform(-22.5, -1.0, points_per_scan))
        r = np.minimum(1.2 / np.tan(-el), 15 + rng.uniform(0, 3, points_per_scan))
        pts = origin + np.column_stack([r * np.cos(az), r * np.sin(az), -np.minimum(r * np.tan(-el), 1.2) + rng.normal(0, 0.02, points_per_scan)])
        alpha = np.ones((points_per_scan, num_classes))
        alpha[np.arange(points_per_scan), rng.integers(1, num_classes, points_per_scan)] += rng.gamma(2.0, 8.0, points_per_scan)
        scans.append((pts, alpha, origin))
    return scans


def load_workload(quick: bool):
    if BENCH.exists() and (REPO.parent / "shared/data/bench/rellis_like_30scans.npz").exists():
        from evsemmap_warp.data.datasets import open_dataset

        run = load_config([PRESET, BENCH], method="ebs")
        scans = [(s.points, s.payload, s.sensor_origin) for s in open_dataset(run.dataset)]
        name = "the shared benchmark workload (rellis_like_30scans)"
    else:
        scans = synthetic_scans(30, 60_000)
        name = "synthetic LiDAR-like scans (../shared absent)"
    if quick:
        scans = [(p[:8000], a[:8000], o) for p, a, o in scans[:3]]
        name += ", --quick: 3 scans x 8,000 points"
    else:
        scans = scans[:10]  # the numpy twin's pair expansion is the slow part: 10 scans keep the run within minutes
        name += f", first 10 scans ({sum(len(p) for p, _, _ in scans):,} points)"
    return scans, name


def run_mapper(config, scans, device, workers, num_classes=9):
    mapper = Mapper(config, num_classes, device=device, workers=workers)
    updates = 0
    for pts, alpha, origin in scans:
        updates += mapper.integrate(pts, alpha, payload_type="alpha", sensor_origin=origin).voxel_updates
    return mapper, updates


def strategies(scans, device, repeats, workers_list):
    """Same map from each strategy; times at each thread count."""
    rows, maps, problems = [], {}, []
    n_points = sum(len(p) for p, _, _ in scans)
    for method in ("s-bki", "prob"):
        base = load_config([PRESET], method=method).mapping
        for strategy in STRATEGIES:
            cfg = dataclasses.replace(base, clean=CleanSettings(ScatterStrategy(strategy)))
            for workers in workers_list:
                holder = {}
                seconds = timed(lambda: holder.update(result=run_mapper(cfg, scans, device, workers)), repeats)
                mapper, updates = holder["result"]
                maps[(method, strategy, workers)] = mapper.voxels().arrays
                rows.append({"method": method, "strategy": strategy, "workers": workers, "seconds": seconds,
                             "points_per_s": n_points / seconds, "updates": updates, "updates_per_s": updates / seconds,
                             "voxels": mapper.voxel_count})
        reference = maps[(method, "atomic", workers_list[0])]
        for key, arrays in maps.items():
            if key[0] == method and (not np.array_equal(arrays.index, reference.index)
                                     or not np.allclose(arrays.rows(), reference.rows(), rtol=1e-10, atol=1e-12)):
                problems.append(f"{key}: map differs from the atomic scatter's")
        rows.append(numpy_and_torch(method, base, scans, repeats, n_points))  # one thread, same rules
    for method in ("ebs", "dempster"):
        cfg = load_config([RELEASE], method=method).mapping
        for workers in workers_list:
            holder = {}
            seconds = timed(lambda: holder.update(result=run_mapper(cfg, scans, device, workers)), repeats)
            mapper, updates = holder["result"]
            rows.append({"method": f"{method} (release mode)", "strategy": "block gather", "workers": workers, "seconds": seconds,
                         "points_per_s": n_points / seconds, "updates": updates, "updates_per_s": updates / seconds, "voxels": mapper.voxel_count})
    return rows, problems


# The compatibility modes' gather kernels in each form: (kernel, form, factory options); the first form
# of each kernel is the engine's.
GATHER_FORMS = (
    ("S-BKI gather (sbki mode, free_res 0.5)", "per-cell branches + prefetch", {"branch_free": False, "prefetch": True}),
    ("S-BKI gather (sbki mode, free_res 0.5)", "per-cell branches", {"branch_free": False, "prefetch": False}),
    ("S-BKI gather (sbki mode, free_res 0.5)", "branch-free + prefetch", {"branch_free": True, "prefetch": True}),
    ("S-BKI gather (sbki mode, free_res 0.5)", "branch-free", {"branch_free": True, "prefetch": False}),
    ("S-BKI gather (sbki mode, free_res 0.5)", "per-cell branches + prefetch, near-face masks ignored", {"near_faces": False}),
    ("release gather (ebs, release mode)", "branch-free + prefetch", {"prefetch": True}),
    ("release gather (ebs, release mode)", "branch-free", {"prefetch": False}),
)


def gather_forms(scans, device, repeats):
    """The launches of the compatibility modes (the gather kernel, its table growth) for each kernel form,
    one thread, from the same prepared scans; every form must give the same map bit for bit."""
    import functools

    from bench_integrate import compat_config

    from evsemmap_warp.kernels import block_gather, release

    rows, problems, reference = [], [], {}
    for kernel_name, form, options in GATHER_FORMS:
        sbki = kernel_name.startswith("S-BKI")
        config = compat_config(0.5) if sbki else load_config([RELEASE], method="ebs").mapping
        preparing = Mapper(config, 9, device=device, workers=1)
        preparing.integrator.gather_kernel = functools.partial(block_gather.gather_sbki_kernel if sbki else release.gather_release_kernel, **options)
        launches = [preparing.prepare(pts, np.argmax(alpha, axis=1) if sbki else alpha, payload_type="label" if sbki else "alpha",
                                      sensor_origin=origin)
                    for pts, alpha, origin in scans]
        holder = {}

        def run():
            mapper = Mapper(config, 9, device=device, workers=1, origin=preparing.origin)
            holder["updates"] = sum(mapper.launch(launch).voxel_updates for launch in launches)
            holder["mapper"] = mapper

        seconds = timed(run, repeats)
        arrays = holder["mapper"].voxels().arrays
        if kernel_name not in reference:
            reference[kernel_name] = (arrays, seconds)
        first, first_seconds = reference[kernel_name]
        if not (np.array_equal(arrays.index, first.index) and np.array_equal(arrays.rows(), first.rows())):
            problems.append(f"{kernel_name}, {form}: map differs from the engine's form")
        rows.append({"kernel": kernel_name, "form": form, "seconds": seconds, "updates_per_s": holder["updates"] / seconds,
                     "relative": seconds / first_seconds})
    return rows, problems


def numpy_and_torch(method, config, scans, repeats, n_points):
    """The numpy twin's scatter (expand pairs, unique, add.at) and torch.index_add_ on its pairs."""
    prepared = []
    for pts, alpha, _ in scans:
        total = alpha.sum(axis=1)
        u, p = alpha.shape[1] / total, alpha / total[:, None]
        onehot = config.media.value == "onehot"
        lengths = np.full(len(pts), config.length_m) if not config.adaptive_length else config.length_m * config.beta * np.exp(1 - config.gamma * u)
        prepared.append((pts, np.argmax(alpha, 1) if onehot else None, None if onehot else p, lengths, u))

    def numpy_run():
        for pts, labels, probs, lengths, u in prepared:
            ref.scatter_points(pts, labels, probs, lengths, u, None, ref.MODE_RADIUS, config.resolution_m, 0.0, config.sigma0, 1, alpha_k(scans))

    seconds = timed(numpy_run, repeats)
    row = {"method": method, "strategy": "numpy twin (1 thread)", "workers": 1, "seconds": seconds, "points_per_s": n_points / seconds}
    try:
        import torch
    except ImportError:
        return row
    torch.set_num_threads(1)
    from evsemmap_warp.reference import sorted_scatter as sref

    pairs = []
    for pts, labels, probs, lengths, u in prepared:
        keys, point_id, weight = sref.expand_pairs(pts, lengths, config.resolution_m, 0.0, config.sigma0)
        y = np.eye(alpha_k(scans))[labels] if labels is not None else probs
        uniq, inverse = np.unique(keys, return_inverse=True)
        pairs.append((torch.from_numpy(inverse.reshape(-1)), torch.from_numpy(weight[:, None] * y[point_id]), len(uniq)))

    def torch_run():
        for inverse, contributions, n in pairs:
            torch.zeros((n, contributions.shape[1]), dtype=torch.float64).index_add_(0, inverse, contributions)

    row["torch_index_add_seconds"] = timed(torch_run, repeats)
    return row


def alpha_k(scans) -> int:
    return scans[0][1].shape[1]


def hash_microbench(device, quick, repeats):
    """Insert and find rates at load factors, uniform random keys and LiDAR-like (spatially clustered) keys."""
    capacity = 1 << (16 if quick else 22)
    rng = np.random.default_rng(1)
    out = []
    for kind in ("uniform", "lidar-like"):
        for load in (0.25, 0.5, 0.75, 0.9, 0.95):
            n = int(capacity * load)
            if kind == "uniform":
                index = rng.integers(-(1 << 19), 1 << 19, (n, 3))
            else:  # a ground surface: neighbouring voxels, as a scan's keys arrive
                side = int(np.sqrt(n)) + 1
                gx, gy = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
                index = np.column_stack([gx.ravel(), gy.ravel(), (np.sin(gx.ravel() / 7.0) * 3).astype(int)])[:n]
            keys = wp.array(np.unique(pack_voxel_keys(index)), dtype=wp.int64, device=device)
            m = keys.shape[0]
            rows = wp.empty(m, dtype=int, device=device)

            def insert():
                table = wp.full(capacity, ht.EMPTY_KEY, dtype=wp.int64, device=device)
                slot_rows = wp.zeros(capacity, dtype=int, device=device)
                count = wp.zeros(1, dtype=int, device=device)
                wp.launch(ht.insert_keys, dim=m, inputs=[keys, ht.hash_table(table, slot_rows, count, capacity), rows], device=device)
                wp.synchronize_device(device)
                return table, slot_rows, count

            table, slot_rows, count = insert()
            insert_s = timed(insert, repeats)

            def find():
                wp.launch(ht.lookup_keys, dim=m, inputs=[keys, ht.hash_table(table, slot_rows, count, capacity), rows], device=device)
                wp.synchronize_device(device)

            find_s = timed(find, repeats)
            out.append({"keys": kind, "load": load, "n": m, "insert_per_s": m / insert_s, "find_per_s": m / find_s})
    return out


def precision_and_stream(device, quick, repeats):
    n = 1 << (20 if quick else 25)
    src = wp.array(np.random.default_rng(2).random(n), dtype=wp.float64, device=device)
    dst = wp.empty(n, dtype=wp.float64, device=device)

    def copy():
        wp.launch(mb.stream_copy, dim=n, inputs=[src, dst], device=device)
        wp.synchronize_device(device)

    stream_gbs = 16 * n / timed(copy, repeats) / 1e9
    rows_n, updates, k = 1 << (16 if quick else 20), 1 << (18 if quick else 22), 13
    rng = np.random.default_rng(3)
    rows = wp.array(rng.integers(0, rows_n, updates).astype(np.int32), dtype=int, device=device)
    w64 = wp.array(rng.random(updates), dtype=wp.float64, device=device)
    w32 = wp.array(rng.random(updates).astype(np.float32), dtype=wp.float32, device=device)
    d64 = wp.zeros((rows_n, k), dtype=wp.float64, device=device)
    d32 = wp.zeros((rows_n, k), dtype=wp.float32, device=device)

    def add64():
        wp.launch(mb.add_rows64, dim=updates, inputs=[rows, w64, d64], device=device)
        wp.synchronize_device(device)

    def add32():
        wp.launch(mb.add_rows32, dim=updates, inputs=[rows, w32, d32], device=device)
        wp.synchronize_device(device)

    return {"stream_gbs": stream_gbs, "row_add64_per_s": updates / timed(add64, repeats), "row_add32_per_s": updates / timed(add32, repeats), "row_columns": k}


def scaling(scans, device, quick, repeats):
    """Points per scan, K, kernel length: each strategy on one scan, one thread."""
    pts, alpha, origin = scans[0]
    base = load_config([PRESET], method="s-bki").mapping
    out = []
    sizes = (1000, 4000, len(pts)) if quick else (1000, 5000, 20000, len(pts))
    for n in sizes:
        for strategy in STRATEGIES:
            cfg = dataclasses.replace(base, clean=CleanSettings(ScatterStrategy(strategy)))
            s = timed(lambda: run_mapper(cfg, [(pts[:n], alpha[:n], origin)], device, 1), repeats)
            out.append({"axis": "points per scan", "x": n, "strategy": strategy, "points_per_s": n / s})
    for k in (3, 9, 20):
        a = np.ones((len(pts), k))
        a[np.arange(len(pts)), np.argmax(alpha, 1) % k] += 10
        for strategy in STRATEGIES:
            cfg = dataclasses.replace(load_config([PRESET], method="prob").mapping, clean=CleanSettings(ScatterStrategy(strategy)))
            s = timed(lambda: run_mapper(cfg, [(pts, a, origin)], device, 1, num_classes=k), repeats)
            out.append({"axis": "classes K", "x": k, "strategy": strategy, "points_per_s": len(pts) / s})
    for length in (0.2, 0.3, 0.45) if quick else (0.2, 0.3, 0.45, 0.6):
        for strategy in STRATEGIES:
            cfg = dataclasses.replace(base, length_m=length, clean=CleanSettings(ScatterStrategy(strategy)))
            s = timed(lambda: run_mapper(cfg, [(pts, alpha, origin)], device, 1), repeats)
            out.append({"axis": "kernel length / resolution", "x": length / base.resolution_m, "strategy": strategy, "points_per_s": len(pts) / s})
    return out


def plot(out_dir: Path, strategy_rows, hash_rows, scaling_rows, device):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    labels = [f"{r['method']}\n{r['strategy']} x{r['workers']}" for r in strategy_rows]
    ax.barh(labels, [r["points_per_s"] / 1e6 for r in strategy_rows], color="#3b7dd8")
    ax.set_xlabel("input points per second (millions)")
    ax.set_title(f"Integration strategies ({device})")
    ax.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "strategies.png", dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 4))
    for kind in ("uniform", "lidar-like"):
        rs = [r for r in hash_rows if r["keys"] == kind]
        ax.plot([r["load"] for r in rs], [r["insert_per_s"] / 1e6 for r in rs], "o-", label=f"insert, {kind}")
        ax.plot([r["load"] for r in rs], [r["find_per_s"] / 1e6 for r in rs], "s--", label=f"find, {kind}")
    ax.set_xlabel("load factor")
    ax.set_ylabel("million keys per second")
    ax.set_title(f"Hash table ({device}, one launch)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "hash_load.png", dpi=110)
    plt.close(fig)
    axes = sorted({r["axis"] for r in scaling_rows})
    fig, axs = plt.subplots(1, len(axes), figsize=(4 * len(axes), 3.6))
    for ax, name in zip(np.atleast_1d(axs), axes):
        for strategy in STRATEGIES:
            rs = [r for r in scaling_rows if r["axis"] == name and r["strategy"] == strategy]
            ax.plot([r["x"] for r in rs], [r["points_per_s"] / 1e6 for r in rs], "o-", label=strategy)
        ax.set_xlabel(name)
        ax.set_ylabel("M input points/s (1 thread)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "scaling.png", dpi=110)
    plt.close(fig)


# Bytes one voxel update moves, by strategy (modelled; K classes): the atomic scatter probes the table
# once (its adding pass finds or inserts the voxel: one 8-byte key at low load; the insert pass before
# it runs only for points that may not fit, near the fill limit) and read-modify-writes K + 3 float64
# columns; the sorted strategy writes and sorts a 16-byte (key, id) pair and a 12-byte (point, weight)
# record, reads them back, and touches the row once per voxel (amortised over its ~4 pairs); the
# hash-grid gather reads a point (24 B position + 8 B length + K weights) per update and writes the row
# once per voxel.
def bytes_per_update(strategy: str, k: int) -> float:
    if strategy == "atomic":
        return 8 + 2 * 8 * (k + 3)
    if strategy == "sorted":
        return 16 * 2 * 2 + 12 * 2 + 8 * (k + 3) / 4
    if strategy == "gather":
        return 32 + 8 * k + 8 * (k + 3) / 4
    # release block gather: a point (12 B position + K float64 weights) is read once per target block and
    # serves its 8 cells; the row is written once per cell (~20 updates each)
    return (12 + 8 * k) / 8 + 8 * (k + 3) / 20


def determinism_cost(strategy_rows) -> dict[str, float]:
    one = {r["strategy"]: r["seconds"] for r in strategy_rows if r["method"] == "s-bki" and r["workers"] == 1}
    return {name: one[name] / one["atomic"] for name in STRATEGIES if name != "atomic" and name in one}


def derived_figures(strategy_rows, hash_rows, prec, k: int = 9) -> dict:
    """What the report concludes from, computed from the run's figures (kept in the record): each
    strategy row's modelled bytes per update and share of the streaming bandwidth (added to the row), the
    time of one update of the atomic scatter (s-bki, one thread) beside a random keyed row add and a hash
    find measured in the same run, the cost of float64 and of determinism."""
    for r in strategy_rows:
        if r.get("updates_per_s"):
            model = r["strategy"] if r["strategy"] in STRATEGIES else "release"
            r["bytes_per_update_model"] = bytes_per_update(model, k)
            r["roofline_share_percent"] = r["updates_per_s"] * r["bytes_per_update_model"] / 1e9 / prec["stream_gbs"] * 100
    shares = [r for r in strategy_rows if "roofline_share_percent" in r]
    top = max(shares, key=lambda r: r["roofline_share_percent"]) if shares else None
    out = {"bytes_per_update_model": {name: bytes_per_update(name, k) for name in (*STRATEGIES, "release")},
           "highest_roofline_share_percent": top["roofline_share_percent"] if top else None,
           "highest_roofline_share_row": f"{top['method']}, {top['strategy']}, {top['workers']} thread{'s' if top['workers'] > 1 else ''}"
           if top else None,
           "float64_cost": prec["row_add32_per_s"] / prec["row_add64_per_s"], "determinism_cost": determinism_cost(strategy_rows)}
    atomic = next((r for r in strategy_rows if r["method"] == "s-bki" and r["strategy"] == "atomic" and r["workers"] == 1), None)
    find = next((r for r in hash_rows if r["keys"] == "lidar-like" and r["load"] == 0.5), None)
    if atomic and find:
        out["update_ns"] = 1e9 / atomic["updates_per_s"]
        out["row_add_ns"], out["row_columns"] = 1e9 / prec["row_add64_per_s"], prec["row_columns"]
        out["find_ns"] = 1e9 / find["find_per_s"]
        out["row_add_and_find_ns"] = out["row_add_ns"] + out["find_ns"]
        # the page's conclusions print these too: derived here so that every figure it prints is in the record
        out["update_over_accesses"] = out["update_ns"] / out["row_add_and_find_ns"]
        out["kernel_own_ns_at_least"] = out["update_ns"] - out["row_add_and_find_ns"]
    return out


def conclusions(derived: dict) -> list[str]:
    """The roofline section's conclusions, each argued from this run's figures."""
    out = []
    share = derived["highest_roofline_share_percent"]
    if share is not None:
        text = f"The highest share in this run is {share:.0f} % ({derived['highest_roofline_share_row']})"
        if share < 50:
            text += (": by this model every strategy moves less than half the bytes the streaming copy moves in the same time, "
                     "so none is bound by memory bandwidth in this run.")
        else:
            text += ": by this model that row is within a factor of two of the bandwidth roof."
        out.append(text)
    if "update_ns" in derived:
        update, accesses = derived["update_ns"], derived["row_add_and_find_ns"]
        text = (f"One voxel update of the atomic scatter (s-bki, one thread) takes {update:.0f} ns; in the microbenchmarks below a "
                f"random keyed add of a {derived['row_columns']}-column float64 row takes {derived['row_add_ns']:.0f} ns and a hash find "
                f"at load 0.5 (LiDAR-like keys) {derived['find_ns']:.0f} ns, so the update's row add and its one probe (find or insert) would take "
                f"{accesses:.0f} ns at random addresses. ")
        if update > accesses:
            text += (f"The update takes {derived['update_over_accesses']:.1f}x that: with accesses no slower than random ones, at least "
                     f"{derived['kernel_own_ns_at_least']:.0f} ns of it is the kernel's own work (its traversal, weight and bookkeeping), which this "
                     "run does not break down further.")
        else:
            text += ("The update takes no longer than that, so its memory accesses could account for all of its time; this run does "
                     "not separate them from its arithmetic.")
        out.append(text)
    return out


def vector_unit() -> str:
    """The widest vector instructions this machine's CPU has (from its flags)."""
    flags = set(machine().get("cpu_flags", []))
    return "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "AVX" if "avx" in flags else "SSE"


def record_name(path: Path) -> str:
    return path.resolve().relative_to(REPO).as_posix() if path.resolve().is_relative_to(REPO) else str(path)


def write_report(out: Path, device, workload, strategy_rows, problems, gather_rows, hash_rows, prec, scaling_rows, seconds, derived,
                 record: Path):
    lines = [
        "# Kernel study", "",
        f"<!-- page-record: {record_name(record)} -->",
        f"Written by `python tools/kernel_study.py --device {device}` in {seconds:.0f} s ({workload}); its record: "
        f"`{record_name(record)}`. Medians after a warm-up; one run, so ratios are like for like. Regenerate rather than edit.", "",
        "## Integration strategies (same map out of each: checked by the tool)", "",
        "| method | strategy | threads | s | input pts/s | voxel updates/s | roofline share |", "|---|---|---|---|---|---|---|",
    ]
    k = 9
    for r in strategy_rows:
        ups = r.get("updates_per_s")
        strategy = r["strategy"]
        roof = f"{r['roofline_share_percent']:.0f} %" if ups else ""
        lines.append(f"| {r['method']} | {strategy} | {r['workers']} | {r['seconds']:.3f} | {r['points_per_s']:,.0f} | "
                     f"{ups:,.0f} | {roof} |" if ups else f"| {r['method']} | {strategy} | 1 | {r['seconds']:.3f} | {r['points_per_s']:,.0f} | | |")
        if "torch_index_add_seconds" in r:
            lines.append(f"| {r['method']} | torch.index_add_ of the same pairs (reduction only, 1 thread) | 1 | "
                         f"{r['torch_index_add_seconds']:.3f} | | | |")
    lines += ["", "Maps: " + ("every strategy gave the atomic scatter's voxels and values (rtol 1e-10)." if not problems else "; ".join(problems)), "",
              "![strategies](kernel_study/strategies.png)", "",
              "## Roofline", "",
              f"A streaming float64 copy moves **{prec['stream_gbs']:.1f} GB/s** on this device (one launch). The share above is the "
              "modelled bytes per voxel update (atomic: one key probe + a read-modify-write of K + 3 float64 columns = "
              f"{bytes_per_update('atomic', k):.0f} B at K = 9; sorted: {bytes_per_update('sorted', k):.0f} B; hash-grid gather: "
              f"{bytes_per_update('gather', k):.0f} B; release block gather: {bytes_per_update('release', k):.0f} B) times the "
              "achieved update rate, over that bandwidth.", "", *[line for text in conclusions(derived) for line in (text, "")],
              "## Cost of precision and of determinism", "",
              f"Keyed atomic row adds ({prec['row_columns']} columns, random rows): float64 {prec['row_add64_per_s']:,.0f} rows/s, "
              f"float32 {prec['row_add32_per_s']:,.0f} rows/s (float64 costs x{prec['row_add32_per_s'] / prec['row_add64_per_s']:.2f}). ",
              "Determinism: a CPU launch runs on one core into its own shard, so every strategy gives the same map for a given "
              "thread count; the sorted and gather strategies also fix each voxel's summation order, which a GPU's atomics do "
              "not. Their cost, one thread, s-bki: " + ", ".join(
                  f"{name} x{cost:.2f}" for name, cost in determinism_cost(strategy_rows).items()) + " the atomic scatter's time.", "",
              "## The compatibility modes' gather kernels, form by form", "",
              "One thread; the launches only (each block's cells found, through the map's brick cache when it holds the block, "
              "or inserted, the points weighed against its cells, the sums added, table growth included), from scans prepared "
              "once; the same map bit for bit from every form (checked). "
              "Branch-free: a point's kernel values for all of a block's cells added, zeros included (S-BKI), or selected "
              "within reach (release); per-cell branches (S-BKI): a branch on each cell's kernel value being positive. The "
              f"compiler turns both into vector code over a block's 8 cells ({vector_unit()} on this machine; the branches become "
              "masked adds). Prefetch: each thread asks for the brick-cache and table "
              "lines of the block 16 threads ahead and the value rows of the block 8 ahead (`prefetch_brick`). The first form of "
              "each kernel is the engine's.", "",
              "| kernel | form | s | voxel updates/s | time vs the engine's form |", "|---|---|---|---|---|"]
    lines += [f"| {r['kernel']} | {r['form']} | {r['seconds']:.3f} | {r['updates_per_s']:,.0f} | x{r['relative']:.2f} |" for r in gather_rows]
    lines += ["", "## Hash table", "", "| keys | load | keys | insert/s | find/s |", "|---|---|---|---|---|"]
    lines += [f"| {r['keys']} | {r['load']:.2f} | {r['n']:,} | {r['insert_per_s']:,.0f} | {r['find_per_s']:,.0f} |" for r in hash_rows]
    lines += ["", "![hash](kernel_study/hash_load.png)", "", "## Scaling (one scan, one thread)", "",
              "| axis | x | strategy | input pts/s |", "|---|---|---|---|"]
    lines += [f"| {r['axis']} | {r['x']:g} | {r['strategy']} | {r['points_per_s']:,.0f} |" for r in scaling_rows]
    lines += ["", "![scaling](kernel_study/scaling.png)", "",
              "## Not measured in this run", "",
              "- GPU figures: no CUDA device was available to the run that wrote this file unless the device above says cuda." if device == "cpu" else "",
              "- Block-keyed (8^3 voxels per key) hashing of the clean map was not built: the release mode's blocks of "
              "2^3 cells are the block-keyed form measured here.", ""]
    out.write_text("\n".join(lines))


def index_forms(n: int, rounds: int = 9, repeats: int = 11, seed: int = 0) -> dict[str, dict[str, float]]:
    """ns per value of ``microbench.radix_scatter_form`` in each form over n packed 25-bit keys (a 13-bit
    digit, as the free samples' leaf keys sort): the median of ``repeats`` launches, its min and median
    over ``rounds`` rounds that take the forms in turn. Raises AssertionError where a form's pass differs
    from its twin's."""
    from evsemmap_warp.reference import microbench as mb_ref

    rng = np.random.default_rng(seed)
    shift, bits = 20, 13
    values = (rng.integers(0, 1 << 25, n).astype(np.int64) << shift) | np.arange(n)
    digits = (values >> shift) & ((1 << bits) - 1)
    first_slot = np.r_[0, np.cumsum(np.bincount(digits, minlength=1 << bits))[:-1]].astype(np.int32)
    values_in = wp.array(values, dtype=wp.int64, device="cpu")
    forms = {f"{'while' if w else 'range'} loop, {'masked' if m else 'as read'}": mb.radix_scatter_form(w, m)
             for w in (True, False) for m in (True, False)}
    want = mb_ref.radix_scatter_form(values, shift, bits)

    def run(kernel) -> tuple[float, np.ndarray]:
        slots = wp.array(first_slot, dtype=int, device="cpu")
        out = wp.empty(n, dtype=wp.int64, device="cpu")
        start = time.perf_counter()
        wp.launch(kernel, dim=1, inputs=[values_in, shift, bits, slots, out], device="cpu")
        return time.perf_counter() - start, out

    for name, kernel in forms.items():
        assert (run(kernel)[1].numpy() == want).all(), f"{name}: not the twin's pass"
    per_round: dict[str, list[float]] = {name: [] for name in forms}
    for _ in range(rounds):
        for name, kernel in forms.items():
            per_round[name].append(statistics.median(run(kernel)[0] for _ in range(repeats)) / n * 1e9)
    return {name: {"min": min(times), "median": statistics.median(times)} for name, times in per_round.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="small sizes, one repeat: checks the study runs and its strategies agree")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--out", type=Path, default=REPO / "docs", help="folder for kernel_study.md and kernel_study/*.png")
    parser.add_argument("--index-forms", type=int, metavar="N", nargs="?", const=327_000,
                        help="only time the radix scatter's index forms over N values (default 327000) on the CPU, and print them")
    args = parser.parse_args()
    if args.index_forms:
        for name, ns in index_forms(args.index_forms).items():
            print(f"{name}: {ns['min']:.2f} ns per value (min over rounds), {ns['median']:.2f} (median)")
        print(machine().get("cpu_model", "CPU model unknown"))
        return 0
    device = resolve_device(args.device)
    repeats = args.repeats or (1 if args.quick else 3)
    start = time.perf_counter()
    scans, workload = load_workload(args.quick)
    workers_list = (1, 2) if device == "cpu" else (1,)
    print(f"study on {device}: {workload}", file=sys.stderr)
    strategy_rows, problems = strategies(scans, device, repeats, workers_list)
    print("strategies done", file=sys.stderr)
    gather_rows, gather_problems = gather_forms(scans, device, repeats)
    problems += gather_problems
    hash_rows = hash_microbench(device, args.quick, repeats)
    prec = precision_and_stream(device, args.quick, repeats)
    scaling_rows = scaling(scans, device, args.quick, repeats)
    (args.out / "kernel_study").mkdir(parents=True, exist_ok=True)
    plot(args.out / "kernel_study", strategy_rows, hash_rows, scaling_rows, device)
    derived = derived_figures(strategy_rows, hash_rows, prec)
    seconds = time.perf_counter() - start
    results = {"device": device, "quick": args.quick, "repeats": repeats, "workload": workload, "seconds": seconds, "strategies": strategy_rows,
               "gather_forms": gather_rows, "hash_table": hash_rows, "precision_and_stream": prec, "scaling": scaling_rows, "derived": derived,
               "problems": problems}
    record = write_record("kernel_study", results, folder=args.out / "bench")
    write_report(args.out / "kernel_study.md", device, workload, strategy_rows, problems, gather_rows, hash_rows, prec, scaling_rows,
                 seconds, derived, record)
    print(f"record: {record}", file=sys.stderr)
    print(f"wrote {args.out / 'kernel_study.md'} in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    if problems:
        print("MISMATCH: " + "; ".join(problems), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

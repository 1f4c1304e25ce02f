"""Same-run A/B of the CPU tables' host-memory choices (``core/host_memory.py``) and of numpy's
transparent-huge-page advice during a map's read-out, on the integration benchmark's workload.

Each variant maps the workload's 30 scans in the sbki mode (``tools/bench_integrate.py``'s
``compat_config``, free_resolution 4 unless ``--free-resolution``) on one worker thread, scan by scan,
into a fresh map, then reads it out (``Mapper.voxels``):

* ``engine``: the tables as ``core/host_memory.py`` makes them, numpy's advice as the process has it;
* ``readout_without_advice``: numpy's huge-page advice off while the map is read out, as a process
  started with ``NUMPY_MADVISE_HUGEPAGE=0`` has it (numpy's switch, flipped by this tool only);
* ``tables_from_numpy``: the tables' arrays from np.zeros (numpy's huge-page advice) instead of
  ``lazily_zeroed``;
* ``tables_unpopulated``: ``lazily_zeroed`` without MAP_POPULATE for grown tables;
* ``rows_copied``: no row reservation (``reserved_zeros`` refused): each growth copies the rows.

The variants run in rounds, one repeat of each per round, so that a shared machine's slower stretch
falls on every variant alike; each time is the median over the rounds. Each repeat also counts the
process's minor page faults, and its map's digest (every stored voxel's index and values) must be the
same for every variant, or the tool exits 1 after writing its record (docs/bench/bench_host_memory-<UTC>.json).

    python tools/bench_host_memory.py [--repeats 5] [--free-resolution 4] [--scans N] [--variants engine tables_from_numpy ...]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import hashlib
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from bench_integrate import compat_config, load_scans, sbki_labels  # noqa: E402
from bench_record import RECORDS, write_record  # noqa: E402

from evsemmap_warp.core import host_memory  # noqa: E402
from evsemmap_warp.core.mapper import Mapper  # noqa: E402

# numpy's switch for its huge-page advice (numpy >= 1.20); NUMPY_MADVISE_HUGEPAGE=0 sets it at import.
NUMPY_ADVICE_SWITCH = getattr(getattr(np, "_core", np.core), "multiarray")._set_madvise_hugepage
VARIANTS = ("engine", "readout_without_advice", "tables_from_numpy", "tables_unpopulated", "rows_copied")


@contextlib.contextmanager
def replaced(name: str, value):
    """``host_memory.<name>`` replaced by ``value`` while the block runs."""
    before = getattr(host_memory, name)
    setattr(host_memory, name, value)
    try:
        yield
    finally:
        setattr(host_memory, name, before)


@contextlib.contextmanager
def numpy_advice(on: bool):
    before = NUMPY_ADVICE_SWITCH(on)
    try:
        yield
    finally:
        NUMPY_ADVICE_SWITCH(before)


def tables(variant: str):
    """The table memory of ``variant``, in force while its scans are mapped."""
    if variant == "tables_from_numpy":
        return replaced("lazily_zeroed", lambda shape, dtype, populate=False: np.zeros(shape, dtype))
    if variant == "tables_unpopulated":
        lazily_zeroed = host_memory.lazily_zeroed
        return replaced("lazily_zeroed", lambda shape, dtype, populate=False: lazily_zeroed(shape, dtype))
    if variant == "rows_copied":
        return replaced("reserved_zeros", lambda rows, columns: None)
    return contextlib.nullcontext()


def digest(mapper: Mapper) -> str:
    arrays = mapper.voxels().arrays
    sha = hashlib.sha256()
    for name in ("index", "evidence", "weight_sum", "weighted_uncertainty_sum", "hits", "touched"):
        sha.update(np.ascontiguousarray(getattr(arrays, name)).tobytes())
    return sha.hexdigest()


def faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def one_repeat(variant: str, config, scans, labels) -> dict:
    """Map the scans into a fresh map and read it out: seconds and minor page faults of each."""
    with tables(variant):
        mapper = Mapper(config, 9, workers=1)
        before, integrate_s = faults(), 0.0
        for scan, label in zip(scans, labels):
            start = time.perf_counter()
            mapper.integrate(scan.points, label, payload_type="label", sensor_origin=scan.sensor_origin)
            integrate_s += time.perf_counter() - start
        integrate_faults, before = faults() - before, faults()
        with numpy_advice(False) if variant == "readout_without_advice" else contextlib.nullcontext():
            start = time.perf_counter()
            mapper.voxels()
            readout_s = time.perf_counter() - start
        readout_faults = faults() - before
        out = {"integrate_s": integrate_s, "integrate_faults": integrate_faults, "readout_s": readout_s,
               "readout_faults": readout_faults, "voxels": mapper.voxel_count, "digest": digest(mapper)}
    del mapper  # released before the next map: memory the process has not touched faults in more slowly
    gc.collect()
    return out


def summary(runs: list[dict]) -> dict:
    out = {key: statistics.median(r[key] for r in runs) for key in ("integrate_s", "integrate_faults", "readout_s", "readout_faults")}
    out |= {f"all_{key}": [round(r[key], 4) for r in runs] for key in ("integrate_s", "readout_s")}
    return out | {"voxels": runs[0]["voxels"], "digest": runs[0]["digest"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--free-resolution", type=float, default=4.0)
    parser.add_argument("--scans", type=int, default=None, help="map the first N scans only (a trial)")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS), help="the variants to run (engine always runs)")
    parser.add_argument("--record-dir", type=Path, default=RECORDS, help="where the run's record goes (default docs/bench)")
    args = parser.parse_args()
    started = time.time()
    dataset, scans = load_scans()
    labels = sbki_labels(dataset)
    scans, labels = scans[:args.scans], labels[:args.scans]
    config = compat_config(args.free_resolution)
    one_repeat("engine", config, scans[:1], labels[:1])  # compiles the kernels
    runs = {variant: [] for variant in VARIANTS if variant == "engine" or variant in args.variants}
    for round_ in range(args.repeats):
        for variant in runs:
            runs[variant].append(one_repeat(variant, config, scans, labels))
            print(f"round {round_ + 1} {variant}: " + json.dumps({k: v for k, v in runs[variant][-1].items() if k != "digest"}), file=sys.stderr)
    results = {"workload": {"scans": len(scans), "points": sum(len(s.points) for s in scans), "free_resolution": args.free_resolution,
                            "workers": 1}, "repeats": args.repeats, "order": "rounds: one repeat of each variant per round",
               "thp": {name: Path(f"/sys/kernel/mm/transparent_hugepage/{name}").read_text().strip()
                       for name in ("enabled", "defrag") if Path(f"/sys/kernel/mm/transparent_hugepage/{name}").exists()},
               "variants": {variant: summary(variant_runs) for variant, variant_runs in runs.items()}}
    engine = results["variants"]["engine"]
    for variant, row in results["variants"].items():
        row["integrate_vs_engine"] = round(row["integrate_s"] / engine["integrate_s"], 3)
        row["readout_vs_engine"] = round(row["readout_s"] / engine["readout_s"], 3)
        print(f"{variant:24s} integrate {row['integrate_s']:.3f} s (x{row['integrate_vs_engine']:.3f}, {row['integrate_faults']:,.0f} faults)  "
              f"read-out {row['readout_s']:.3f} s (x{row['readout_vs_engine']:.3f}, {row['readout_faults']:,.0f} faults)")
    same = len({row["digest"] for row in results["variants"].values()}) == 1
    results["maps_identical"] = same
    print(write_record("bench_host_memory", results, started=started, folder=args.record_dir))
    if not same:
        print("MISMATCH: the variants' maps differ", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

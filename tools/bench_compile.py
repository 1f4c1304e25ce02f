"""What the first use of the kernels costs: Warp compiles every kernel module a command needs on first use
and caches it (``WARP_CACHE_PATH``). For each method (METHOD@sbki: in the S-BKI compatibility mode),
``evsemmap map`` on a tiny synthetic drive runs once with an empty kernel cache (cold: compiling
included) and then ``--repeats`` times with the cache it filled (warm); the difference is the compile
time a new user waits once per Warp version. Also: how many modules were compiled and what the cache
holds. The compatibility modes' gather kernels, each a module of its own built per class count and form,
are then compiled alone (``wp.load_module``: the variant a CPU launch runs), each ``--repeats`` times
into an empty cache in a fresh process: what the first S-BKI or release map adds.

The figures go to a run record (docs/bench/bench_compile-<UTC>.json, tools/bench_record.py); the last line
printed is its path.

    python tools/bench_compile.py [--methods ebs,s-bki,s-csm,s-bki@sbki] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_record import write_record

REPO = Path(__file__).resolve().parents[1]
EVSEMMAP = [sys.executable, "-m", "evsemmap_warp.apps.cli"]
# Warp's compiled CPU modules: one shared object per module and content hash
MODULE_SUFFIXES = (".o", ".so", ".dll", ".dylib")


def timed(args: list[str], cache: Path) -> float:
    started = time.perf_counter()
    done = subprocess.run(EVSEMMAP + args, capture_output=True, text=True, cwd=REPO, env=os.environ | {"WARP_CACHE_PATH": str(cache)})
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{done.stderr[-3000:]}")
    return seconds


# The compatibility modes' gather kernels as their integrators make them for the bench workload (K = 9,
# 2^3 cells per block): name -> the statement that makes ``kernel``.
GATHER_KERNELS = {
    "S-BKI gather": "from evsemmap_warp.kernels import block_gather; kernel = block_gather.gather_sbki_kernel(9, 2)",
    "release gather (Bayes)": "from evsemmap_warp.kernels import release; kernel = release.gather_release_kernel(9, 2, fusion=0)",
    "release gather (Dempster)": "from evsemmap_warp.kernels import release; kernel = release.gather_release_kernel(9, 2, fusion=1)",
}


def kernel_compile_seconds(make_kernel: str, cache: Path) -> float:
    """Seconds to compile one kernel's module for the CPU into the empty ``cache``, in a fresh process."""
    # A one-line kernel is compiled first: a process's first compile also pays once for setting up Warp's
    # compiler, which is not this kernel's. (Warp reads a kernel's source: the script is a file.)
    script = cache.with_suffix(".py")
    script.write_text("import time\nfrom evsemmap_warp.core.warp_runtime import init_warp\nwp = init_warp()\n\n\n"
                      "@wp.kernel(module='unique')\ndef first(a: wp.array(dtype=float)):\n    a[wp.tid()] = 1.0\n\n\n"
                      f"wp.load_module(first.module, device='cpu')\n{make_kernel}\nstarted = time.perf_counter()\n"
                      "wp.load_module(kernel.module, device='cpu')\n"
                      "print(time.perf_counter() - started)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=REPO,
                          env=os.environ | {"WARP_CACHE_PATH": str(cache), "PYTHONPATH": str(REPO)})
    if done.returncode != 0:
        raise SystemExit(f"compiling {make_kernel!r} failed:\n{done.stderr[-3000:]}")
    return float(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="ebs,s-bki,s-csm,s-bki@sbki", help="methods, METHOD@sbki for the S-BKI compatibility mode")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    results = {"repeats": args.repeats, "methods": {}, "gather_kernels": {}}
    with tempfile.TemporaryDirectory(prefix="bench_compile_") as tmp:
        drive = Path(tmp) / "drive"
        subprocess.run(EVSEMMAP + ["synth", "--world", "tiny", "--no-camera", "--frames", "3", "--out", str(drive), "--quiet"],
                       check=True, capture_output=True, cwd=REPO)
        sbki_mode = Path(tmp) / "sbki_mode.yaml"
        sbki_mode.write_text("mapping:\n  compat: sbki\n")
        for entry in args.methods.split(","):
            method, _, mode = entry.partition("@")
            cache = Path(tmp) / f"cache_{entry}"
            command = ["map", str(drive), *([str(sbki_mode)] if mode == "sbki" else []), "--method", method, "--out", str(Path(tmp) / f"{entry}.npz"), "--quiet"]
            cold = timed(command, cache)
            warm = statistics.median(timed(command, cache) for _ in range(args.repeats))
            modules = sorted({f.name for f in cache.rglob("*") if f.is_file() and f.suffix in MODULE_SUFFIXES})
            size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file())
            row = {"cold_s": round(cold, 2), "warm_s": round(warm, 2), "compile_s": round(cold - warm, 2), "compiled_modules": len(modules),
                   "compile_s_per_module": round((cold - warm) / max(1, len(modules)), 2), "cache_mb": round(size / 1e6, 1)}
            results["methods"][entry] = row
            print(f"{entry}: cold {row['cold_s']} s, warm {row['warm_s']} s: compiling {row['compile_s']} s for {row['compiled_modules']} modules "
                  f"({row['compile_s_per_module']} s each), cache {row['cache_mb']} MB", flush=True)
        for name, make_kernel in GATHER_KERNELS.items():
            runs = [kernel_compile_seconds(make_kernel, Path(tmp) / f"kernel_cache_{len(results['gather_kernels'])}_{repeat}")
                    for repeat in range(args.repeats)]
            results["gather_kernels"][name] = {"compile_s": round(statistics.median(runs), 2), "all_compile_s": [round(r, 2) for r in runs]}
            print(f"{name}: compiled alone in {statistics.median(runs):.2f} s (median of {args.repeats})", flush=True)
    print(write_record("bench_compile", results))


if __name__ == "__main__":
    main()

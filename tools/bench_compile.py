"""What the first use of the kernels costs: Warp compiles every kernel module a command needs on first use
and caches it (``WARP_CACHE_PATH``). For each method, ``evsemmap map`` on a tiny synthetic drive runs once
with an empty kernel cache (cold: compiling included) and then ``--repeats`` times with the cache it filled
(warm); the difference is the compile time a new user waits once per Warp version. Also: how many
modules were compiled and what the cache holds.

The figures go to a run record (docs/bench/bench_compile-<UTC>.json, tools/bench_record.py); the last line
printed is its path.

    python tools/bench_compile.py [--methods ebs,s-bki,s-csm] [--repeats 3]
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="ebs,s-bki,s-csm")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    results = {"repeats": args.repeats, "methods": {}}
    with tempfile.TemporaryDirectory(prefix="bench_compile_") as tmp:
        drive = Path(tmp) / "drive"
        subprocess.run(EVSEMMAP + ["synth", "--world", "tiny", "--no-camera", "--frames", "3", "--out", str(drive), "--quiet"],
                       check=True, capture_output=True, cwd=REPO)
        for method in args.methods.split(","):
            cache = Path(tmp) / f"cache_{method}"
            command = ["map", str(drive), "--method", method, "--out", str(Path(tmp) / f"{method}.npz"), "--quiet"]
            cold = timed(command, cache)
            warm = statistics.median(timed(command, cache) for _ in range(args.repeats))
            modules = sorted({f.name for f in cache.rglob("*") if f.is_file() and f.suffix in MODULE_SUFFIXES})
            size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file())
            row = {"cold_s": round(cold, 2), "warm_s": round(warm, 2), "compile_s": round(cold - warm, 2), "compiled_modules": len(modules),
                   "compile_s_per_module": round((cold - warm) / max(1, len(modules)), 2), "cache_mb": round(size / 1e6, 1)}
            results["methods"][method] = row
            print(f"{method}: cold {row['cold_s']} s, warm {row['warm_s']} s: compiling {row['compile_s']} s for {row['compiled_modules']} modules "
                  f"({row['compile_s_per_module']} s each), cache {row['cache_mb']} MB", flush=True)
    print(write_record("bench_compile", results))


if __name__ == "__main__":
    main()

"""Run records of the benchmark tools: every figure a README or docs table shows comes from one of these
JSON files under ``docs/bench/``, written by the tool that measured it.

A record holds the tool, the command line, when it ran, the commit (and whether the tree was
clean), the machine (CPU model, cores, flags, memory, the load when it started), the versions of
Python and the packages that matter, how Warp compiles CPU kernels (its flags: the figures depend on
them), and the tool's raw results (every timing, every count). ``tools/perf_records.py`` generates
docs tables from records and checks that the docs' figures are in them.

    from bench_record import write_record
    path = write_record("bench_batch", results)          # docs/bench/bench_batch-<UTC time>.json
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RECORDS = REPO / "docs" / "bench"


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


# Whether the tracked files were as committed when the tool started (this module is imported then): what
# the run itself writes under docs/ (a plot) does not make its record one of a modified tree.
TREE_CLEAN_AT_START = _git("status", "--porcelain", "--untracked-files=no") == ""


def machine() -> dict:
    """What the figures depend on: CPU model and flags, cores, memory, load, OS."""
    info = {"platform": platform.platform(), "cores": os.cpu_count(), "load_average_1_5_15": list(os.getloadavg())}
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text()
        for line in cpuinfo.splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and "cpu_model" not in info:
                info["cpu_model"] = value.strip()
            if key.strip() == "flags" and "cpu_flags" not in info:
                flags = set(value.split())
                info["cpu_flags"] = sorted(f for f in flags if f.startswith(("avx", "sse4", "fma", "bmi")))
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                info["memory_gb"] = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return info


def versions() -> dict:
    out = {"python": platform.python_version()}
    for name in ("numpy", "warp", "torch", "ray", "zstandard"):
        module = sys.modules.get(name)
        if module is None:
            try:
                from importlib.metadata import version

                out[name] = version({"warp": "warp-lang"}.get(name, name))
            except Exception:  # not installed: not part of this record
                continue
        else:
            out[name] = getattr(module, "__version__", "")
    return out


def warp_build() -> dict | None:
    """How Warp builds CPU kernels in this process (None when Warp is not loaded): its CPU compiler flags
    and optimization level. Warp compiles with its own Clang/LLVM, at -O2 on the CPU unless
    ``wp.config.optimization_level`` says otherwise, for the host's CPU (``-march=native``)."""
    warp = sys.modules.get("warp")
    if warp is None:
        return None
    level = getattr(warp.config, "optimization_level", None)
    return {"cpu_compiler_flags": getattr(warp.config, "cpu_compiler_flags", None),
            "cpu_optimization_level": level if level is not None else "default (-O2 on the CPU)", "mode": getattr(warp.config, "mode", None)}


def _json_value(value):
    """numpy scalars and arrays (a tool's counts often are) as JSON values."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


def write_record(tool: str, results: dict, *, started: float | None = None, folder: Path = RECORDS) -> Path:
    """Write ``results`` with the run's provenance to <folder>/<tool>-<UTC time>.json (``folder``:
    docs/bench unless a trial run puts it elsewhere); returns the path."""
    now = datetime.datetime.now(datetime.timezone.utc)
    record = {
        "tool": tool, "command": [Path(sys.executable).name, *sys.argv], "utc": now.isoformat(timespec="seconds"),
        "commit": _git("rev-parse", "HEAD"), "tree_clean": TREE_CLEAN_AT_START,
        "machine": machine(), "versions": versions(), "warp_build": warp_build(), "results": results,
    }
    if started is not None:
        record["seconds"] = round(now.timestamp() - started, 1)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{tool}-{now.strftime('%Y%m%dT%H%M%SZ')}.json"
    path.write_text(json.dumps(record, indent=1, default=_json_value) + "\n")
    return path

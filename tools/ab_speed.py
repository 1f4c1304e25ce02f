"""Same-run speed A/B of the integration bench: this checkout against another one (a ``git worktree`` of the
reference commit), ``tools/bench_integrate.py`` of each checkout run in its own process, the two sides
alternating round by round on the same machine, so that both see the same load and the same day's VM.

The sides take turns going first, round by round. Writes docs/bench/ab_speed-<UTC>.json: both commits,
every round's seconds per row on both sides, each row's median over the rounds and ours / reference
(below 1: this checkout is faster), and whether both sides mapped the same voxel counts. Prints one line
per row.

    git worktree add --detach /tmp/ref COMMIT
    python tools/ab_speed.py /tmp/ref [--rounds 2] [--repeats 3] [--free-resolutions 0.5 4]

The reference checkout runs from its own tree: ``evsemmap_warp/kernels`` and ``evsemmap_warp/configs`` are
linked to its top-level folders there (as the editable install maps them) when they are not yet.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
from bench_record import RECORDS, write_record  # noqa: E402


def _commit(root: Path) -> str:
    return subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True).stdout.strip()


def _link_subpackages(root: Path) -> None:
    for name in ("kernels", "configs"):
        link = root / "evsemmap_warp" / name
        if not link.exists():
            link.symlink_to(Path("..") / name)


def bench(root: Path, args, out: Path) -> dict:
    """One bench_integrate run of the checkout at ``root``: its record's rows (a checkout from before the
    records, whose bench has no --record-dir, prints them on its ``details:`` line)."""
    env = dict(os.environ, PYTHONPATH=str(root))
    tool = root / "tools" / "bench_integrate.py"
    writes_records = "--record-dir" in tool.read_text()
    command = [sys.executable, str(tool), "--repeats", str(args.repeats), "--skip-numpy", "--free-resolutions", *args.free_resolutions]
    done = subprocess.run(command + (["--record-dir", str(out)] if writes_records else []), cwd=out, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"bench_integrate in {root} failed:\n{done.stderr[-3000:]}")
    if not writes_records:
        return json.loads(next(line for line in done.stdout.splitlines() if line.startswith("details: "))[len("details: "):])
    record = json.loads(next(out.glob("bench_integrate-*.json")).read_text())
    return record["results"]["rows"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reference", type=Path, help="the other checkout (a git worktree of the reference commit)")
    parser.add_argument("--rounds", type=int, default=2, help="runs per side, alternating (default 2)")
    parser.add_argument("--repeats", type=int, default=3, help="bench_integrate's repeats per run (default 3)")
    parser.add_argument("--free-resolutions", nargs="+", default=["0.5", "4"])
    parser.add_argument("--record-dir", type=Path, default=RECORDS)
    args = parser.parse_args()
    reference = args.reference.resolve()
    _link_subpackages(reference)
    started = time.time()
    sides = {"ours": REPO, "reference": reference}
    runs: dict[str, list[dict]] = {side: [] for side in sides}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.rounds):
            # Each round swaps which side runs first: a VM's speed drifts within a round too.
            for side, root in (list(sides.items()) if round_ % 2 == 0 else list(sides.items())[::-1]):
                out = Path(tmp) / f"{side}-{round_}"
                out.mkdir()
                runs[side].append(bench(root, args, out))
                print(f"round {round_ + 1}/{args.rounds}, {side}: done ({time.time() - started:.0f} s)", file=sys.stderr)
    rows = {}
    for name in runs["ours"][0]:
        if not all(name in run for side in sides for run in runs[side]):
            continue
        seconds = {side: [run[name]["seconds"] for run in runs[side]] for side in sides}
        medians = {side: statistics.median(values) for side, values in seconds.items()}
        voxels = {side: {run[name]["voxels"] for run in runs[side]} for side in sides}
        rows[name] = {"ours_seconds": seconds["ours"], "reference_seconds": seconds["reference"], "ours_median_s": medians["ours"],
                      "reference_median_s": medians["reference"], "ours_over_reference": medians["ours"] / medians["reference"],
                      "same_voxel_counts": voxels["ours"] == voxels["reference"]}
        print(f"{name:28s} ours {medians['ours']:.3f} s  reference {medians['reference']:.3f} s  "
              f"x{rows[name]['ours_over_reference']:.3f}{'' if rows[name]['same_voxel_counts'] else '  VOXEL COUNTS DIFFER'}")
    results = {"reference_commit": _commit(reference), "rounds": args.rounds, "repeats": args.repeats,
               "free_resolutions": args.free_resolutions, "rows": rows}
    print(write_record("ab_speed", results, started=started, folder=args.record_dir))
    return 0 if all(row["same_voxel_counts"] for row in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())

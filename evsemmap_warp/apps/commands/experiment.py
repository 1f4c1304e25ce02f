"""``evsemmap experiment``: run a study from a config: data, network, maps, scores, tables (cached, resumable)."""

from __future__ import annotations

import sys
import time
from pathlib import Path


def add_parser(sub) -> None:
    """Add ``experiment`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("experiment", help="run a study from a config: data, network, maps, scores, tables (cached, resumable)")
    p.add_argument("config", help="experiment YAML, or a built-in name (demo, paper-main, paper-robustness, paper-ablation, paper-unseen)")
    p.add_argument("--out", type=Path, default=None, help="results folder (default: results_<name>)")
    p.add_argument("--cache", type=Path, default=None, help="stage cache shared between studies (default: OUT/cache)")
    p.add_argument("--quick", action="store_true", help="the study scaled down by its config's quick section: checks that it runs (CI), numbers not for reading")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run the study of an experiment config stage by stage (cached), then print its results table."""
    from ..experiment import Experiment, load_experiment

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

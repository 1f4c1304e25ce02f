"""``evsemmap demo``: the small study on the synthetic world: from nothing to a comparison table and maps."""

from __future__ import annotations

from pathlib import Path

from .experiment import run as run_experiment


def add_parser(sub) -> None:
    """Add ``demo`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("demo", help="the small study on the synthetic world: from nothing to a comparison table and maps")
    p.add_argument("--out", type=Path, default=Path("evsemmap_demo"), help="results folder (default: evsemmap_demo)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """The built-in ``demo`` study, run as ``evsemmap experiment demo``."""
    args.config = "demo"
    return run_experiment(args)

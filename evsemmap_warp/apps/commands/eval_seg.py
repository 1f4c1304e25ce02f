"""``evsemmap eval-seg``: 2D metrics and calibration plots of a checkpoint on a dataset."""

from __future__ import annotations

import json
from pathlib import Path

from .args import add_dataset_args, segmentation_source


def add_parser(sub) -> None:
    """Add ``eval-seg`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("eval-seg", help="2D metrics and calibration plots of a checkpoint on a dataset")
    p.add_argument("checkpoint", type=Path)
    # seed 2: other synthetic frames than training saw (seed 1)
    add_dataset_args(p, 100, 2, "synthetic frame size (the network resizes to its own)")
    p.add_argument("--out", type=Path, help="folder for metrics.json and the plots")
    p.set_defaults(func=run)


def run(args) -> int:
    """Score a segmentation checkpoint on a dataset: 2D metrics and calibration plots."""
    from ...segmentation.train import evaluate_checkpoint

    summary = evaluate_checkpoint(args.checkpoint, segmentation_source(args), args.out)
    print(json.dumps(summary, indent=1))
    return 0

"""``evsemmap train-convbki``: learn ConvBKI's per-class length scales from a projected, labelled sequence."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...config import ConfigError
from .args import positive, positive_float


def add_parser(sub) -> None:
    """Add ``train-convbki`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("train-convbki", help="learn ConvBKI's per-class length scales from a projected, labelled sequence")
    p.add_argument("sequence", type=Path, help="RELLIS-3D-layout sequence with per-point labels")
    p.add_argument("--alpha-dir", type=Path, metavar="DIR", help="folder of per-frame alpha .npy (evsemmap infer output; required)")
    p.add_argument("--out", type=Path, required=True, help="length-scale file to write (.json; use as mapping.convbki.lengths_file)")
    p.add_argument("--resolution-m", type=positive_float, default=0.3, help="voxel size of the map it will be used with (m)")
    p.add_argument("--epochs", type=positive, default=15)
    p.add_argument("--window-scans", type=positive, default=10)
    p.add_argument("--queries", type=positive, default=4000, help="ground-truth points scored per window")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """Learn ConvBKI's per-class length scales from a labelled sequence and its alpha files."""
    from ...methods import convbki
    from ...classes import class_set
    from ...geometry.projection import ProjectionConfig
    from ...data.sequences import Rellis3DSequence

    if args.alpha_dir is None:
        raise ConfigError("train-convbki: --alpha-dir DIR is required (the folder of per-frame alpha .npy `evsemmap infer` wrote)")
    seq = Rellis3DSequence(args.sequence)

    def alpha_for_frame(frame):
        for name in (f"{frame.index:06d}.npy", f"{frame.image.stem}.npy"):  # experiment cache or `evsemmap infer` names
            if (args.alpha_dir / name).exists():
                return np.load(args.alpha_dir / name).astype(np.float32)
        return None

    windows = convbki.training_windows(seq, alpha_for_frame, ProjectionConfig(), window_scans=args.window_scans,
                                       queries_per_window=args.queries)
    if not windows:
        raise ValueError(f"{args.sequence}: no window of {args.window_scans} scans with alpha in {args.alpha_dir} and per-point labels")
    lengths, history = convbki.train_lengths(windows, len(class_set().names), args.resolution_m, epochs=args.epochs, progress=not args.quiet)
    convbki.save_lengths(args.out, lengths)
    print(json.dumps({"out": str(args.out), "windows": len(windows), "loss": [round(h, 4) for h in history]} | lengths.as_dict(), indent=1))
    return 0

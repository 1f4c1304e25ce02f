"""``evsemmap train-seg``: train the evidential segmentation network."""

from __future__ import annotations

import json
from pathlib import Path

from .args import add_dataset_args, positive, positive_float, segmentation_source


def add_parser(sub) -> None:
    """Add ``train-seg`` to the ``evsemmap`` subcommands."""
    from ...segmentation.config import ModelConfig

    p = sub.add_parser("train-seg", help="train the evidential segmentation network")
    add_dataset_args(p, 400, 1, "network input size (and synthetic frame size)")
    p.add_argument("--out", type=Path, required=True, help="folder for checkpoints, history, metrics and plots")
    p.add_argument("--arch", default=ModelConfig.arch, help="r18-os16 (CPU default), r50-os8 (full size) or torchvision-r50")
    p.add_argument("--width", type=positive, default=ModelConfig.width, help="channels of the first ResNet stage (64 = standard)")
    p.add_argument("--aspp-channels", type=positive, default=ModelConfig.aspp_channels)
    p.add_argument("--head", choices=("evidential", "softmax"), default="evidential")
    p.add_argument("--epochs", type=positive, default=20)
    p.add_argument("--batch-size", type=positive, default=8)
    p.add_argument("--lr", type=positive_float, default=2e-3)
    p.add_argument("--kl-schedule", choices=("paper", "release"), default="paper")
    p.add_argument("--val-fraction", type=float, default=0.1)
    p.add_argument("--time-budget-s", type=positive_float, default=None, help="stop after the epoch that passes this many seconds")
    p.add_argument("--logit-clamp", type=positive_float, default=10.0, help="evidence = exp(clamp(logit, -c, c))")
    p.add_argument("--normalization", choices=("imagenet", "caffe"), default="imagenet")
    p.add_argument("--backbone-weights", type=Path, help="backbone state dict to start from (nothing is downloaded)")
    p.add_argument("--resume", type=Path, help="checkpoint to continue from")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """Train the segmentation network; writes its checkpoints into ``--out``."""
    from ...classes import class_set
    from ...segmentation.config import ModelConfig
    from ...segmentation.train import TrainConfig, train

    classes = class_set()
    config = TrainConfig(
        model=ModelConfig(arch=args.arch, num_classes=len(classes), width=args.width, aspp_channels=args.aspp_channels),
        head=args.head, input_size=tuple(args.input_size), epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
        kl_schedule=args.kl_schedule, val_fraction=args.val_fraction, seed=args.seed, time_budget_s=args.time_budget_s,
        logit_clamp=args.logit_clamp, normalization=args.normalization,
        backbone_weights=str(args.backbone_weights) if args.backbone_weights else None,
    )
    summary = train(segmentation_source(args), classes.names, config, args.out, resume=args.resume, progress=not args.quiet)
    print(json.dumps(summary, indent=1))
    return 0

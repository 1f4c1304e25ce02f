"""Segmentation benchmark on this CPU.

1. Training and inference images per second for the default model (r18-os16, width 32, ASPP 64) and
   the full-size one (r50-os8, width 64, ASPP 256) at the default input size (128 x 256), batch 8.
2. The training target: the default model trained on synthetic off-road frames for --budget seconds
   (default 600): the time at which validation mIoU first reaches 0.8, the final metrics, and how
   well the evidential uncertainty u flags errors (mean u on right and wrong pixels, AUROC).

Writes history, metrics and the reliability / uncertainty plots to --out; the figures go to a run record
(docs/bench/bench_segmentation-<UTC>.json, tools/bench_record.py): the last line printed is its path, the
line before it the figures as one JSON object.

    python tools/bench_segmentation.py [--budget 600] [--frames 400] [--out bench_seg]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench_record import write_record  # noqa: E402

from evsemmap_warp.classes import class_set  # noqa: E402
from evsemmap_warp.segmentation.config import ModelConfig  # noqa: E402
from evsemmap_warp.segmentation.evidential import edl_loss  # noqa: E402
from evsemmap_warp.segmentation.data import SyntheticOffroad  # noqa: E402
from evsemmap_warp.segmentation.model import build_model  # noqa: E402
from evsemmap_warp.segmentation.train import TrainConfig, train  # noqa: E402

SIZES = {"default r18-os16": ModelConfig(), "full r50-os8": ModelConfig(arch="r50-os8", width=64, aspp_channels=256)}


def throughput(config: ModelConfig, size=(128, 256), batch=8, steps=3) -> dict:
    model = build_model(config)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    x = torch.randn(batch, 3, *size)
    y = torch.randint(0, config.num_classes, (batch, *size))
    timings = []
    for step in range(steps + 1):  # the first step warms up allocators and kernels
        start = time.perf_counter()
        loss, _ = edl_loss(model(x), y, 0.1)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if step:
            timings.append(time.perf_counter() - start)
    model.eval()
    with torch.no_grad():
        model(x)
        start = time.perf_counter()
        for _ in range(steps):
            model(x)
        infer = (time.perf_counter() - start) / steps
    return {"params_M": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
            "train_images_per_s": round(batch / (sum(timings) / len(timings)), 1), "infer_images_per_s": round(batch / infer, 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budget", type=float, default=600.0, help="training seconds for the target run")
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--epochs", type=int, default=60, help="schedule length; the budget usually ends training first")
    parser.add_argument("--out", type=Path, default=Path("bench_seg"))
    args = parser.parse_args()

    result = {"threads": torch.get_num_threads()}
    for name, cfg in SIZES.items():
        result[name] = throughput(cfg)
        print(f"{name}: {result[name]}", file=sys.stderr)

    config = TrainConfig(epochs=args.epochs, time_budget_s=args.budget)
    summary = train(SyntheticOffroad(args.frames, config.input_size), class_set().names, config, args.out)
    history = json.loads((args.out / "history.json").read_text())
    reached = [h["seconds"] for h in history if h["val_miou"] >= 0.8]
    result["target_run"] = {
        "seconds_to_val_miou_0.8": round(reached[0], 1) if reached else None,
        "epochs": summary["epochs_run"], "train_seconds": round(summary["train_seconds"], 1),
        "val_miou": round(summary["miou"], 3), "val_pixel_accuracy": round(summary["pixel_accuracy"], 3),
        "ece": round(summary["ece"], 3), "mean_u_correct": round(summary["mean_u_correct"], 3),
        "mean_u_wrong": round(summary["mean_u_wrong"], 3), "uncertainty_auroc": round(summary["uncertainty_auroc"], 3),
        "iou": summary["iou"], "plots": [str(args.out / "reliability.png"), str(args.out / "uncertainty.png")],
    }
    print(json.dumps(result))
    print(write_record("bench_segmentation", result | {"budget_s": args.budget, "frames": args.frames, "epochs_asked": args.epochs}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

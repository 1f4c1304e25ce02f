"""Training, evaluation, checkpoints and inference for the evidential (or softmax) segmentation.

Checkpoints are ``torch.save`` dictionaries of tensors and plain Python values (no pickled objects),
loaded with ``weights_only=True``: model weights, optimiser state, epoch, and the metadata needed to
use the model: classes, normalisation, input size, model config, head, format version.
"""

from __future__ import annotations

import json
import random
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .. import __version__, files
from .data import CAFFE_MEAN, IMAGENET_MEAN, IMAGENET_STD, SegmentationTensors, resize_pair, to_tensor
from .evidential import dirichlet_from_logits, edl_loss, kl_weight
from .metrics import SegmentationMetrics
from .config import ModelConfig
from .model import build_model, load_backbone_weights

CHECKPOINT_VERSION = 1


@dataclass
class TrainConfig:
    """How a segmentation network is trained (``evsemmap train-seg``'s flags; stored in checkpoints): its
    model, head, input size (H, W px), schedule, KL annealing, logit clamp, validation share, seed,
    optional time budget (s), normalisation and starting weights."""

    model: ModelConfig = ModelConfig()
    head: str = "evidential"  # evidential (EDL loss) | softmax (cross-entropy, the "vanilla" baseline)
    input_size: tuple[int, int] = (128, 256)
    epochs: int = 20
    batch_size: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-4
    kl_schedule: str = "paper"
    kl_anneal_epochs: int = 0  # 0: the number of epochs (paper: lambda reaches 0.5 at the last epoch)
    logit_clamp: float = 10.0
    val_fraction: float = 0.1
    seed: int = 1
    time_budget_s: float | None = None  # stop after the epoch that passes it
    normalization: str = "imagenet"  # imagenet (RGB means) | caffe (the release's BGR means on RGB, docs/compatibility.md §5.1)
    backbone_weights: str | None = None  # a state dict for the backbone; nothing is ever downloaded

    @property
    def mean_std(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The per-channel (mean, std) images are normalised with, RGB order."""
        return (IMAGENET_MEAN if self.normalization == "imagenet" else CAFFE_MEAN), IMAGENET_STD

    def validate(self) -> None:
        """Raise ValueError naming the first value out of its range (head, validation share, epochs, batch
        size, learning rate, normalisation, logit clamp)."""
        if self.head not in ("evidential", "softmax"):
            raise ValueError(f"head must be 'evidential' or 'softmax', got {self.head!r}")
        if not 0 < self.val_fraction < 1:
            raise ValueError(f"val_fraction must lie in (0, 1), got {self.val_fraction}")
        if self.epochs < 1 or self.batch_size < 1 or self.lr <= 0:
            raise ValueError("epochs and batch_size must be >= 1 and lr > 0")
        if self.normalization not in ("imagenet", "caffe"):
            raise ValueError(f"normalization must be 'imagenet' or 'caffe', got {self.normalization!r}")
        if not self.logit_clamp > 0:
            raise ValueError(f"logit_clamp must be > 0, got {self.logit_clamp}")


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's random generators."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def predict(model, images: torch.Tensor, head: str, clamp: float):
    """(alpha or probabilities [B, K, H, W], probabilities, uncertainty [B, H, W])."""
    logits = model(images)
    if head == "evidential":
        return dirichlet_from_logits(logits, clamp)
    probs = torch.softmax(logits, dim=1)
    return probs, probs, 1.0 - probs.max(dim=1).values


@torch.no_grad()
def evaluate(model, loader, head: str, clamp: float, num_classes: int) -> SegmentationMetrics:
    """The ``SegmentationMetrics`` of ``model`` over ``loader``'s (images, labels) batches, in eval mode
    without gradients."""
    model.eval()
    metrics = SegmentationMetrics(num_classes)
    for images, labels in loader:
        _, probs, unc = predict(model, images, head, clamp)
        metrics.update(probs.numpy(), unc.numpy(), labels.numpy())
    return metrics


class TimeBudgetWarning(UserWarning):
    """Training ended before its last epoch because its time budget ran out."""


def save_checkpoint(path, model, optimizer, epoch: int, config: TrainConfig, class_names, history) -> Path:
    """Write a checkpoint (weights, optimizer state and the meta ``load_checkpoint`` needs: classes,
    normalisation, training config, epoch, history) to ``path`` atomically; tensors and plain values only.
    Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "format_version": CHECKPOINT_VERSION, "written_by": f"evsemmap_warp {__version__}",
        "classes": list(class_names), "mean": list(config.mean_std[0]), "std": list(config.mean_std[1]),
        "train_config": json.dumps(asdict(config)), "epoch": epoch, "history": json.dumps(history),
    }
    checkpoint = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "meta": meta}
    return files.write_atomically(path, lambda f: torch.save(checkpoint, f))  # a killed run never leaves half a checkpoint


def load_checkpoint(path, class_names=None):
    """(model in eval mode, TrainConfig, meta, raw checkpoint). Refuses other versions and, when
    ``class_names`` is given, a checkpoint trained for another class set."""
    path = Path(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        meta = ckpt["meta"]
        cfg = json.loads(meta["train_config"])
        if not isinstance(cfg, dict) or not isinstance(cfg.get("model"), dict):
            raise TypeError("train_config is not a mapping with a model section")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such checkpoint") from None
    except Exception as exc:  # torch raises many types for corrupt files
        raise ValueError(f"{path}: not a readable evsemmap segmentation checkpoint ({type(exc).__name__}: {exc})") from None
    if meta.get("format_version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint format {meta.get('format_version')}, this version reads {CHECKPOINT_VERSION}")
    if class_names is not None and list(class_names) != list(meta["classes"]):
        raise ValueError(f"{path}: trained for classes {meta['classes']}, but {list(class_names)} were asked for")
    try:
        config = TrainConfig(**{**cfg, "model": ModelConfig(**cfg["model"]), "input_size": tuple(cfg["input_size"])})
    except (TypeError, KeyError, ValueError) as exc:  # unknown or missing config keys
        raise ValueError(f"{path}: the checkpoint's training config does not fit this version ({exc})") from None
    model = build_model(config.model)
    try:
        model.load_state_dict(ckpt["model"])
    except (RuntimeError, KeyError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path}: the weights do not fit a {config.model.arch} network of its config ({first})") from None
    model.eval()
    return model, config, meta, ckpt


def split_indices(n: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """(train, validation) indices of ``n`` items, a seeded random ``val_fraction`` (at least one) for
    validation, both sorted; raises ValueError when fewer than 2 training items would be left (batch
    normalisation needs two images in a batch)."""
    order = np.random.default_rng(seed).permutation(n)
    n_val = max(1, int(round(n * val_fraction)))
    if n - n_val < 2:
        raise ValueError(f"{n} images are too few: {n_val} go to validation and training needs at least 2")
    return sorted(order[n_val:].tolist()), sorted(order[:n_val].tolist())


def train(source, class_names, config: TrainConfig, out_dir, *, resume=None, progress: bool = True) -> dict:
    """Train on ``source`` (a dataset of (image, labels)); writes last.pt, best.pt, history.json,
    metrics.json and the calibration plots into ``out_dir``. Returns the final summary."""
    config.validate()
    out_dir = Path(out_dir)
    seed_everything(config.seed)
    train_idx, val_idx = split_indices(len(source), config.val_fraction, config.seed)
    loaders = [torch.utils.data.DataLoader(SegmentationTensors(source, idx, config.input_size, *config.mean_std), batch_size=config.batch_size,
                                           shuffle=shuffle, drop_last=shuffle and len(idx) > config.batch_size,
                                           generator=torch.Generator().manual_seed(config.seed))
               for idx, shuffle in ((train_idx, True), (val_idx, False))]
    train_loader, val_loader = loaders
    if config.model.num_classes != len(class_names):
        raise ValueError(f"the model has {config.model.num_classes} outputs but the dataset has {len(class_names)} classes")
    model = build_model(config.model)
    if config.backbone_weights and resume is None:
        load_backbone_weights(model, config.backbone_weights)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    start_epoch, history = 1, []
    if resume is not None:
        _, _, meta, ckpt = load_checkpoint(resume, class_names)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        start_epoch, history = int(meta["epoch"]) + 1, json.loads(meta["history"])
        if start_epoch > config.epochs:
            raise ValueError(f"{resume}: already trained for {meta['epoch']} epochs; ask for more than {config.epochs}")
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.epochs, last_epoch=start_epoch - 2)
    anneal = config.kl_anneal_epochs or config.epochs
    started = time.perf_counter()
    best = max((h["val_miou"] for h in history), default=-1.0)
    bar = tqdm(total=(config.epochs - start_epoch + 1) * len(train_loader), disable=not progress, unit="batch", dynamic_ncols=True)
    for epoch in range(start_epoch, config.epochs + 1):
        model.train()
        lam = kl_weight(epoch, anneal, config.kl_schedule)
        losses = []
        for images, labels in train_loader:
            logits = model(images)
            if config.head == "evidential":
                loss, _ = edl_loss(logits, labels, lam, config.logit_clamp)
            else:
                loss = torch.nn.functional.cross_entropy(logits, labels)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
            bar.update(1)
            bar.set_postfix(epoch=epoch, loss=f"{np.mean(losses[-20:]):.3f}", lr=f"{scheduler.get_last_lr()[0]:.2e}",
                            val_miou=f"{history[-1]['val_miou']:.3f}" if history else "-")
        scheduler.step()
        metrics = evaluate(model, val_loader, config.head, config.logit_clamp, len(class_names))
        history.append({"epoch": epoch, "loss": float(np.mean(losses)), "kl_lambda": lam, "val_miou": metrics.miou,
                        "val_pixel_accuracy": metrics.pixel_accuracy, "seconds": time.perf_counter() - started})
        bar.set_postfix(epoch=epoch, loss=f"{np.mean(losses):.3f}", val_miou=f"{metrics.miou:.3f}")
        save_checkpoint(out_dir / "last.pt", model, optimizer, epoch, config, class_names, history)
        if metrics.miou > best:
            best = metrics.miou
            save_checkpoint(out_dir / "best.pt", model, optimizer, epoch, config, class_names, history)
        if config.time_budget_s is not None and time.perf_counter() - started > config.time_budget_s and epoch < config.epochs:
            break
    bar.close()
    epochs_run = history[-1]["epoch"]
    summary = metrics.summary(class_names) | {"epochs_run": epochs_run, "epochs_planned": config.epochs,
                                              "train_seconds": time.perf_counter() - started}
    if epochs_run < config.epochs:
        summary["stopped_by_time_budget"] = config.time_budget_s
        warnings.warn(f"{out_dir}: training stopped by its time budget ({config.time_budget_s:g} s) after {epochs_run} of "
                      f"{config.epochs} epochs: the network is not trained to its config, and results depend on this "
                      f"machine's speed", TimeBudgetWarning, stacklevel=2)
    files.write_json_atomically(out_dir / "history.json", history, indent=1)
    files.write_json_atomically(out_dir / "metrics.json", summary, indent=1)
    metrics.save_plots(out_dir)
    return summary


def evaluate_checkpoint(checkpoint, source, out_dir=None, *, batch_size: int = 8) -> dict:
    """Metrics (and plots, when ``out_dir`` is given) of a checkpoint on every frame of ``source``."""
    model, config, meta, _ = load_checkpoint(checkpoint)
    data = SegmentationTensors(source, range(len(source)), config.input_size, meta["mean"], meta["std"])
    metrics = evaluate(model, torch.utils.data.DataLoader(data, batch_size=batch_size), config.head, config.logit_clamp, len(meta["classes"]))
    summary = metrics.summary(meta["classes"])
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        files.write_json_atomically(out_dir / "metrics.json", summary, indent=1)
        metrics.save_plots(out_dir)
    return summary


@torch.no_grad()
def infer_alpha(model, config: TrainConfig, meta: dict, images, *, batch_size: int = 4, progress: bool = False):
    """Yield (alpha or probabilities [K, H, W] float16 at the network's input size, u [H, W]) per
    uint8 RGB image [H, W, 3]: the in-memory hand-off to the projection step."""
    batch = []
    bar = tqdm(total=len(images) if hasattr(images, "__len__") else None, disable=not progress, unit="img")

    def flush():
        x = torch.stack(batch)
        out, _, unc = predict(model, x, config.head, config.logit_clamp)
        bar.update(len(batch))
        batch.clear()
        return [(o.half().numpy(), u.numpy()) for o, u in zip(out, unc)]

    for image in images:
        resized, _ = resize_pair(np.asarray(image), None, config.input_size)
        batch.append(to_tensor(resized, meta["mean"], meta["std"]))
        if len(batch) == batch_size:
            yield from flush()
    if batch:
        yield from flush()
    bar.close()

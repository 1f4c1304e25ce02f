"""2D segmentation metrics: confusion matrix, mIoU over classes present in the ground truth, pixel
accuracy, expected calibration error (equal-width bins on max-probability confidence), AUROC of the
uncertainty u for detecting errors, and the reliability / uncertainty-vs-error plots."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class SegmentationMetrics:
    """Running 2D metrics of a segmentation network, fed batch by batch (``update``): the confusion matrix, a
    reliability histogram of the winning probability (``bins`` bins) and histograms of the uncertainty u
    on right and wrong pixels."""

    num_classes: int
    bins: int = 15
    confusion: np.ndarray = field(init=False)
    bin_count: np.ndarray = field(init=False)
    bin_confidence: np.ndarray = field(init=False)
    bin_correct: np.ndarray = field(init=False)
    u_hist_correct: np.ndarray = field(init=False)
    u_hist_wrong: np.ndarray = field(init=False)

    def __post_init__(self):
        self.confusion = np.zeros((self.num_classes, self.num_classes), np.int64)
        self.bin_count = np.zeros(self.bins, np.int64)
        self.bin_confidence = np.zeros(self.bins)
        self.bin_correct = np.zeros(self.bins)
        # u in [0, 1]: 1000-bin histograms give the AUROC to ~1e-3 without keeping every pixel.
        self.u_hist_correct = np.zeros(1000, np.int64)
        self.u_hist_wrong = np.zeros(1000, np.int64)

    def update(self, probabilities: np.ndarray, uncertainty: np.ndarray, target: np.ndarray, ignore_index: int | None = None) -> None:
        """probabilities [N, K, ...], uncertainty [N, ...], target [N, ...] (class ids)."""
        pred = probabilities.argmax(axis=1).ravel()
        conf = probabilities.max(axis=1).ravel()
        u = uncertainty.ravel()
        t = target.ravel()
        keep = np.ones_like(t, bool) if ignore_index is None else t != ignore_index
        pred, conf, u, t = pred[keep], conf[keep], u[keep], t[keep]
        if len(t) and (t.min() < 0 or t.max() >= self.num_classes):
            raise ValueError(f"target ids must lie in [0, {self.num_classes - 1}], got {t.min()}..{t.max()}")
        self.confusion += np.bincount(t * self.num_classes + pred, minlength=self.num_classes**2).reshape(self.num_classes, -1)
        correct = pred == t
        b = np.minimum((conf * self.bins).astype(int), self.bins - 1)
        self.bin_count += np.bincount(b, minlength=self.bins)
        self.bin_confidence += np.bincount(b, weights=conf, minlength=self.bins)
        self.bin_correct += np.bincount(b, weights=correct, minlength=self.bins)
        ub = np.minimum((np.clip(u, 0, 1) * 1000).astype(int), 999)
        self.u_hist_correct += np.bincount(ub[correct], minlength=1000)
        self.u_hist_wrong += np.bincount(ub[~correct], minlength=1000)

    @property
    def iou(self) -> np.ndarray:
        """Per class; NaN for classes absent from the ground truth (they are left out of mIoU)."""
        tp = np.diag(self.confusion).astype(float)
        gt = self.confusion.sum(axis=1)
        union = gt + self.confusion.sum(axis=0) - tp
        return np.where(gt > 0, tp / np.maximum(union, 1), np.nan)

    @property
    def miou(self) -> float:
        """Mean IoU over the classes present in the ground truth (NaN when none is)."""
        return float(np.nanmean(self.iou)) if np.isfinite(self.iou).any() else float("nan")

    @property
    def pixel_accuracy(self) -> float:
        """Share of pixels labelled right."""
        return float(np.trace(self.confusion) / max(self.confusion.sum(), 1))

    @property
    def ece(self) -> float:
        """Expected calibration error of the winning probability over the reliability bins."""
        n = self.bin_count.sum()
        gap = np.abs(self.bin_correct - self.bin_confidence)  # per bin: |sum correct - sum confidence|
        return float(gap.sum() / max(n, 1))

    def merged(self, other: "SegmentationMetrics") -> "SegmentationMetrics":
        """The metrics of both inputs together (the counts and histograms added)."""
        if (other.num_classes, other.bins) != (self.num_classes, self.bins):
            raise ValueError(f"cannot merge metrics of {other.num_classes} classes / {other.bins} bins into {self.num_classes} / {self.bins}")
        out = SegmentationMetrics(self.num_classes, self.bins)
        for name in ("confusion", "bin_count", "bin_confidence", "bin_correct", "u_hist_correct", "u_hist_wrong"):
            setattr(out, name, getattr(self, name) + getattr(other, name))
        return out

    def mean_uncertainty(self, correct: bool) -> float:
        """Mean u over the pixels labelled right (``correct``) or wrong."""
        hist = self.u_hist_correct if correct else self.u_hist_wrong
        centers = (np.arange(1000) + 0.5) / 1000
        return float((hist * centers).sum() / max(hist.sum(), 1))

    @property
    def uncertainty_auroc(self) -> float:
        """P(u of a wrong pixel > u of a right one), ties counted half: 0.5 = u says nothing."""
        wrong, right = self.u_hist_wrong.astype(float), self.u_hist_correct.astype(float)
        if wrong.sum() == 0 or right.sum() == 0:
            return float("nan")
        right_below = np.cumsum(right) - right
        return float((wrong * (right_below + 0.5 * right)).sum() / (wrong.sum() * right.sum()))

    def summary(self, class_names) -> dict:
        """The metrics as plain values for ``metrics.json``: mIoU, pixel accuracy, ECE, the AUROC of u, mean
        u right and wrong, and IoU per class (None where absent)."""
        return {
            "miou": self.miou, "pixel_accuracy": self.pixel_accuracy, "ece": self.ece,
            "uncertainty_auroc": self.uncertainty_auroc,
            "mean_u_correct": self.mean_uncertainty(True), "mean_u_wrong": self.mean_uncertainty(False),
            "iou": {name: (None if np.isnan(v) else float(v)) for name, v in zip(class_names, self.iou)},
        }

    def save_plots(self, out_dir) -> list[Path]:
        """reliability.png (accuracy vs confidence per bin) and uncertainty.png (u histograms)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        edges = np.linspace(0, 1, self.bins + 1)
        used = self.bin_count > 0
        acc = np.where(used, self.bin_correct / np.maximum(self.bin_count, 1), 0)
        fig, ax = plt.subplots(figsize=(4.5, 4.5))
        ax.bar(edges[:-1], acc, width=1 / self.bins, align="edge", edgecolor="k", label="accuracy")
        ax.plot([0, 1], [0, 1], "r--", label="perfect calibration")
        ax.set(xlabel="confidence (max p)", ylabel="accuracy", title=f"Reliability, ECE {self.ece:.3f}")
        ax.legend(loc="upper left")
        fig.tight_layout()
        paths = [out_dir / "reliability.png"]
        fig.savefig(paths[0], dpi=110)
        plt.close(fig)
        fig, ax = plt.subplots(figsize=(5.5, 3.5))
        centers = (np.arange(1000) + 0.5) / 1000
        for hist, name in ((self.u_hist_correct, "correct"), (self.u_hist_wrong, "wrong")):
            coarse = hist.reshape(50, 20).sum(axis=1)
            ax.plot(centers.reshape(50, 20).mean(axis=1), coarse / max(coarse.sum(), 1), label=f"{name} pixels")
        ax.set(xlabel="uncertainty u = K / S", ylabel="fraction of pixels", title=f"AUROC of u for errors: {self.uncertainty_auroc:.3f}")
        ax.legend()
        fig.tight_layout()
        paths.append(out_dir / "uncertainty.png")
        fig.savefig(paths[1], dpi=110)
        plt.close(fig)
        return paths

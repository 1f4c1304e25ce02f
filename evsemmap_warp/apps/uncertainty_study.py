"""Does the network's uncertainty flag its errors, and what does the mapping make of it (issue 29)?

For one condition of a study (a network's alpha on a held-out sequence), measured where the mapping sees it:
- on the camera pixels and on the projected LiDAR points: the AUROC of u = K / S for wrong predictions, the
  expected calibration error and its reliability bins, and the u histograms of right and wrong predictions
  (``SegmentationMetrics``);
- per method: the share of points its uncertainty threshold drops and how many of those were right, and the
  kernel lengths its adaptive length gives the points it keeps (with the share under half a voxel, and the
  share whose kernel reaches no voxel center at all, so that the point updates nothing);
- per map: the Brier scores (``MapScores``) and the error rate of the map's labels by decile of its variance.

Conditions of several seeds or drives add up (``merge``): histograms are summed, rates recomputed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.integrators import make_integrator, threshold_mask
from ..core.mapper import VoxelState
from ..geometry.projection import sample_map
from ..segmentation.metrics import SegmentationMetrics
from ..voxel_keys import voxel_index_of

LENGTH_EDGES_M = np.linspace(0.0, 1.0, 51)  # histogram of kernel lengths (m); the offroad preset's longest is 0.82 m
DECILES = 10
# what cached diagnostics hold: raise it when they gain or change a count, so that older caches are recomputed
DIAGNOSTICS_VERSION = 1


@dataclass
class MethodDiagnostics:
    """What one method does with a condition's points (counts, so that conditions add up) and its map's
    error rate by variance decile."""

    adaptive_length: bool = False  # the method's kernel length follows u
    points: int = 0  # projected points with scored ground truth
    right: int = 0  # of them, the network's label was right
    dropped: int = 0  # dropped by the method's uncertainty threshold
    dropped_right: int = 0  # of the dropped, the network's label was right
    kept_short: int = 0  # kept, with a kernel shorter than half a voxel
    kept_reaching_nothing: int = 0  # kept, with a kernel that reaches no voxel center (the point updates nothing)
    kept_reaching_nothing_right: int = 0
    class_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [K] scored points per true class
    class_dropped: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [K] of them, dropped
    length_hist: np.ndarray = field(default_factory=lambda: np.zeros(len(LENGTH_EDGES_M) - 1, np.int64))
    decile_errors: np.ndarray = field(default_factory=lambda: np.zeros(DECILES, np.int64))
    decile_queries: np.ndarray = field(default_factory=lambda: np.zeros(DECILES, np.int64))
    brier: list = field(default_factory=list)  # (min-max, analytic, per query) of each map

    def merge(self, other: "MethodDiagnostics") -> "MethodDiagnostics":
        """Both together: the counts and histograms added, the maps' Brier scores listed."""
        out = MethodDiagnostics(adaptive_length=self.adaptive_length or other.adaptive_length)
        for name in ("points", "right", "dropped", "dropped_right", "kept_short", "kept_reaching_nothing", "kept_reaching_nothing_right"):
            setattr(out, name, getattr(self, name) + getattr(other, name))
        for name in ("length_hist", "decile_errors", "decile_queries", "class_points", "class_dropped"):
            setattr(out, name, getattr(self, name) + getattr(other, name))
        out.brier = self.brier + other.brier
        return out

    def summary(self) -> dict:
        """Shares (of the scored points), rates and the mean Brier scores as plain values."""
        kept = self.points - self.dropped

        def share(a, b):
            return float(a / b) if b else None

        brier = np.array([b for b in self.brier if None not in b], float).reshape(-1, 3)
        lengths = np.repeat((LENGTH_EDGES_M[:-1] + LENGTH_EDGES_M[1:]) / 2, self.length_hist)
        return {
            "dropped_share": share(self.dropped, self.points),
            "dropped_right_share": share(self.dropped_right, self.dropped),  # precision of the drop, inverted
            "kept_right_share": share(self.right - self.dropped_right, kept),
            "kept_short_share": share(self.kept_short, kept),
            "kept_reaching_nothing_share": share(self.kept_reaching_nothing, kept),
            "kept_reaching_nothing_right_share": share(self.kept_reaching_nothing_right, self.kept_reaching_nothing),
            "dropped_share_by_true_class": [share(d, p) for d, p in zip(self.class_dropped, self.class_points)],
            "median_length_m": float(np.median(lengths)) if len(lengths) and self.adaptive_length else None,
            "error_rate_by_variance_decile": [share(e, q) for e, q in zip(self.decile_errors, self.decile_queries)],
            "brier_minmax": float(brier[:, 0].mean()) if len(brier) else None,
            "brier_analytic": float(brier[:, 1].mean()) if len(brier) else None,
            "brier_per_query": float(brier[:, 2].mean()) if len(brier) else None,
        }


@dataclass
class ConditionDiagnostics:
    """A condition's (or several merged) pixel and point metrics of the network, and per method what the
    mapping does with the points."""

    pixels: SegmentationMetrics
    points: SegmentationMetrics
    methods: dict  # method -> MethodDiagnostics

    def merge(self, other: "ConditionDiagnostics") -> "ConditionDiagnostics":
        """Both conditions together (seeds, drives): the network's metrics and each method's counts added."""
        return ConditionDiagnostics(self.pixels.merged(other.pixels), self.points.merged(other.points),
                                    {m: d.merge(other.methods[m]) for m, d in self.methods.items() if m in other.methods})

    def summary(self) -> dict:
        """The headline numbers as plain values (JSON, tables)."""
        def network(metrics: SegmentationMetrics) -> dict:
            return {"accuracy": metrics.pixel_accuracy, "ece": metrics.ece, "uncertainty_auroc": metrics.uncertainty_auroc,
                    "mean_u_right": metrics.mean_uncertainty(True), "mean_u_wrong": metrics.mean_uncertainty(False)}

        return {"pixels": network(self.pixels), "points": network(self.points), "methods": {m: d.summary() for m, d in self.methods.items()}}

    def arrays(self) -> dict:
        """Everything, histograms included, as plain values (cached per condition, summed across seeds)."""
        def metrics(m: SegmentationMetrics) -> dict:
            return {k: getattr(m, k).tolist() for k in ("confusion", "bin_count", "bin_confidence", "bin_correct", "u_hist_correct", "u_hist_wrong")}

        def method(d: MethodDiagnostics) -> dict:
            return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.__dict__.items()}

        return {"pixels": metrics(self.pixels), "points": metrics(self.points), "methods": {m: method(d) for m, d in self.methods.items()}}

    @classmethod
    def from_arrays(cls, data: dict) -> "ConditionDiagnostics":
        """The diagnostics ``arrays()`` wrote (read back from the cache)."""
        def metrics(d: dict) -> SegmentationMetrics:
            m = SegmentationMetrics(len(d["confusion"]), bins=len(d["bin_count"]))
            for k, v in d.items():
                setattr(m, k, np.asarray(v, dtype=getattr(m, k).dtype))
            return m

        def method(d: dict) -> MethodDiagnostics:
            out = MethodDiagnostics()
            for k, v in d.items():
                if isinstance(getattr(out, k), np.ndarray):
                    v = np.asarray(v, dtype=np.int64)
                elif k == "brier":
                    v = [tuple(b) for b in v]
                setattr(out, k, v)
            return out

        return cls(metrics(data["pixels"]), metrics(data["points"]), {m: method(d) for m, d in data["methods"].items()})


def uncertainty_of(alpha: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Probabilities alpha / S and uncertainty u = K / S of Dirichlet concentrations along ``axis``."""
    alpha = np.asarray(alpha, np.float64)
    total = alpha.sum(axis=axis, keepdims=True)
    return alpha / total, (alpha.shape[axis] / total).squeeze(axis)


def pixel_labels_at_alpha(labels: np.ndarray, alpha_shape: tuple[int, int]) -> np.ndarray:
    """The label image [H, W] read at the centers of the network's output pixels [h, w] (nearest)."""
    height, width = labels.shape
    h, w = alpha_shape
    rows = np.minimum(((np.arange(h) + 0.5) * height / h).astype(np.int64), height - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * width / w).astype(np.int64), width - 1)
    return labels[np.ix_(rows, cols)]


def network_metrics(num_classes: int, probabilities: np.ndarray, uncertainty: np.ndarray, truth: np.ndarray, scored) -> SegmentationMetrics:
    """``SegmentationMetrics`` of predictions [N, K] (u [N]) against ``truth`` [N], on the scored classes only."""
    metrics = SegmentationMetrics(num_classes)
    keep = np.isin(truth, scored)
    if keep.any():
        metrics.update(probabilities[keep], uncertainty[keep], truth[keep])
    return metrics


def method_diagnostics(mapping, num_classes: int, insertions, scored, mapper=None, gt=None, brier=None) -> MethodDiagnostics:
    """What a method (``mapping``: its MappingConfig) does with a condition's points: ``insertions`` is a list
    of (points [N, 3], u [N], right [N] bool, truth [N], predicted [N]) per map insertion, the threshold
    taken as the mapper takes it. With ``mapper`` and ``gt`` (points, labels): the error rate of the map's
    labels by decile of its variance at the scored ground-truth points; ``brier``: the map's three Brier
    scores."""
    out = MethodDiagnostics(adaptive_length=bool(mapping.adaptive_length), class_points=np.zeros(num_classes, np.int64),
                            class_dropped=np.zeros(num_classes, np.int64))
    integrator = make_integrator(mapping, num_classes)
    half_voxel = 0.5 * mapping.resolution_m
    for points, u, right, truth, predicted in insertions:
        keep = np.ones(len(u), bool)
        if mapping.uncertainty_threshold and len(u):
            keep, _ = threshold_mask(mapping, u, predicted)
        scored_points = np.isin(truth, scored)
        out.points += int(scored_points.sum())
        out.right += int((right & scored_points).sum())
        out.dropped += int((~keep & scored_points).sum())
        out.dropped_right += int((~keep & right & scored_points).sum())
        out.class_points += np.bincount(truth[scored_points], minlength=num_classes)
        out.class_dropped += np.bincount(truth[scored_points & ~keep], minlength=num_classes)
        kept = keep & scored_points
        if not kept.any() or not hasattr(integrator, "kernel_lengths"):
            continue
        lengths = integrator.kernel_lengths(u[kept])
        # the nearest voxel center is the point's own voxel's; a sparse kernel is zero at and beyond its length
        own = voxel_index_of(points[kept], mapping.resolution_m, integrator.grid_offset_m, np.zeros(3, np.int64))
        centers = (own + 0.5) * mapping.resolution_m + integrator.grid_offset_m
        nothing = np.linalg.norm(points[kept] - centers, axis=1) >= lengths
        out.kept_short += int((lengths < half_voxel).sum())
        out.kept_reaching_nothing += int(nothing.sum())
        out.kept_reaching_nothing_right += int((nothing & right[kept]).sum())
        out.length_hist += np.histogram(np.clip(lengths, 0, LENGTH_EDGES_M[-1] - 1e-9), LENGTH_EDGES_M)[0]
    if mapper is not None and gt is not None:
        points, labels = gt
        scored_gt = np.isin(labels, scored)
        result = mapper.query(np.asarray(points, np.float64)[scored_gt])
        occupied = result.state == VoxelState.OCCUPIED
        wrong = result.label[occupied] != labels[scored_gt][occupied]
        order = np.argsort(result.variance[occupied], kind="stable")  # deciles by rank: many voxels share a variance
        for k, part in enumerate(np.array_split(order, DECILES)):
            out.decile_errors[k] += int(wrong[part].sum())
            out.decile_queries[k] += len(part)
    if brier is not None:
        out.brier.append(tuple(brier))
    return out


def plot_group(name: str, diagnostics: ConditionDiagnostics, methods, resolution_m: float, path) -> None:
    """One figure per group of conditions: u histograms of right and wrong points, the reliability diagram,
    the kept points' kernel lengths per method, and each map's error rate by variance decile."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(19, 4.2))
    points = diagnostics.points
    centers = (np.arange(1000) + 0.5) / 1000
    for hist, label in ((points.u_hist_correct, "right"), (points.u_hist_wrong, "wrong")):
        coarse = hist.reshape(50, 20).sum(axis=1)
        axes[0].plot(centers.reshape(50, 20).mean(axis=1), coarse / max(coarse.sum(), 1), label=f"{label} points ({hist.sum():,})")
    axes[0].set(xlabel="uncertainty u = K / S", ylabel="share of points", title=f"u of the network's labels, AUROC {points.uncertainty_auroc:.3f}")
    axes[0].legend(fontsize=8)
    edges = np.linspace(0, 1, points.bins + 1)
    used = points.bin_count > 0
    accuracy = np.where(used, points.bin_correct / np.maximum(points.bin_count, 1), 0)
    axes[1].bar(edges[:-1], accuracy, width=1 / points.bins, align="edge", edgecolor="k", label="accuracy of the points")
    axes[1].plot([0, 1], [0, 1], "r--", label="perfect calibration")
    axes[1].set(xlabel="confidence (max p)", ylabel="accuracy", title=f"Reliability at the points, ECE {points.ece:.3f}")
    axes[1].legend(fontsize=8, loc="upper left")
    length_centers = (LENGTH_EDGES_M[:-1] + LENGTH_EDGES_M[1:]) / 2
    for m in methods:
        d = diagnostics.methods.get(m)
        if d is not None and d.adaptive_length and d.length_hist.sum():
            axes[2].plot(length_centers, d.length_hist / d.length_hist.sum(), label=m)
    axes[2].axvline(0.5 * resolution_m, color="0.5", ls=":", label="half a voxel")
    axes[2].set(xlabel="kernel length (m)", ylabel="share of kept points", title="Kernel lengths of the kept points")
    axes[2].legend(fontsize=8)
    for m in methods:
        d = diagnostics.methods.get(m)
        if d is not None and d.decile_queries.sum():
            rates = d.decile_errors / np.maximum(d.decile_queries, 1)
            axes[3].plot(np.arange(1, DECILES + 1), 100 * rates, marker="o", label=m)
    axes[3].set(xlabel="variance decile of the map's label (1 = least)", ylabel="error rate (%)", title="Map errors by variance decile")
    axes[3].legend(fontsize=8)
    fig.suptitle(name)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

"""Stage D (docs/algorithm.md §4): a map queried at 3D ground-truth points.

* Only ground-truth points of the scored classes (the paper's seven, ids 2..8) count.
* The confusion matrix (full K x K, ground truth rows, prediction columns) holds the scored queries
  that land in OCCUPIED voxels; queries the map calls free or unknown are left out of it.
* IoU per scored class present in the ground truth (absent classes are None, shown "-"); mIoU over
  the present ones; Acc = correct / scored occupied queries (sky or void predictions count as wrong);
  O.Acc = scored occupied queries / scored queries.
* Brier score of the variance map, x100: per occupied voxel holding >= 1 scored ground-truth point,
  "correct" = the voxel's label equals the majority ground truth of its points, confidence = 1 - the
  normalised variance of its label; normalised by min-max over those voxels (primary) and by the
  analytic bound 1 / (4 (K alpha0 + 1)); plus the per-query variant.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.mapper import VoxelState

PAPER_SCORED_CLASSES = (2, 3, 4, 5, 6, 7, 8)


@dataclass
class MapScores:
    """A map's scores at the 3D ground truth (the module's definitions): the confusion matrix [K, K] (truth
    rows), IoU per scored class (None where absent), mIoU, Acc and O.Acc in [0, 1], the Brier scores
    (x100; None without occupied voxels), and the query counts."""

    class_names: tuple[str, ...]
    scored_classes: tuple[int, ...]
    confusion: np.ndarray  # [K, K] int64
    iou: dict[str, float | None]
    miou: float
    accuracy: float
    occupied_accuracy: float
    brier_minmax: float | None
    brier_analytic: float | None
    brier_per_query: float | None
    scored_queries: int
    occupied_queries: int
    scored_voxels: int
    truth_counts: np.ndarray = None  # [K] scored ground-truth queries per class (occupied or not)
    extra: dict = field(default_factory=dict)

    def row(self) -> dict:
        """Flat dict for tables: per-class IoU, mIoU, Acc, O.Acc and BS in percent."""
        out = {name: (None if v is None else 100 * v) for name, v in self.iou.items()}
        out |= {"mIoU": 100 * self.miou, "Acc": 100 * self.accuracy, "O.Acc": 100 * self.occupied_accuracy,
                "BS": self.brier_minmax, "BS (analytic)": self.brier_analytic, "BS (per query)": self.brier_per_query}
        return out

    def as_dict(self) -> dict:
        """The scores as plain values for JSON (``scores.json``): lists instead of arrays, plus ``extra``."""
        return {"class_names": list(self.class_names), "scored_classes": list(self.scored_classes),
                "confusion": self.confusion.tolist(), "iou": self.iou, "miou": self.miou, "accuracy": self.accuracy,
                "occupied_accuracy": self.occupied_accuracy, "brier_minmax": self.brier_minmax,
                "brier_analytic": self.brier_analytic, "brier_per_query": self.brier_per_query,
                "scored_queries": self.scored_queries, "occupied_queries": self.occupied_queries,
                "scored_voxels": self.scored_voxels, "truth_counts": self.truth_counts.tolist()} | self.extra


def _brier(correct: np.ndarray, variance: np.ndarray, low: float, high: float) -> float | None:
    if len(correct) == 0:
        return None
    normalised = np.clip((variance - low) / (high - low), 0, 1) if high > low else np.zeros_like(variance)
    return float(100 * np.mean((correct.astype(float) - (1 - normalised)) ** 2))


def evaluate_map(mapper, points: np.ndarray, labels: np.ndarray, scored_classes=PAPER_SCORED_CLASSES) -> MapScores:
    """Query ``mapper`` at ground-truth ``points`` [M, 3] with class ``labels`` [M] (the map's ids)."""
    points = np.asarray(points, np.float64)
    labels = np.asarray(labels, np.int64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) != len(labels):
        raise ValueError(f"ground truth: need points [M, 3] and labels [M], got {list(points.shape)} and {list(labels.shape)}")
    k = mapper.num_classes
    if len(labels) and (labels.min() < 0 or labels.max() >= k):
        raise ValueError(f"ground truth: labels must lie in 0..{k - 1} (the map's classes), got {labels.min()}..{labels.max()}")
    scored_classes = tuple(int(c) for c in scored_classes)
    scored = np.isin(labels, scored_classes)
    points, labels = points[scored], labels[scored]
    result = mapper.query(points)
    occupied = result.state == VoxelState.OCCUPIED
    truth, predicted = labels[occupied], result.label[occupied].astype(np.int64)
    confusion = np.bincount(truth * k + predicted, minlength=k * k).reshape(k, k)
    truth_counts = np.bincount(labels, minlength=k)
    iou, miou, accuracy, occupied_accuracy = _confusion_scores(confusion, truth_counts, scored_classes, mapper.class_names)
    occupied_count = int(occupied.sum())

    # Brier score per occupied voxel with ground truth: group the occupied queries by voxel.
    variance = result.variance[occupied].astype(np.float64)
    voxel = result.voxel_index[occupied]
    brier_minmax = brier_analytic = brier_query = None
    voxels = 0
    if occupied_count:
        _, group, counts = np.unique(voxel, axis=0, return_inverse=True, return_counts=True)
        group = group.ravel()
        voxels = len(counts)
        votes = np.zeros((voxels, k), np.int64)
        np.add.at(votes, (group, truth), 1)
        majority = votes.argmax(axis=1)
        first = np.zeros(voxels, np.int64)
        first[group[::-1]] = np.arange(len(group))[::-1]
        voxel_label, voxel_variance = predicted[first], variance[first]
        voxel_correct = voxel_label == majority
        bound = 1.0 / (4 * (k * mapper.config.prior + 1))
        brier_minmax = _brier(voxel_correct, voxel_variance, voxel_variance.min(), voxel_variance.max())
        brier_analytic = _brier(voxel_correct, voxel_variance, 0.0, bound)
        brier_query = _brier(truth == predicted, variance, variance.min(), variance.max())
    return MapScores(
        class_names=tuple(mapper.class_names), scored_classes=scored_classes, confusion=confusion, iou=iou,
        miou=miou, accuracy=accuracy, occupied_accuracy=occupied_accuracy,
        brier_minmax=brier_minmax, brier_analytic=brier_analytic, brier_per_query=brier_query,
        scored_queries=int(len(labels)), occupied_queries=occupied_count, scored_voxels=voxels, truth_counts=truth_counts,
    )


def _confusion_scores(confusion: np.ndarray, truth_counts: np.ndarray, scored_classes, class_names):
    """IoU per scored class (None where the ground truth lacks it), mIoU over the present ones, Acc
    over the occupied queries (the confusion matrix), O.Acc = occupied / scored queries."""
    iou, present = {}, []
    for c in scored_classes:
        tp = confusion[c, c]
        fp = confusion[:, c].sum() - tp
        fn = confusion[c, :].sum() - tp
        if truth_counts[c] > 0:
            iou[class_names[c]] = float(tp / (tp + fp + fn)) if tp + fp + fn > 0 else 0.0
            present.append(iou[class_names[c]])
        else:
            iou[class_names[c]] = None
    occupied, scored = int(confusion.sum()), int(truth_counts.sum())
    return (iou, float(np.mean(present)) if present else 0.0, float(np.trace(confusion) / occupied) if occupied else 0.0,
            float(occupied / scored) if scored else 0.0)


def pool_scores(parts: list[MapScores]) -> MapScores:
    """docs/algorithm.md §4.5: several maps (e.g. the 5 RELLIS-3D folds) scored as one, from their summed
    confusion matrices and ground-truth counts. Brier scores are per-map normalised, so the pooled
    ones are the means of the parts'."""
    first = parts[0]
    confusion = sum(p.confusion for p in parts)
    truth_counts = sum(p.truth_counts for p in parts)
    iou, miou, accuracy, occupied_accuracy = _confusion_scores(confusion, truth_counts, first.scored_classes, first.class_names)

    def mean(name):
        values = [getattr(p, name) for p in parts if getattr(p, name) is not None]
        return float(np.mean(values)) if values else None

    return MapScores(
        class_names=first.class_names, scored_classes=first.scored_classes, confusion=confusion, iou=iou, miou=miou,
        accuracy=accuracy, occupied_accuracy=occupied_accuracy, brier_minmax=mean("brier_minmax"),
        brier_analytic=mean("brier_analytic"), brier_per_query=mean("brier_per_query"),
        scored_queries=sum(p.scored_queries for p in parts), occupied_queries=sum(p.occupied_queries for p in parts),
        scored_voxels=sum(p.scored_voxels for p in parts), truth_counts=truth_counts,
    )


def markdown_table(rows: dict[str, dict], columns: list[str], digits: int = 1) -> str:
    """Rows (name -> row dict) as a Markdown table; None is shown as '-'."""
    def cell(v):
        return "-" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))

    lines = ["| method | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    lines += ["| " + name + " | " + " | ".join(cell(row.get(c)) for c in columns) + " |" for name, row in rows.items()]
    return "\n".join(lines)


def scored_class_names(scores: MapScores) -> list[str]:
    """The names of the classes ``scores`` scored, in id order."""
    return [scores.class_names[c] for c in scores.scored_classes]

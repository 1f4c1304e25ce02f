"""Maps set against each other in the viewer: which maps are shown (the one chosen, or all side by side),
and two maps of one frame and lattice compared voxel by voxel (``MapDiff``: labels that differ, colored by
which map agrees with a ground truth when one is given, and the variance difference); ``Comparison`` is
the part of ``MapViewer`` that shows them."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .colors import DIVERGING, color_bar_image, diverging, swatch_image
from .map_layer import MapLayer

DIFF_MODES = ("off", "labels differ", "variance difference")
DIFF_COLORS = {
    "first map agrees with the truth": (0, 158, 115),
    "second map agrees with the truth": (0, 114, 178),
    "neither agrees with the truth": (213, 94, 0),
    "labels differ (no truth here)": (204, 121, 167),
}


@dataclass
class MapDiff:
    """Voxels of map ``a`` with a voxel of map ``b`` at the same place (same lattice): rows of each,
    whether their labels differ, the truth's label there (-1: none) and the variance difference."""

    a_name: str
    b_name: str
    a_rows: np.ndarray
    b_rows: np.ndarray
    differ: np.ndarray
    a_label: np.ndarray
    b_label: np.ndarray
    truth: np.ndarray
    variance_difference: np.ndarray  # variance in a - variance in b
    only_a: int
    only_b: int
    classes: list[str] = field(default_factory=list)

    def category(self) -> np.ndarray:
        """Per compared voxel: 0 a agrees with the truth, 1 b agrees, 2 neither, 3 no truth; -1 same label."""
        out = np.full(len(self.a_rows), -1, np.int64)
        known = self.truth >= 0
        out[self.differ & ~known] = 3
        out[self.differ & known & (self.a_label == self.truth)] = 0
        out[self.differ & known & (self.b_label == self.truth)] = 1
        out[self.differ & known & (self.a_label != self.truth) & (self.b_label != self.truth)] = 2
        return out

    def counts(self, keep: np.ndarray | None = None) -> dict[str, int]:
        """Counts over the compared voxels (``keep``: a mask over them, e.g. the shown ones)."""
        keep = np.ones(len(self.a_rows), bool) if keep is None else keep
        category = self.category()[keep]
        names = list(DIFF_COLORS)
        out = {"compared": int(keep.sum()), "differ": int(self.differ[keep].sum()), "with truth": int((self.truth[keep] >= 0).sum())}
        out.update({name: int((category == k).sum()) for k, name in enumerate(names)})
        known = self.truth[keep] >= 0
        out["first map right"] = int((self.a_label[keep][known] == self.truth[keep][known]).sum())
        out["second map right"] = int((self.b_label[keep][known] == self.truth[keep][known]).sum())
        return out

    def describe(self, keep: np.ndarray | None = None) -> str:
        """Markdown: how many voxels differ, and, with a truth, which map agrees with it where they do."""
        c = self.counts(keep)
        share = 100.0 * c["differ"] / c["compared"] if c["compared"] else 0.0
        lines = [f"first **{self.a_name}**, second **{self.b_name}**",
                 f"{c['compared']:,} voxels shown in both; labels differ in **{c['differ']:,}** ({share:.1f} %)",
                 f"only in the first: {self.only_a:,}; only in the second: {self.only_b:,}"]
        if c["with truth"]:
            lines.append(f"where the truth says ({c['with truth']:,} voxels): first right {c['first map right']:,}, "
                         f"second right {c['second map right']:,}")
            lines.append("of the differing: " + ", ".join(f"{name} **{c[name]:,}**" for name in DIFF_COLORS))
        return "\n\n".join(lines)


def compare_maps(a, b, truth: np.ndarray | None = None) -> MapDiff:
    """Match the voxels of two viewer ``MapLayer``s of one frame and lattice by place; ``truth``: the
    truth's label per voxel of ``a`` in ``a``'s class indices (-1: none), ``load_truth``."""
    if abs(a.resolution - b.resolution) > 1e-9 * a.resolution or abs(a.grid_offset - b.grid_offset) > 1e-9:
        raise ValueError(f"compare: {a.name} has {a.resolution} m voxels (grid offset {a.grid_offset}) and {b.name} "
                         f"{b.resolution} m ({b.grid_offset}): only maps of one voxel lattice are compared voxel by voxel")
    if [c.lower() for c in a.classes] != [c.lower() for c in b.classes]:
        raise ValueError(f"compare: {a.name} and {b.name} have different class lists ({a.classes} and {b.classes})")
    b_of_a = b.voxel_at(a.centers) if len(a.centers) else np.zeros(0, np.int64)
    a_rows = np.flatnonzero(b_of_a >= 0)
    b_rows = b_of_a[a_rows]
    a_label, b_label = a.label[a_rows].astype(np.int64), b.label[b_rows].astype(np.int64)
    truth_rows = np.full(len(a_rows), -1, np.int64) if truth is None else np.asarray(truth, np.int64)[a_rows]
    return MapDiff(a.name, b.name, a_rows, b_rows, a_label != b_label, a_label, b_label, truth_rows,
                   a.variance[a_rows].astype(np.float64) - b.variance[b_rows].astype(np.float64),
                   only_a=int(len(a.centers) - len(a_rows)), only_b=int(len(b.centers) - len(np.unique(b_rows))), classes=list(a.classes))


def load_truth(path, layer, frame=None) -> np.ndarray:
    """The ground truth's label of every voxel of ``layer`` (its class indices, -1 where none):

    - a projection (``evsemmap project``'s ground_truth.npz: ``points`` [N, 3] in the world frame,
      ``labels`` [N] remap-v3 class indices, ``frame``): the most frequent label of the points in a voxel;
    - a map file: its label where it has an OCCUPIED voxel.

    Class names are matched by name; a frame recorded in the file must be ``frame``."""
    from ...core.map_file import is_compact
    from ...core.mapper import read_map_arrays
    from ...frames import WorldFrame, check_same_frame

    path = Path(path)
    names = [c.lower() for c in layer.classes]
    map_file = path.is_file() and is_compact(path)  # a map file of format 3 or later is no npz
    try:
        arrays = {}
        if not map_file:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
    except FileNotFoundError:
        raise ValueError(f"{path}: no such ground-truth file") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz ({exc})") from None
    if "points" in arrays and "labels" in arrays:
        from ...classes import class_set

        recorded = arrays.get("frame")
        if recorded is not None:
            truth_frame = WorldFrame.from_dict(json.loads(str(recorded)), f"{path}: frame")
            check_same_frame("compare with the truth", (str(layer.path), frame), (str(path), truth_frame))
        points = np.asarray(arrays["points"], np.float64).reshape(-1, 3)
        labels = np.asarray(arrays["labels"], np.int64).reshape(-1)
        if len(points) != len(labels):
            raise ValueError(f"{path}: {len(points)} points but {len(labels)} labels")
        source_names = [n.lower() for n in class_set("remap_v3").names]
        table = np.array([names.index(n) if n in names else -1 for n in source_names] + [-1], np.int64)
        labels = table[np.where((labels >= 0) & (labels < len(source_names)), labels, len(source_names))]
        rows = layer.voxel_at(points)
        ok = (rows >= 0) & (labels >= 0)
        k = len(names)
        votes = np.bincount(rows[ok] * k + labels[ok], minlength=len(layer.centers) * k).reshape(len(layer.centers), k)
        return np.where(votes.sum(axis=1) > 0, votes.argmax(axis=1), -1)
    if map_file or "alpha" in arrays or "centers" in arrays:
        data, meta = read_map_arrays(path)
        other = MapLayer.from_arrays(path.stem, path, data, meta)
        check_same_frame("compare with the truth", (str(layer.path), frame), (str(path), WorldFrame.from_dict(meta.get("frame"), f"{path}: meta.frame")))
        other_names = [c.lower() for c in other.classes]
        table = np.array([names.index(n) if n in names else -1 for n in other_names], np.int64)
        rows = other.voxel_at(layer.centers)
        found = rows >= 0
        out = np.full(len(layer.centers), -1, np.int64)
        occupied = other.state[rows[found]] == 2
        out[np.flatnonzero(found)[occupied]] = table[other.label[rows[found]][occupied]]
        return out
    raise ValueError(f"{path}: not a ground truth: expected 'points' and 'labels' (evsemmap project's ground_truth.npz) "
                     f"or a map file, found arrays {sorted(arrays)}")


class Comparison:
    """The part of a ``MapViewer`` that says which maps are shown and where: the map chosen in *Map*, every map
    side by side (shifted ``side_by_side_step`` m apart along x), or the chosen map compared with the *Second
    map* (*Compare maps*), against the ground truth at ``truth_path`` (``load_truth``) when one is given."""

    def __init__(self, viewer, truth_path: Path | None):
        self.viewer = viewer
        self.truth_path = truth_path
        self.side_by_side_step = 0.0
        self._truth: dict = {}
        self._diffs: dict = {}

    def pair(self) -> tuple[int, int] | None:
        """(first, second) map indices while a comparison is shown."""
        viewer = self.viewer
        if viewer.gui_diff is None or viewer.gui_diff.value == "off":
            return None
        first, second = int(viewer.gui_map.value.split(":")[0]), int(viewer.gui_diff_against.value.split(":")[0])
        return (first, second) if first != second else None

    def shown_layers(self) -> list[int]:
        """The maps drawn now: the first of a comparison, every map side by side, or the one chosen."""
        if self.pair() is not None:
            return [self.pair()[0]]
        if self.viewer.gui_side_by_side.value:
            return list(range(len(self.viewer.layers)))
        return [int(self.viewer.gui_map.value.split(":")[0])]

    def shift(self, i: int) -> np.ndarray:
        """Where map ``i`` is drawn relative to its place (m, display only): along x, side by side."""
        side_by_side = self.viewer.gui_side_by_side.value and self.pair() is None
        return np.array([self.side_by_side_step * i if side_by_side else 0.0, 0.0, 0.0])

    def truth_labels(self, i: int) -> np.ndarray | None:
        """The ground truth's label of every voxel of map ``i`` (-1: none), None without a truth."""
        if self.truth_path is None:
            return None
        layer = self.viewer.layers[i]
        key = (i, id(layer))
        if key not in self._truth:
            self._truth = {key: load_truth(self.truth_path, layer, self.viewer.frame)}
        return self._truth[key]

    def diff(self) -> MapDiff:
        """The comparison of the first and second maps chosen in the GUI (cached)."""
        first, second = self.pair()
        layers = self.viewer.layers
        key = (first, second, id(layers[first]), id(layers[second]))
        if key not in self._diffs:
            self._diffs = {key: compare_maps(layers[first], layers[second], self.truth_labels(first))}
        return self._diffs[key]

    def check(self) -> bool:
        """Whether the maps chosen can be shown: two maps that cannot be compared voxel by voxel turn the
        comparison off (which refreshes the view) and say why."""
        try:
            if self.pair() is not None:
                self.diff()
        except ValueError as exc:
            self.viewer.gui_diff_status.content = f"**Cannot compare:** {exc}"
            self.viewer.gui_diff.value = "off"
            return False
        return True

    def rows_compared(self, i: int) -> np.ndarray | None:
        """[V] bool over map ``i``'s voxels: those the comparison shows (None: map ``i`` is not compared)."""
        pair = self.pair()
        if pair is None or i != pair[0]:
            return None
        diff = self.diff()
        compared = np.zeros(len(self.viewer.layers[i].state), bool)
        compared[diff.a_rows[diff.differ] if self.viewer.gui_diff.value == "labels differ" else diff.a_rows] = True
        return compared

    def colors(self, i: int, rows: np.ndarray) -> tuple[np.ndarray, tuple[float, float] | None]:
        """(colors, the color bar's range) of the compared map ``i``'s voxels ``rows``: by which map the truth
        agrees with, or by the variance difference (a range symmetric about 0)."""
        diff = self.diff()
        where = np.full(len(self.viewer.layers[i].state), -1, np.int64)
        where[diff.a_rows] = np.arange(len(diff.a_rows))
        at = where[rows]
        if self.viewer.gui_diff.value == "labels differ":
            table = np.array(list(DIFF_COLORS.values()), np.uint8)
            return table[np.clip(diff.category()[at], 0, len(table) - 1)], None
        values = diff.variance_difference[at]
        limit = float(np.abs(values).max()) if len(values) else 0.0
        limit = limit if limit > 0 else 1.0
        return diverging(values, limit), (-limit, limit)

    def legend_image(self, color_range: tuple[float, float] | None) -> np.ndarray:
        """The comparison's legend: the categories' swatches, or the variance difference's color bar."""
        if self.viewer.gui_diff.value == "labels differ":
            return swatch_image(list(DIFF_COLORS.items()))
        lo, hi = color_range or (-1.0, 1.0)
        return color_bar_image(lo, hi, "variance: first - second map", DIVERGING)

    def show_status(self, color_range: tuple[float, float] | None) -> None:
        """The *Compare maps* folder's counts for the voxels shown."""
        pair = self.pair()
        if pair is None:
            return
        viewer = self.viewer
        variance = viewer.gui_diff.value == "variance difference"
        # the voxels the filters leave (not those below the evidence threshold, whose labels no point decided),
        # of which "labels differ" draws those that differ
        text = self.diff().describe(viewer.voxels.visible_mask(pair[0], compared=False)[self.diff().a_rows])
        if variance and color_range:
            text += (f"\n\ncolor: variance of the first minus the second, ±{color_range[1]:.3g} "
                     "(blue: the first map is surer, red: the second)")
        viewer.gui_diff_status.content = text

    def describe_voxel(self, i: int, row: int) -> str | None:
        """A line on the second map and the truth at a voxel of the compared map (None elsewhere)."""
        pair = self.pair()
        if pair is None or i != pair[0]:
            return None
        diff = self.diff()
        at = np.flatnonzero(diff.a_rows == row)
        if not len(at):
            return None
        k = int(at[0])
        classes = self.viewer.layers[i].classes
        truth = diff.truth[k]
        return (f"second map ({diff.b_name}): **{classes[diff.b_label[k]]}**, variance "
                f"{self.viewer.layers[pair[1]].variance[diff.b_rows[k]]:.3g}; truth: " + (classes[truth] if truth >= 0 else "none here"))

"""One map as the viewer holds it (``MapLayer``): what is drawn or reported of a map file, a map in memory
or a store's overview, in float64 world coordinates of its frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...core.map_file import lattice_index, read_map_file
from ...core.mapper import reader_mapper
from ...frames import WorldFrame
from ...terrain.known import evidence_sums
from ...voxel_keys import voxel_index_of

STATE_NAMES = ("UNKNOWN", "FREE", "OCCUPIED")


def held_classes(label: np.ndarray, state: np.ndarray) -> np.ndarray:
    """Class indices that some OCCUPIED voxel carries: the classes a map holds, and the only ones its class
    toggles offer (a FREE voxel's label is the free-space evidence's, "void", which no object has)."""
    return np.unique(label[state == STATE_NAMES.index("OCCUPIED")]).astype(np.int64)


def frame_of(meta: dict, where) -> WorldFrame | None:
    """The world frame a map file's meta records (None: written before maps recorded their frame)."""
    frame = (meta or {}).get("frame")
    return frame if isinstance(frame, WorldFrame) else WorldFrame.from_dict(frame, f"{where}: meta.frame")


def frame_label(frame: WorldFrame | None) -> str:
    """"map (EPSG:32617)", "map", or "not recorded": the frame as the GUI names it."""
    if frame is None:
        return "not recorded"
    return frame.name + (f" ({frame.crs})" if frame.crs else "")


@dataclass
class MapLayer:
    """One map file, as the viewer needs it: float64 centers in world coordinates of ``frame`` (metres)."""

    name: str
    path: Path
    classes: list[str]
    resolution: float
    grid_offset: float
    centers: np.ndarray
    voxel_index: np.ndarray
    alpha: np.ndarray
    label: np.ndarray
    state: np.ndarray
    variance: np.ndarray
    hits: np.ndarray
    mean_uncertainty: np.ndarray
    evidence_sum: np.ndarray  # [V] float64 evidence summed over classes: what terrain.known compares
    method: str
    frame: WorldFrame | None = None
    origin_index: np.ndarray = field(default_factory=lambda: np.zeros(3, np.int64))  # the map origin's voxel index
    # a store overview's rows stand for several voxels each (its tiles are decimated): how many; None: one each
    weight: np.ndarray | None = None
    # class indices that label at least one OCCUPIED voxel (held_classes); None: from the voxels held
    present: np.ndarray | None = None

    def present_labels(self) -> np.ndarray:
        """Class indices that some OCCUPIED voxel carries (the classes the map holds)."""
        if self.present is not None:
            return self.present
        return held_classes(self.label, self.state)

    @classmethod
    def from_file(cls, path) -> "MapLayer":
        """A map file as a layer (read and validated by map_file.read_map_file), read out as ``from_voxels``."""
        contents = read_map_file(path)
        return cls.from_voxels(Path(path).stem, Path(path), reader_mapper(contents), contents.voxels())

    @classmethod
    def from_voxels(cls, name: str, path, reader, voxels, summary=None) -> "MapLayer":
        """A layer of ``voxels`` (VoxelArrays, global indices in key order) read out with ``reader``'s (a
        Mapper's) parameters, classes, origin and frame; ``summary``: their read-out when at hand. The
        layer holds what is drawn or reported, not the sums (evidence, weights) it was read out of."""
        summary = summary if summary is not None else reader.summarize(voxels.evidence, voxels.touched)
        label, state, variance = summary.label.astype(np.int32, copy=False), summary.state.astype(np.int8, copy=False), summary.variance
        del summary  # its class probabilities [V, K] are not drawn: gone before the concentrations are made
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_unc = np.where(voxels.weight_sum > 0, voxels.weighted_uncertainty_sum / voxels.weight_sum, np.nan)
        resolution = reader.config.resolution_m
        return cls(name, Path(path), list(reader.class_names), resolution, reader.grid_offset_m, reader.voxel_centers(voxels.index),
                   np.asarray(voxels.index, np.int64), reader.concentrations(voxels.evidence), label, state, variance, voxels.hits,
                   mean_unc, evidence_sums(voxels.evidence), reader.config.method, reader.frame, lattice_index(reader.origin, resolution))

    @classmethod
    def from_arrays(cls, name: str, path: Path, arrays: dict, meta: dict) -> "MapLayer":
        """A layer from a map file's arrays and meta (map_file.file_arrays gives them for maps that are not files);
        ``evidence_sum`` [V] may stand for ``evidence`` [V, K] (a store's overview keeps only the sums)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_unc = np.where(arrays["weight_sum"] > 0, arrays["weighted_uncertainty_sum"] / arrays["weight_sum"], np.nan)
        return cls(name, path, list(meta["classes"]), float(arrays["resolution"]), float(meta.get("grid_offset_m", 0.0)),
                   np.asarray(arrays["centers"], np.float64), arrays["voxel_index"].astype(np.int64), arrays["alpha"],
                   arrays["label"], arrays["state"], arrays["variance"], arrays["hits"], mean_unc,
                   arrays["evidence_sum"] if "evidence_sum" in arrays else evidence_sums(arrays["evidence"]), meta["method"],
                   frame_of(meta, path), lattice_index(np.asarray(arrays["origin"], np.float64), float(arrays["resolution"])))

    @classmethod
    def from_mapper(cls, name: str, path, mapper, voxels=None) -> "MapLayer":
        """A map in memory, as its map file would show it: ``mapper``'s voxels, or ``voxels`` (a copy of
        them, global indices) read out with ``mapper``'s parameters, origin and frame."""
        arrays, summary = mapper.voxels() if voxels is None else (voxels, None)
        return cls.from_voxels(name, path, mapper, arrays, summary)

    def voxel_at(self, points_world: np.ndarray) -> np.ndarray:
        """Row of the voxel containing each point, -1 where none is stored (map files are sorted by key)."""
        if len(self.voxel_index) == 0:
            return np.full(len(points_world), -1)
        # Global indices can exceed the table's 21-bit key range (far maps), so pack relative to the
        # map's own bounding box; the order stays x, then y, then z, as the file is sorted.
        index = voxel_index_of(points_world, self.resolution, self.grid_offset, self.origin_index)
        lo, hi = self.voxel_index.min(axis=0), self.voxel_index.max(axis=0)
        inside = np.all((index >= lo) & (index <= hi), axis=1)
        span = hi - lo + 1

        def pack(rows):
            rows = np.asarray(rows, np.int64) - lo
            return (rows[:, 0] * span[1] + rows[:, 1]) * span[2] + rows[:, 2]

        stored = pack(self.voxel_index)
        keys = pack(np.where(inside[:, None], index, lo).astype(np.int64))
        rows = np.clip(np.searchsorted(stored, keys), 0, len(stored) - 1)
        return np.where(inside & (stored[rows] == keys), rows, -1)

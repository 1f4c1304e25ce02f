"""Scan sources for the mapper, listed in one registry by ``dataset.kind``.

Every dataset yields ``Scan`` records one at a time, so a sequence of any length streams through
``Mapper.integrate`` without being held in memory.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Protocol

import numpy as np

from ..config import ConfigError, DatasetConfig, PayloadType
from ..frames import WorldFrame
from .pcd import ExtraColumnsWarning, read_pcd
from .world_frame import place_in_world


@dataclass
class Scan:
    """One insertion of a dataset: its ``name`` (for error messages), points [N, 3] (m, the dataset's world
    frame), the payload ([N] labels or [N, K] alpha / probabilities, as ``payload_type`` says) and the
    sensor origin [3] (m, same frame)."""

    name: str
    points: np.ndarray  # [N, 3] world frame, m
    payload: np.ndarray  # [N] labels or [N, K] alpha / probabilities, as payload_type says
    payload_type: PayloadType
    sensor_origin: np.ndarray  # [3] world frame, m


class Dataset(Protocol):
    """``len`` insertions (scans, or bins of frames); ``scans(start, stop)`` yields insertions
    start..stop-1 exactly as iterating the whole dataset yields them (same world frame), so that
    batch workers map chunks of one sequence; datasets pickle, for those workers. ``frame``: the
    world frame the scans' points are in (``data/world_frame.py`` decides it)."""

    num_classes: int
    class_names: tuple[str, ...]
    frame: WorldFrame

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Scan]: ...

    def scans(self, start: int, stop: int) -> Iterator[Scan]:
        """Insertions ``start`` .. ``stop - 1``, exactly as iterating the whole dataset yields them."""

    def frames_in(self, start: int, stop: int) -> int:
        """How many sensor frames insertions ``start`` .. ``stop - 1`` hold (one per insertion, or a bin's
        frames)."""


class _Insertions:
    """What every dataset shares: iteration is scans(0, len); one frame per insertion."""

    def __iter__(self) -> Iterator[Scan]:
        return self.scans(0, len(self))

    def frames_in(self, start: int, stop: int) -> int:
        return max(0, min(stop, len(self)) - start)


class PcdSequence(_Insertions):
    """Numbered PCD files (``pattern`` with ``{index}``), labels in the ``label`` field, the sensor
    origin from VIEWPOINT (the S-BKI datasets' layout)."""

    def __init__(self, config: DatasetConfig):
        if config.payload is not PayloadType.LABEL:
            raise ConfigError(f"dataset.payload: a pcd_sequence carries integer labels, got {config.payload.value!r}")
        if "{index}" not in config.pattern:
            raise ConfigError(f"dataset.pattern must contain '{{index}}', got {config.pattern!r}")
        self.root = config.resolve_path()
        self.files = [self.root / config.pattern.format(index=i) for i in range(config.first_index, config.last_index + 1)]
        missing = [str(f) for f in self.files if not f.exists()]
        if missing:
            raise ConfigError(f"dataset: {len(missing)} scan file(s) missing, first {missing[0]}")
        self.num_classes = config.num_classes
        self.class_names = config.class_names
        self.frame = place_in_world(config).frame
        self._extra_columns_reported = False

    def __len__(self) -> int:
        return len(self.files)

    def scans(self, start: int, stop: int) -> Iterator[Scan]:
        """The scans of files ``start`` .. ``stop - 1``: points and sensor origin as the files give them, the
        ``label`` field as payload. An extra undeclared column warns once per dataset."""
        for path in self.files[start:stop]:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                cloud = read_pcd(path)
            for w in caught:
                if issubclass(w.category, ExtraColumnsWarning):
                    # the S-BKI toy files all carry one undeclared column: say so once per dataset
                    if self._extra_columns_reported:
                        continue
                    self._extra_columns_reported = True
                    w.message = ExtraColumnsWarning(f"{self.root}: the scan files carry more columns than their headers "
                                                    f"declare (first {path.name}); the extra columns are ignored")
                warnings.warn(w.message, w.category, stacklevel=2)
            if "label" not in cloud.fields:
                raise ConfigError(f"{path}: no 'label' field; a pcd_sequence needs per-point labels")
            yield Scan(str(path), cloud.points, cloud.fields["label"].astype(np.int64), PayloadType.LABEL, cloud.sensor_origin)


class BenchNpz(_Insertions):
    """The shared benchmark workload (rellis_like_30scans.npz): per-scan points in millimetres and a
    two-class sparse evidence vector per point, expanded here to alpha [N, 9]."""

    def __init__(self, config: DatasetConfig):
        self.path = config.resolve_path()
        self._data = None
        self.offsets = self.data["scan_offsets"]
        self.num_classes = config.num_classes or 9
        self.class_names = config.class_names
        self.payload_type = config.payload
        self.frame = place_in_world(config).frame

    @property
    def data(self):
        """The workload's arrays (an open ``np.load``, read once); raises ConfigError when the file is not a
        readable benchmark npz."""
        if self._data is None:
            try:
                self._data = np.load(self.path, allow_pickle=False)
                self._data["scan_offsets"]
            except (OSError, ValueError, KeyError) as exc:
                raise ConfigError(f"{self.path}: not a readable benchmark npz ({exc})") from None
        return self._data

    def __getstate__(self):
        return self.__dict__ | {"_data": None}  # the open file stays behind; a worker opens its own

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def scan_points(self, i: int) -> np.ndarray:
        """Scan ``i``'s points [N, 3] (m, float64 from the file's millimetres rounded through float32, as the
        C++ reads them)."""
        a, b = self.offsets[i], self.offsets[i + 1]
        return (self.data["xyz_mm"][a:b] / 1000.0).astype(np.float32).astype(np.float64)

    def scan_alpha(self, i: int) -> np.ndarray:
        """Scan ``i``'s alpha [N, K] float32: 1 plus the evidence of each point's top two classes."""
        a, b = self.offsets[i], self.offsets[i + 1]
        alpha = np.ones((b - a, self.num_classes), dtype=np.float32)
        rows = np.arange(b - a)
        alpha[rows, self.data["alpha_top_class"][a:b]] += self.data["alpha_top_evidence"][a:b].astype(np.float32)
        alpha[rows, self.data["alpha_second_class"][a:b]] += self.data["alpha_second_evidence"][a:b].astype(np.float32)
        return alpha

    def scans(self, start: int, stop: int) -> Iterator[Scan]:
        """Scans ``start`` .. ``stop - 1`` with their alpha (or the workload's ``label`` array when the
        payload is labels) and sensor origins."""
        for i in range(start, min(stop, len(self))):
            a, b = self.offsets[i], self.offsets[i + 1]
            origin = self.data["origins_mm"][i] / 1000.0
            if self.payload_type is PayloadType.LABEL:
                payload = self.data["label"][a:b].astype(np.int64)
            else:
                payload = self.scan_alpha(i)
            yield Scan(f"{self.path} scan {i}", self.scan_points(i), payload, self.payload_type, origin)


class LabelledSequence(_Insertions):
    """A sequence mapped from its per-point labels: a RELLIS-3D-layout folder (``rellis3d``; real, or
    ``evsemmap synth`` output), a SemanticKITTI sequence (``semantickitti``) or a robot log whose clouds
    carry a label field (``bag``). RELLIS ids are remapped to the 9 v3 classes, SemanticKITTI ids to its
    19 learning classes. Points are placed in the world frame with their float64 poses (``frame``,
    ``data/world_frame.py``). Zero returns are dropped."""

    def __init__(self, config: DatasetConfig):
        if config.payload is not PayloadType.LABEL:
            raise ConfigError(f"dataset.payload: a {config.kind} sequence is mapped from its per-point labels, got {config.payload.value!r}")
        if config.kind == "bag":
            from .logs import LogSequence

            self.sequence = LogSequence(config.resolve_logs(), config.bag)
            ontology = config.bag.label_ontology
        else:
            from .sequences import Rellis3DSequence, SemanticKittiSequence

            root = config.resolve_path()
            self.sequence = Rellis3DSequence(root) if config.kind == "rellis3d" else SemanticKittiSequence(root)
            ontology = "rellis3d" if config.kind == "rellis3d" else "semantickitti"
        self.table, self.class_names = label_table(ontology, config.num_classes)
        self.frames = [f for f in self.sequence.frames if f.point_labels is not None]
        if not self.frames:
            if config.kind == "bag" and self.sequence.frames:
                self.sequence.read_point_labels(self.sequence.frames[0])  # raises, naming the field and the cloud's fields
            raise ConfigError(f"{self.sequence.root}: no scan has a per-point label file")
        self.num_classes = config.num_classes or len(self.class_names)
        self.class_names = config.class_names or self.class_names
        self.world = place_in_world(config, self.sequence)
        self.frame = self.world.frame

    def __len__(self) -> int:
        return len(self.frames)

    def scans(self, start: int, stop: int) -> Iterator[Scan]:
        """Frames ``start`` .. ``stop - 1`` as scans: points placed in the world frame with their float64
        poses, zero returns dropped, labels remapped to the class set."""
        from .sequences import remap_point_labels

        for frame in self.frames[start:stop]:
            scan = self.sequence.read_scan(frame)
            labels = remap_point_labels(self.sequence.read_point_labels(frame), self.table, frame.point_labels)
            yield labelled_scan(str(frame.scan), scan, labels, self.world.to_world(self.sequence.pose(frame)))


def labelled_scan(name: str, scan: np.ndarray, labels: np.ndarray, to_world: np.ndarray) -> Scan:
    """A LiDAR scan [N, 4] (sensor frame) with its class labels [N], placed in the world frame with the float64
    transform ``to_world`` [4, 4]; zero returns dropped (every labelled source places its scans here)."""
    returned = np.any(scan[:, :3] != 0, axis=1)
    points = scan[returned, :3].astype(np.float64) @ to_world[:3, :3].T + to_world[:3, 3]
    return Scan(name, points, labels[returned], PayloadType.LABEL, to_world[:3, 3].copy())


def label_table(ontology: str, num_classes: int = 0) -> tuple[np.ndarray, tuple[str, ...]]:
    """Raw per-point label id -> class id, and the class names, for an ontology: rellis3d (to the 9
    v3 classes), semantickitti (to its 19 learning classes) or none (ids are already classes)."""
    if ontology == "rellis3d":
        from ..classes import class_set, original_to_v3_table

        return original_to_v3_table().astype(np.int64), class_set("remap_v3").names
    if ontology == "semantickitti":
        from .sequences import semantickitti_learning_map

        return semantickitti_learning_map(), ("unlabeled",) + tuple(f"class_{i}" for i in range(1, 20))
    if num_classes < 1:
        raise ConfigError("dataset.num_classes: labels that are class ids already (label_ontology none) need the number of classes")
    return np.arange(num_classes, dtype=np.int64), tuple(f"class_{i}" for i in range(num_classes))


DATASETS = {"pcd_sequence": PcdSequence, "bench_npz": BenchNpz, "rellis3d": LabelledSequence, "semantickitti": LabelledSequence,
            "bag": LabelledSequence}


def open_dataset(config: DatasetConfig) -> Dataset:
    """The dataset a config's ``dataset`` section describes (its ``kind`` picks the reader); raises
    ConfigError for an unknown kind or data that is missing or inconsistent."""
    if config.kind not in DATASETS:
        raise ConfigError(f"dataset.kind {config.kind!r} is unknown; known: {sorted(DATASETS)}")
    return DATASETS[config.kind](config)


def open_sequence(sources, *, frame: str | None = None, crs: str | None = None) -> "Rellis3DSequence | LogSequence":
    """A sequence with cameras (for projection, inference and experiments) from what a user names: a
    RELLIS-3D-layout folder, or robot logs with the config files or presets that say their topics.
    Its ``world`` (a ``Placement``) says the world frame its points are mapped in (``frame`` and
    ``crs`` as the --frame and --crs flags)."""
    from ..config import load_config
    from .sequences import Rellis3DSequence

    sources = [str(s) for s in ([sources] if isinstance(sources, (str, Path)) else sources)]
    run = load_config(sources, frame=frame, crs=crs)
    dataset = run.dataset
    if dataset is None or dataset.kind not in ("rellis3d", "bag"):
        what = "no dataset" if dataset is None else f"a {dataset.kind!r} dataset"
        raise ConfigError(f"{' '.join(sources)}: {what}; a sequence with a camera is a RELLIS-3D-layout folder or robot logs (kind: bag)")
    if dataset.kind == "bag":
        from .logs import LogSequence

        sequence = LogSequence(dataset.resolve_logs(), dataset.bag)
    else:
        sequence = Rellis3DSequence(dataset.resolve_path())
    sequence.world = place_in_world(dataset, sequence)
    return sequence

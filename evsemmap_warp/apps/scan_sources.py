"""Where a map's payload comes from: per-point labels (the datasets of ``data/datasets.py``), or the
camera, labelled by a segmentation checkpoint run on the fly or by alpha files ``evsemmap infer``
wrote, projected onto the scans and grouped into bins (docs/algorithm.md §2).

Every source has ``len`` insertions and ``scans(start, stop)``, so ``evsemmap map`` iterates it whole
and ``evsemmap batch`` maps chunks of it in worker processes (sources pickle; a checkpoint's network
is loaded in each worker, once). Every source also has ``num_classes``, ``class_names`` and the world
``frame`` its scans are in, from which ``Mapper.for_dataset`` makes its empty map."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ..config import ConfigError, PayloadType, RunConfig
from ..core.mapper import Mapper
from ..frames import WorldFrame
from ..data.datasets import Scan, open_dataset, open_sequence
from ..geometry.projection import ProjectionConfig, bin_frames, project_frames


_NETWORKS: dict = {}  # checkpoint (path, mtime) -> loaded network, per process


class _CameraScans:
    """Frames with a camera image, their values projected onto their scans, in bins of ``bin_frames``."""

    payload_type = PayloadType.ALPHA

    def __init__(self, run: RunConfig, bin_frames_: int | None):
        dataset = run.dataset
        self.sequence = open_sequence(list(run.sources), frame=dataset.frame or None, crs=dataset.crs or None)
        self.frame = self.sequence.world.frame
        self.frames = [f for f in self.sequence.frames if f.image is not None]
        if not self.frames:
            raise ConfigError(f"{' '.join(run.sources)}: no scan has a camera image to label it from")
        self.bin_frames = bin_frames_ or run.bin_frames

    def __len__(self) -> int:
        return -(-len(self.frames) // self.bin_frames)

    def __iter__(self) -> Iterator[Scan]:
        return self.scans(0, len(self))

    def frames_in(self, start: int, stop: int) -> int:
        return len(self.frames[start * self.bin_frames: stop * self.bin_frames])

    def insertion_frames(self, k: int) -> list:
        """The frames binned into insertion ``k``."""
        return self.frames[k * self.bin_frames: (k + 1) * self.bin_frames]

    def frame_values(self, frame) -> np.ndarray:
        """[K, H, W] what ``scans`` projects for one frame: the checkpoint's alpha (or probabilities) or the alpha file's."""
        return self._values([frame])(frame)

    def _values(self, frames):
        """values_for_frame over ``frames``, asked in that order."""
        raise NotImplementedError

    def scans(self, start: int, stop: int) -> Iterator[Scan]:
        frames = self.frames[start * self.bin_frames: stop * self.bin_frames]
        projected = project_frames(self.sequence, frames, self._values(frames), ProjectionConfig(), self.sequence.world)
        for b in bin_frames(projected, self.bin_frames):
            yield Scan(f"frames {b.frames[0]}..{b.frames[-1]}", b.points, b.values, self.payload_type, b.sensor_origin)


class CheckpointScans(_CameraScans):
    """Scans labelled by a segmentation checkpoint: batched inference on each frame's image."""

    def __init__(self, run: RunConfig, checkpoint, bin_frames_: int | None, batch_size: int = 4):
        from ..segmentation.train import load_checkpoint

        super().__init__(run, bin_frames_)
        self.checkpoint, self.batch_size = Path(checkpoint), batch_size
        model, train_config, meta, _ = load_checkpoint(self.checkpoint)
        self._network = (model, train_config, meta)
        self.class_names = tuple(meta["classes"])
        self.num_classes = train_config.model.num_classes
        self.payload_type = PayloadType.ALPHA if train_config.head == "evidential" else PayloadType.PROB

    def __getstate__(self):
        return self.__dict__ | {"_network": None}  # a worker loads the checkpoint itself

    def _values(self, frames):
        from ..segmentation.train import infer_alpha, load_checkpoint

        if self._network is None:
            key = (str(self.checkpoint.resolve()), self.checkpoint.stat().st_mtime_ns)
            if key not in _NETWORKS:  # once per worker process, however many tasks it runs
                model, train_config, meta, _ = load_checkpoint(self.checkpoint)
                _NETWORKS.clear()
                _NETWORKS[key] = (model, train_config, meta)
            self._network = _NETWORKS[key]
        model, train_config, meta = self._network
        outputs = infer_alpha(model, train_config, meta, (self.sequence.read_image(f) for f in frames), batch_size=self.batch_size)
        return lambda frame: next(outputs)[0].astype(np.float32)


class AlphaFileScans(_CameraScans):
    """Scans labelled by the alpha files of ``evsemmap infer`` (``<image name>.npy``, or
    ``NNNNNN.npy`` by frame number as the experiments cache them)."""

    def __init__(self, run: RunConfig, folder, bin_frames_: int | None):
        super().__init__(run, bin_frames_)
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ConfigError(f"--alpha-dir {self.folder}: no such folder")
        self.frames = [f for f in self.frames if self._path(f) is not None]
        if not self.frames:
            raise ConfigError(f"{self.folder}: no alpha file for any frame (expected <image name>.npy or NNNNNN.npy)")
        first = self._load(self.frames[0])
        from ..classes import class_set

        self.num_classes = first.shape[0]
        names = class_set().names
        self.class_names = names if len(names) == self.num_classes else tuple(f"class_{i}" for i in range(self.num_classes))

    def _path(self, frame) -> Path | None:
        stem = getattr(frame.image, "stem", None)
        for name in ([f"{stem}.npy"] if stem else []) + [f"{frame.index:06d}.npy"]:
            if (self.folder / name).is_file():
                return self.folder / name
        return None

    def _load(self, frame) -> np.ndarray:
        path = self._path(frame)
        try:
            alpha = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{path}: not a readable alpha file ({exc})") from None
        if alpha.dtype.kind not in "biuf" or alpha.ndim != 3 or not np.isfinite(alpha).all():
            raise ConfigError(f"{path}: alpha must be a finite [K, H, W] array, got shape {list(alpha.shape)}")
        if hasattr(self, "num_classes") and alpha.shape[0] != self.num_classes:
            raise ConfigError(f"{path}: {alpha.shape[0]} classes, the first alpha file has {self.num_classes}")
        return alpha.astype(np.float32)

    def _values(self, frames):
        return self._load


def open_scan_source(run: RunConfig, *, checkpoint=None, alpha_dir=None, bin_frames: int | None = None, batch_size: int = 4):
    """The scans of a run: per-point labels, or the camera labelled by a checkpoint or alpha files."""
    if checkpoint is not None and alpha_dir is not None:
        raise ConfigError("--checkpoint and --alpha-dir both label the scans from the camera: give one of them")
    if checkpoint is not None:
        return CheckpointScans(run, checkpoint, bin_frames, batch_size)
    if alpha_dir is not None:
        return AlphaFileScans(run, alpha_dir, bin_frames)
    if bin_frames is not None:
        raise ConfigError("--bin-frames applies to camera-labelled scans (--checkpoint or --alpha-dir)")
    return open_dataset(run.dataset)


@dataclass
class ScanList:
    """Scans already in memory (an experiment's projected bins) as a source: same interface."""

    items: list[Scan]
    num_classes: int
    class_names: tuple[str, ...]
    frame: WorldFrame

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self) -> Iterator[Scan]:
        return iter(self.items)

    def scans(self, start: int, stop: int) -> Iterator[Scan]:
        """Scans ``start`` .. ``stop - 1`` of the list."""
        return iter(self.items[start:stop])


def map_scans(mapper: Mapper, scans, progress=None) -> list:
    """Integrate ``scans`` in order into ``mapper`` (the next ones read and prepared meanwhile; an
    error names its scan); returns the per-scan IntegrationStats."""
    return mapper.integrate_many(scans, progress=progress)

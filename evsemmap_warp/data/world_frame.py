"""Which world frame a source's scans are mapped in: the one rule, for every source and command
(docs/algorithm.md §6.6).

- a robot log: its fixed frame (``dataset.bag.fixed_frame``; default the root of the LiDAR's TF tree,
  with ``pose_source: odometry`` the odometry's header frame);
- a sequence folder: the frame its ``poses.txt`` is written in, poses used as given. The frame's name
  (and CRS) come from ``dataset.frame`` / ``dataset.crs``, else from the folder's ``frame.yaml``
  (``name: map``, ``crs: EPSG:32617``; ``evsemmap synth`` writes one), else ``poses:<folder name>``;
- point files (PCD sequences, the benchmark npz): their points' own frame, named by ``dataset.frame``
  or ``points:<folder or file name>``.

``dataset.frame: first-scan`` keeps the paper's convention instead: coordinates relative to the first
scan's LiDAR pose, a frame of that source alone (``first-scan of <source>``), never georeferenced.

A frame of one run (``odom`` by name, or one the log's odometry or TF marks as drifting, see
``LogSequence.is_run_frame``) records its run (``frames.WorldFrame.run``): a log's from its first cloud
(``LogSequence.run_id``), a folder's from its ``frame.yaml`` (``run:``; ``evsemmap synth`` writes one),
else unknown (None), which merge and view refuse to combine unless told ``--same-frame``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import ConfigError, DatasetConfig
from ..frames import FIRST_SCAN, WorldFrame
from ..geometry.camera import relative_pose
from .sequences import read_frame_file


@dataclass(frozen=True)
class Placement:
    """Where a source's scans go: the world frame, and for ``first-scan`` the pose that becomes the
    identity (None: poses are used as given)."""

    frame: WorldFrame
    reference: np.ndarray | None = None

    def to_world(self, pose: np.ndarray) -> np.ndarray:
        """A LiDAR pose of the source as the 4x4 transform of its points into the world frame."""
        return pose if self.reference is None else relative_pose(self.reference, pose)


def place_in_world(config: DatasetConfig, sequence=None) -> Placement:
    """The world frame of ``config``'s data (``sequence``: the opened folder or log, for its poses,
    its frame file and a log's fixed frame)."""
    crs = config.crs or None
    run = None
    if config.kind == "bag":
        sequence.check_pose_chain()
        name = sequence.fixed_frame
        source = sequence.root.name
        run = sequence.run_id if sequence.is_run_frame(name) else None
    elif config.kind in ("rellis3d", "semantickitti"):
        own = read_frame_file(sequence.root)
        name = config.frame if config.frame not in ("", FIRST_SCAN) else (own.name if own else f"poses:{sequence.root.name}")
        crs = crs or (own.crs if own else None)
        source = sequence.root.name
        if own is not None and own.name == name:
            run = own.run
    else:  # point files: their own frame
        source = config.resolve_path().name
        name = config.frame if config.frame not in ("", FIRST_SCAN) else f"points:{source}"
    if config.frame == FIRST_SCAN:
        if config.crs:
            raise ConfigError(f"dataset.crs = {config.crs!r} with dataset.frame: first-scan: coordinates relative to the first scan "
                              f"are not georeferenced; drop one of them")
        reference = None
        if sequence is not None and len(sequence.frames) and config.kind not in ("pcd_sequence", "bench_npz"):
            reference = sequence.pose(sequence.frames[0])
        return Placement(WorldFrame(f"first-scan of {source}"), reference)
    return Placement(WorldFrame(name, crs, run))

"""World frames: the named coordinate frame a map lives in, and its optional georeference.

A map is expressed in the frame its data lives in (docs/algorithm.md §6.6): a robot log's fixed TF
frame, the frame a sequence folder's ``poses.txt`` is written in, a point file's own frame. Map files
and stores record that frame, so that anything combining maps (merge, multi-input batch, the viewer's
side-by-side) can check that the frames agree instead of overlaying coordinates of different frames.

A frame that is not world-fixed by convention belongs to one run of one robot: REP 105's ``odom``
drifts with its run, so two drives' ``odom`` frames are two frames that share a name. Such a frame
records its ``run`` (an id derived from the data, so the same input gives the same map bytes), and
maps of two runs, or of a known run and an unknown one (written before maps recorded runs), are
combined only when the user says they share the frame (``same_frame``, ``--same-frame``). Two maps
both of unknown run are taken as one frame, as before runs were recorded.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, replace


# ``frame: first-scan``: the paper's convention, coordinates relative to the first scan's LiDAR pose.
FIRST_SCAN = "first-scan"
_EPSG = re.compile(r"^(?:EPSG|epsg):(\d{4,6})$")
# REP 105: odom is continuous but drifts, a frame of one run; map and earth are world-fixed
RUN_FRAME_NAMES = ("odom",)


def is_run_frame_name(name: str) -> bool:
    """Whether a frame's name marks it as one run's by convention (``odom``, ``robot1/odom``)."""
    return name.rsplit("/", 1)[-1] in RUN_FRAME_NAMES


def run_id(*parts: bytes | str) -> str:
    """A run's id from what identifies its data (a log's first cloud, a drive's poses): the same
    data gives the same id, so the same command on the same input writes the same map bytes."""
    digest = hashlib.sha256()
    for part in parts:
        data = part.encode() if isinstance(part, str) else bytes(part)
        digest.update(len(data).to_bytes(8, "little") + data)
    return digest.hexdigest()[:16]


class FrameError(ValueError):
    """A frame or CRS that is malformed, or two frames that must agree and do not; names both."""


def check_crs(value, where: str = "crs") -> str | None:
    """An EPSG code as ``EPSG:NNNN`` (from "EPSG:32617", "epsg:32617" or 32617); None for none."""
    if value is None or value == "":
        return None
    if isinstance(value, int) and not isinstance(value, bool) and 1024 <= value < 10**6:
        return f"EPSG:{value}"
    match = _EPSG.match(value.strip()) if isinstance(value, str) else None
    # EPSG codes start at 1024: EPSG:0000 would be recorded as EPSG:0, a code of no CRS
    if match is None or int(match.group(1)) < 1024:
        raise FrameError(f"{where} = {value!r} is not an EPSG code (write it as EPSG:NNNN with NNNN from 1024, e.g. EPSG:32617 "
                         f"for UTM zone 17N)")
    return f"EPSG:{int(match.group(1))}"


@dataclass(frozen=True)
class WorldFrame:
    """A map's world frame: its ``name`` (a TF frame id such as ``map``, or a name given to a folder's
    poses), ``crs``, an EPSG code when the coordinates are georeferenced (e.g. a UTM zone, metres), and
    ``run``, the id of the run a frame that is not world-fixed belongs to (None: world-fixed, or a run
    frame whose run is unknown; ``needs_run`` tells them apart)."""

    name: str
    crs: str | None = None
    run: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise FrameError(f"world frame name {self.name!r} must be a non-empty string")
        if self.run is not None and (not isinstance(self.run, str) or not self.run.strip()):
            raise FrameError(f"world frame {self.name!r}: run {self.run!r} must be a non-empty string")
        object.__setattr__(self, "crs", check_crs(self.crs, f"world frame {self.name!r}: crs"))

    @property
    def needs_run(self) -> bool:
        """Whether the frame is one run's: it records a run, or its name marks it so (``odom``)."""
        return self.run is not None or is_run_frame_name(self.name)

    def as_dict(self) -> dict:
        """``{"name": ..., "crs": ...}`` and ``"run"`` when there is one, as map files and store
        indexes record it (a world-fixed frame's dict is what it was before runs were recorded)."""
        return {"name": self.name, "crs": self.crs} | ({"run": self.run} if self.run is not None else {})

    @classmethod
    def from_dict(cls, data, where: str) -> "WorldFrame | None":
        """The frame a file records (None: written before frames were recorded)."""
        if data is None:
            return None
        if not isinstance(data, dict) or set(data) - {"name", "crs", "run"} or not isinstance(data.get("name"), str):
            raise FrameError(f"{where}: frame must be a mapping with a 'name' string, an optional 'crs' and an optional 'run', got {data!r}")
        try:
            return cls(data["name"], data.get("crs"), data.get("run"))
        except FrameError as exc:
            raise FrameError(f"{where}: {exc}") from None

    def describe(self) -> str:
        """The frame in words for messages, e.g. ``frame 'map' (EPSG:32617)``, ``frame 'odom' of run 3f2a...``."""
        run = f" of run {self.run}" if self.run is not None else (" of an unknown run" if self.needs_run else "")
        return f"frame {self.name!r}" + (f" ({self.crs})" if self.crs else "") + run


def describe_frame(frame: WorldFrame | None) -> str:
    """``frame.describe()``, or for None a phrase naming both ways a map comes to have no frame: made
    without one (``Mapper(config, K)`` for points from elsewhere), or written before maps recorded it."""
    return "no recorded frame (made without one, or written before maps recorded their frame)" if frame is None else frame.describe()


def check_same_frame(what: str, first: tuple[str, WorldFrame | None], second: tuple[str, WorldFrame | None], *,
                     same_frame: bool = False) -> None:
    """Refuse to combine data of two frames (or of two CRSs), naming both: ``what`` is the action
    ("merge", "batch", "view side by side"), the pairs are (where, frame). A run frame (``odom``) of
    two runs, or of a known run and an unknown one, is two frames unless ``same_frame``: the user says
    they share it (a drive cut into two logs). Two of unknown run (both written before maps recorded
    runs) pass, as they did then: nothing tells them apart."""
    (where_a, frame_a), (where_b, frame_b) = first, second
    if frame_a == frame_b:
        return
    if frame_a is not None and frame_b is not None and replace(frame_a, run=None) == replace(frame_b, run=None):
        if same_frame:
            return
        raise FrameError(f"{what}: {where_a} is in {frame_a.describe()} but {where_b} in {frame_b.describe()}: {frame_a.name!r} is "
                         f"a frame of one run (REP 105: odometry drifts with its run), so two runs' {frame_a.name!r} frames share a "
                         f"name, not their coordinates; map both in a world-fixed frame (a localiser's map frame), or, if they "
                         f"are one run's frame (a drive cut into two logs), say so: batch --same-frame, merge --same-frame, view --same-frame")
    if frame_a != frame_b:
        raise FrameError(f"{what}: {where_a} is in {describe_frame(frame_a)} but {where_b} in {describe_frame(frame_b)}; "
                          f"maps of different frames cannot be combined (map both in one frame: dataset.frame / --frame "
                          f"names a folder's poses frame, dataset.bag.fixed_frame a log's"
                          + ("; in Python, Mapper.for_dataset(dataset, config) makes a dataset's map in its frame"
                             if None in (frame_a, frame_b) else "") + ")")

"""World frames: the named coordinate frame a map lives in, and its optional georeference.

A map is expressed in the frame its data lives in (docs/algorithm.md §6.6): a robot log's fixed TF
frame, the frame a sequence folder's ``poses.txt`` is written in, a point file's own frame. Map files
and stores record that frame, so that anything combining maps (merge, multi-input batch, the viewer's
side-by-side) can check that the frames agree instead of overlaying coordinates of different frames.
"""

from __future__ import annotations

import re
from dataclasses import dataclass


# ``frame: first-scan``: the paper's convention, coordinates relative to the first scan's LiDAR pose.
FIRST_SCAN = "first-scan"
_EPSG = re.compile(r"^(?:EPSG|epsg):(\d{4,6})$")


class FrameError(ValueError):
    """A frame or CRS that is malformed, or two frames that must agree and do not; names both."""


def check_crs(value, where: str = "crs") -> str | None:
    """An EPSG code as ``EPSG:NNNN`` (from "EPSG:32617", "epsg:32617" or 32617); None for none."""
    if value is None or value == "":
        return None
    if isinstance(value, int) and not isinstance(value, bool) and 1024 <= value < 10**6:
        return f"EPSG:{value}"
    match = _EPSG.match(value.strip()) if isinstance(value, str) else None
    if match is None:
        raise FrameError(f"{where} = {value!r} is not an EPSG code (write it as EPSG:NNNN, e.g. EPSG:32617 for UTM zone 17N)")
    return f"EPSG:{int(match.group(1))}"


@dataclass(frozen=True)
class WorldFrame:
    """A map's world frame: its ``name`` (a TF frame id such as ``map``, or a name given to a folder's
    poses) and ``crs``, an EPSG code when the coordinates are georeferenced (e.g. a UTM zone, metres)."""

    name: str
    crs: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise FrameError(f"world frame name {self.name!r} must be a non-empty string")
        object.__setattr__(self, "crs", check_crs(self.crs, f"world frame {self.name!r}: crs"))

    def as_dict(self) -> dict:
        """``{"name": ..., "crs": ...}``, as map files and store indexes record it."""
        return {"name": self.name, "crs": self.crs}

    @classmethod
    def from_dict(cls, data, where: str) -> "WorldFrame | None":
        """The frame a file records (None: written before frames were recorded)."""
        if data is None:
            return None
        if not isinstance(data, dict) or set(data) - {"name", "crs"} or not isinstance(data.get("name"), str):
            raise FrameError(f"{where}: frame must be a mapping with a 'name' string and an optional 'crs', got {data!r}")
        try:
            return cls(data["name"], data.get("crs"))
        except FrameError as exc:
            raise FrameError(f"{where}: {exc}") from None

    def describe(self) -> str:
        """The frame in words for messages, e.g. ``frame 'map' (EPSG:32617)``."""
        return f"frame {self.name!r}" + (f" ({self.crs})" if self.crs else "")


def describe_frame(frame: WorldFrame | None) -> str:
    """``frame.describe()``, or for None a phrase naming both ways a map comes to have no frame: made
    without one (``Mapper(config, K)`` for points from elsewhere), or written before maps recorded it."""
    return "no recorded frame (made without one, or written before maps recorded their frame)" if frame is None else frame.describe()


def check_same_frame(what: str, first: tuple[str, WorldFrame | None], second: tuple[str, WorldFrame | None]) -> None:
    """Refuse to combine data of two frames (or of two CRSs), naming both: ``what`` is the action
    ("merge", "batch", "view side by side"), the pairs are (where, frame)."""
    (where_a, frame_a), (where_b, frame_b) = first, second
    if frame_a != frame_b:
        raise FrameError(f"{what}: {where_a} is in {describe_frame(frame_a)} but {where_b} in {describe_frame(frame_b)}; "
                          f"maps of different frames cannot be combined (map both in one frame: dataset.frame / --frame "
                          f"names a folder's poses frame, dataset.bag.fixed_frame a log's"
                          + ("; in Python, Mapper.for_dataset(dataset, config) makes a dataset's map in its frame"
                             if None in (frame_a, frame_b) else "") + ")")

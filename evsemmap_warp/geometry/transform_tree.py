"""A tree of coordinate frames with timed transforms: what ROS calls TF, without ROS.

Each frame has one parent. An edge is static (one transform for all time, ``/tf_static`` or a
given extrinsic) or timed (``/tf`` or odometry samples); a timed edge is interpolated between the
two samples that bracket the asked time (linear translation, slerp rotation), and a time outside its
recorded range is refused: extrapolating a robot's motion would silently bend the map. A lookup at
exactly a sample's stamp returns that sample unchanged.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from .camera import quaternion_to_matrix, rigid


class TransformError(ValueError):
    """No transform between two frames at a time; the message names both frames and the time."""


def format_stamp(stamp_ns: int) -> str:
    """A stamp in nanoseconds as ``t = S.SSSSSS s``, for messages."""
    return f"t = {stamp_ns / 1e9:.6f} s"


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (x, y, z, w) along the shorter arc."""
    q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # q and -q are one rotation: take the shorter way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: lerp is exact to float64 rounding and avoids sin(0) / sin(0)
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    return (np.sin((1.0 - fraction) * theta) * q0 + np.sin(fraction * theta) * q1) / np.sin(theta)


@dataclass
class _TimedEdge:
    parent: str
    stamps: list[int] = field(default_factory=list)  # ns, kept sorted
    translations: list[np.ndarray] = field(default_factory=list)
    rotations: list[np.ndarray] = field(default_factory=list)  # unit quaternions (x, y, z, w)

    def add(self, stamp_ns: int, translation, quaternion) -> None:
        q = np.asarray(quaternion, np.float64)
        at = bisect.bisect_right(self.stamps, stamp_ns)
        if at and self.stamps[at - 1] == stamp_ns:  # a repeated stamp: the later message wins
            self.translations[at - 1], self.rotations[at - 1] = np.asarray(translation, np.float64), q / np.linalg.norm(q)
            return
        self.stamps.insert(at, stamp_ns)
        self.translations.insert(at, np.asarray(translation, np.float64))
        self.rotations.insert(at, q / np.linalg.norm(q))

    def trim(self, before_ns: int | None, after_ns: int | None) -> None:
        start = 0 if before_ns is None else max(bisect.bisect_right(self.stamps, before_ns) - 1, 0)
        stop = len(self.stamps) if after_ns is None else bisect.bisect_right(self.stamps, after_ns)
        for samples in (self.stamps, self.translations, self.rotations):
            del samples[stop:]
            del samples[:start]

    def at(self, stamp_ns: int, child: str) -> np.ndarray:
        at = bisect.bisect_right(self.stamps, stamp_ns) - 1
        if at < 0 or (stamp_ns > self.stamps[-1]):
            raise TransformError(f"no transform {self.parent} -> {child} at {format_stamp(stamp_ns)}: it is recorded from "
                                 f"{format_stamp(self.stamps[0])} to {format_stamp(self.stamps[-1])} ({len(self.stamps)} samples)")
        if self.stamps[at] == stamp_ns:
            return rigid(quaternion_to_matrix(self.rotations[at]), self.translations[at])
        t0, t1 = self.stamps[at], self.stamps[at + 1]
        fraction = (stamp_ns - t0) / (t1 - t0)
        translation = self.translations[at] + fraction * (self.translations[at + 1] - self.translations[at])
        return rigid(quaternion_to_matrix(slerp(self.rotations[at], self.rotations[at + 1], fraction)), translation)


def _check_parts(parent: str, child: str, translation, quaternion, stamp_ns: int | None = None) -> None:
    """A transform is a finite translation and a rotation: a zero or non-finite quaternion (an odometry
    not yet initialised) would make every pose through it NaN, or a singular matrix."""
    t, q = np.asarray(translation, np.float64), np.asarray(quaternion, np.float64)
    if not (np.isfinite(t).all() and np.isfinite(q).all() and np.linalg.norm(q) > 1e-9):
        when = "" if stamp_ns is None else f" at {format_stamp(stamp_ns)}"
        raise TransformError(f"the transform {parent!r} -> {child!r}{when} is no rigid transform (translation {t.tolist()}, "
                             f"quaternion {q.tolist()}: finite numbers and a non-zero quaternion needed)")


class TransformTree:
    """Frames and their transforms; ``lookup(target, source, t)`` is the 4x4 pose of ``source`` in
    ``target`` (it maps source coordinates into target coordinates)."""

    def __init__(self):
        self._static: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, 4x4)
        self._timed: dict[str, _TimedEdge] = {}  # child -> edge

    def add_static(self, parent: str, child: str, translation, quaternion) -> None:
        """Add the fixed transform of ``child`` in ``parent`` (translation [3] m, quaternion x y z w). Raises
        TransformError for a frame given two parents, a transform of a frame to itself, or a non-finite or
        zero quaternion."""
        self._check_parent(parent, child)
        _check_parts(parent, child, translation, quaternion)
        self._static[child] = (parent, rigid(quaternion_to_matrix(quaternion), translation))

    def add_timed(self, parent: str, child: str, stamp_ns: int, translation, quaternion) -> None:
        """Add one sample, at ``stamp_ns``, of the moving transform of ``child`` in ``parent`` (translation
        [3] m, quaternion x y z w); raises TransformError as ``add_static``."""
        self._check_parent(parent, child)
        _check_parts(parent, child, translation, quaternion, stamp_ns)
        self._timed.setdefault(child, _TimedEdge(parent)).add(int(stamp_ns), translation, quaternion)

    def trim(self, *, before_ns: int | None = None, after_ns: int | None = None) -> None:
        """Forget the timed samples stamped before ``before_ns`` (but the last one before it, so a lookup at
        ``before_ns`` or later still interpolates) and those after ``after_ns``; static transforms stay. A live
        source keeps its tree to the scans still to come this way, and forgets another timeline's samples
        when time jumped back."""
        for child in list(self._timed):
            edge = self._timed[child]
            edge.trim(before_ns, after_ns)
            if not edge.stamps:
                del self._timed[child]

    def _check_parent(self, parent: str, child: str) -> None:
        if parent == child:
            raise TransformError(f"a transform from frame {child!r} to itself")
        known = self.parent(child)
        if known is not None and known != parent:
            raise TransformError(f"frame {child!r} has two parents, {known!r} and {parent!r} (a TF tree gives each frame one)")

    def parent(self, frame: str) -> str | None:
        """The parent frame of ``frame``, or None for a root or an unknown frame."""
        if frame in self._static:
            return self._static[frame][0]
        if frame in self._timed:
            return self._timed[frame].parent
        return None

    @property
    def frames(self) -> set[str]:
        """Every frame the tree names."""
        children = set(self._static) | set(self._timed)
        return children | {self.parent(c) for c in children}

    def is_timed(self, frame: str) -> bool:
        """True when ``frame``'s transform to its parent moves (has timed samples)."""
        return frame in self._timed

    def time_range(self, frame: str) -> tuple[int, int] | None:
        """(first, last) stamp (ns) of ``frame``'s timed samples, or None for a fixed or unknown edge."""
        edge = self._timed.get(frame)
        return (edge.stamps[0], edge.stamps[-1]) if edge else None

    def path_to_root(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root; raises TransformError when the tree has a loop."""
        path = [frame]
        while (parent := self.parent(path[-1])) is not None:
            if parent in path:
                raise TransformError(f"the TF tree has a loop through {parent!r}")
            path.append(parent)
        return path

    def root(self, frame: str) -> str:
        """The root of ``frame``'s tree."""
        return self.path_to_root(frame)[-1]

    def chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The frames from source up to the common ancestor, and from target up to it."""
        up_source, up_target = self.path_to_root(source), self.path_to_root(target)
        common = next((f for f in up_source if f in up_target), None)
        if common is None:
            known = ", ".join(sorted(self.frames)) or "none"
            raise TransformError(f"frames {target!r} and {source!r} are not connected (the tree of {source!r} ends at "
                                 f"{up_source[-1]!r}, that of {target!r} at {up_target[-1]!r}; frames known: {known})")
        return up_source[: up_source.index(common) + 1], up_target[: up_target.index(common) + 1]

    def is_static_between(self, target: str, source: str) -> bool:
        """True when no transform on the chain from ``source`` to ``target`` moves; raises TransformError
        when they are not connected."""
        up_source, up_target = self.chain(target, source)
        return not any(self.is_timed(f) for f in up_source[:-1] + up_target[:-1])

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """The pose [4, 4] of ``source`` in ``target`` at ``stamp_ns`` (maps source coordinates to target
        coordinates): timed edges interpolated (linear translation, slerp rotation). Raises TransformError
        when the frames are not connected or the stamp lies outside a timed edge's samples, naming the
        frames and the time."""
        up_source, up_target = self.chain(target, source)
        common_from_source = np.eye(4)
        for frame in up_source[:-1]:
            common_from_source = self._edge(frame, stamp_ns) @ common_from_source
        common_from_target = np.eye(4)
        for frame in up_target[:-1]:
            common_from_target = self._edge(frame, stamp_ns) @ common_from_target
        if len(up_target) == 1:
            return common_from_source
        return np.linalg.inv(common_from_target) @ common_from_source

    def _edge(self, child: str, stamp_ns: int) -> np.ndarray:
        if child in self._static:
            return self._static[child][1]
        return self._timed[child].at(stamp_ns, child)

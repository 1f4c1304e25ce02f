"""The Mapper: one voxel map, one integrator, the Dirichlet post-pass, queries and merging.

    mapper = Mapper(load_config([...], method="ebs").mapping, num_classes=9)
    mapper.integrate(points_world, alpha, payload_type="alpha")      # one scan or bin
    mapper.integrate_many(dataset)                                   # scans in order, the next ones prepared meanwhile
    result = mapper.query(query_points)                              # label, probs, variance, state
    mapper.save("map.npz")

Input checks live here, before any launch: shapes, NaN/inf, class counts, negative evidence.

Coordinates: the map keeps a float64 origin, a multiple of ORIGIN_STEP_VOXELS voxels near the
first scan, and hands the integrators points relative to it, so kernels see small numbers however
far from (0, 0, 0) the data lie (UTM coordinates, say). Voxel indices outside the Mapper are global
(relative to the lattice's zero), so maps of one area from different drives stay comparable and
mergeable whatever origin each picked.
"""

from __future__ import annotations

import enum
import os
import threading
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .. import __version__
from ..config import Fusion, MappingConfig, PayloadType, flat_items
from ..frames import WorldFrame, check_same_frame
from ..kernels import load_once
from ..limits import check_memory_bytes
from ..voxel_keys import check_index_range, voxel_index_of
from . import map_file
from .integrators import IntegrationStats, Launch, ScanPayload, SensorOrigin, make_integrator
from .shards import PendingUpdates, ShardLanes
from .voxel_map import EXTRA_COLUMNS, TableBudget, VoxelArrays, VoxelMap, add_duplicate_voxels, sum_shard_rows
from .warp_runtime import device_calls


class VoxelState(enum.IntEnum):
    """A voxel's state: UNKNOWN (no evidence reached it), FREE (label 0 wins), OCCUPIED (another class wins)."""

    UNKNOWN = 0
    FREE = 1
    OCCUPIED = 2


UNKNOWN_LABEL = -1  # query label of a point whose voxel is not in the map
FREE_CLASS = 0  # label 0 (void) means free space
# The automatic origin is a multiple of this many voxels (1.6 km at 0.2 m): data within half of it
# of (0, 0, 0) keep the origin at zero, and it is a multiple of every block size (S-BKI's 2^(depth-1)
# cells, SEE-CSOM's 2), so blocks line up between maps of one area.
ORIGIN_STEP_VOXELS = 8192
# integrate_many: how many launched scans the shards may still be working on (``ShardLanes``).
LAUNCHES_IN_FLIGHT = 2


@dataclass
class DirichletSummary:
    """Post-pass per voxel: argmax label (lowest index on ties), probabilities, the variance of the
    winning class p (1 - p) / (S + 1), and the state (UNKNOWN if never touched, FREE iff label 0)."""

    label: np.ndarray
    probabilities: np.ndarray
    variance: np.ndarray
    state: np.ndarray


def summarize_dirichlet(alpha: np.ndarray, touched: np.ndarray) -> DirichletSummary:
    """The read-out of concentrations ``alpha`` [V, K] (``touched`` [V]: any update landed): the
    ``DirichletSummary`` of every voxel, in float64."""
    # float64: concentrations of a long drive's ground voxels differ in digits float32 does not hold.
    alpha = np.asarray(alpha, dtype=np.float64)
    total = alpha.sum(axis=1)
    probabilities = alpha / total[:, None]
    label = np.argmax(probabilities, axis=1)
    p = probabilities[np.arange(len(label)), label]
    variance = (p - p * p) / (total + 1.0)
    state = np.where(label == FREE_CLASS, VoxelState.FREE, VoxelState.OCCUPIED).astype(np.int8)
    state[~np.asarray(touched, dtype=bool)] = VoxelState.UNKNOWN
    return DirichletSummary(label.astype(np.int32), probabilities, variance, state)


def belief_masses(log_commonality: np.ndarray) -> np.ndarray:
    """Dempster-Shafer masses [V, K] on the singletons from the accumulated log commonality ratios
    D_k = sum_n log(1 + b'_nk / u'_n) (kernels/scatter.py): m_k = (e^D_k - 1) / (sum_j (e^D_j - 1) + 1);
    the frame keeps 1 / (same). Computed in float64 relative to max D, so no exponent overflows."""
    d = np.asarray(log_commonality, dtype=np.float64)
    if d.size == 0:
        return d
    top = d.max(axis=1, keepdims=True)
    scaled = np.exp(d - top) - np.exp(-top)
    return scaled / (scaled.sum(axis=1, keepdims=True) + np.exp(-top))


def summarize_beliefs(masses: np.ndarray, touched: np.ndarray) -> DirichletSummary:
    """The Dempster-Shafer read-out (docs/algorithm.md §3.7): label = argmax of the masses (all zero -> 0, FREE), probabilities =
    masses / their sum, "variance" = the uncommitted mass 1 - sum m."""
    masses = np.asarray(masses, dtype=np.float64)
    committed = masses.sum(axis=1)
    probabilities = np.divide(masses, committed[:, None], out=np.zeros_like(masses), where=committed[:, None] > 0)
    label = np.argmax(masses, axis=1).astype(np.int32)
    state = np.where(label == FREE_CLASS, VoxelState.FREE, VoxelState.OCCUPIED).astype(np.int8)
    state[~np.asarray(touched, dtype=bool)] = VoxelState.UNKNOWN
    return DirichletSummary(label, probabilities, 1.0 - committed, state)


def scan_fingerprint(points: np.ndarray, payload: np.ndarray) -> str:
    """A scan's identity by content, cheap enough for every scan: its size and about 256 evenly spaced points
    and payload rows, hashed (16 hex digits). Two different scans share it only if they agree in all of
    those rows, which different sweeps never do; the same scan mapped twice always does. Sampling instead
    of hashing everything keeps it a small share of a scan's mapping time (docs/performance.md)."""
    import hashlib

    n = len(points)
    step = max(1, n // 256)
    digest = hashlib.blake2b(digest_size=8)
    digest.update(np.int64(n).tobytes())
    digest.update(np.ascontiguousarray(points[::step], np.float64).tobytes())
    digest.update(np.ascontiguousarray(np.asarray(payload)[::step], np.float64).tobytes())
    return digest.hexdigest()


@dataclass
class PreparedScan:
    """A scan ready to launch: the integrator's launch, the scan's fingerprint, and whether the scan
    set the map origin (undone when the launch is refused)."""

    launch: Launch
    scan_id: str
    sets_origin: bool


@dataclass
class QueryResult:
    """Per query point: label (-1 where the voxel is not in the map), probabilities [M, K],
    variance of the label's class, state (VoxelState values), and the global index [M, 3] of the
    voxel the point falls in (stored or not)."""

    label: np.ndarray
    probabilities: np.ndarray
    variance: np.ndarray
    state: np.ndarray
    voxel_index: np.ndarray


class MapVoxels(NamedTuple):
    """Every stored voxel of a map (``Mapper.voxels``): ``arrays``, the accumulated sums per voxel with global
    indices (``VoxelArrays``: index [V, 3], evidence [V, K], hits, touched, ...), and ``summary``, their
    read-out (``DirichletSummary``: label, probabilities, variance, state), row for row in key order.
    Unpacks as ``arrays, summary = mapper.voxels()``."""

    arrays: VoxelArrays
    summary: DirichletSummary


# Coordinates farther than this from (0, 0, 0) are no positions of a map (Earth-centered ones reach
# 6.4e6 m); beyond it float64 cannot place points on a fine voxel lattice, and the origin arithmetic overflows.
MAX_COORDINATE_M = 1e12


def _numeric_array(value, what: str) -> np.ndarray:
    """``value`` as an array of real numbers: numpy arrays and lists as they are, a torch tensor detached
    and on the host; strings, Python objects (ragged rows) and complex numbers are refused."""
    if type(value).__module__.split(".")[0] == "torch":
        value = value.detach().cpu().numpy()
    try:
        array = np.asarray(value)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{what}: cannot be read as an array ({exc})") from None
    if array.dtype.kind not in "biuf":
        kind = {"c": "complex numbers (the imaginary part would be lost)", "O": "Python objects (ragged rows or mixed types)",
                "U": "strings", "S": "bytes"}.get(array.dtype.kind, f"values of dtype {array.dtype}")
        raise ValueError(f"{what}: holds {kind}; pass real numbers")
    return array


def validate_points(points, what: str = "points", *, far_ok: bool = False) -> np.ndarray:
    """[N, 3] finite float64 points, within MAX_COORDINATE_M of (0, 0, 0) unless ``far_ok`` (queries:
    a point however far away is simply in no voxel of the map)."""
    points = _numeric_array(points, what).astype(np.float64, copy=False)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{what}: expected shape [N, 3], got {list(points.shape)}")
    # the common case in two reductions, without numpy's slow row-wise one (NaN fails the comparison)
    if not points.size or max(-points.min(), points.max()) <= (np.finfo(np.float64).max if far_ok else MAX_COORDINATE_M):
        return points
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: {int(bad.sum())} of {len(points)} points have NaN/inf coordinates (first at row {first}: {points[first].tolist()})")
    if far_ok:
        return points
    bad = np.abs(points).max(axis=1) > MAX_COORDINATE_M
    first = int(np.flatnonzero(bad)[0])
    raise ValueError(f"{what}: {int(bad.sum())} of {len(points)} points lie farther than {MAX_COORDINATE_M:g} m from (0, 0, 0) "
                     f"(first at row {first}: {points[first].tolist()}); no map spans that")


def _validate_point(point, what: str) -> np.ndarray:
    """One [3] position (an origin), as validate_points checks a scan."""
    if isinstance(point, (str, bytes)):
        raise ValueError(f"{what}: expected 3 coordinates (x, y, z), got the text {point!r}")
    values = _numeric_array(point, what).reshape(-1)
    if len(values) != 3:
        raise ValueError(f"{what}: expected 3 coordinates (x, y, z), got {len(values)}")
    return validate_points(values.reshape(1, 3), what)[0]


def row_sums(values: np.ndarray) -> np.ndarray:
    """[N] float64 sums of the rows of values [N, K] (float32 or float64), bit for bit numpy's
    ``values.astype(np.float64).sum(axis=1)``: its pairwise order (eight running sums over the columns, then
    the rest) computed column by column, which costs a fraction of numpy's reduction over short rows and the
    float64 copy it needs (docs/performance.md; tests/test_mapping.py holds the two equal)."""
    k = values.shape[1]
    if k > 128:  # numpy splits longer rows in halves first
        return np.asarray(values, dtype=np.float64).sum(axis=1)
    column = lambda j: values[:, j].astype(np.float64)  # noqa: E731
    if k < 8:
        total = np.zeros(len(values))
        for j in range(k):
            total += column(j)
        return total
    partial = [column(j) for j in range(8)]
    j = 8
    while j + 8 <= k:
        for lane in range(8):
            partial[lane] += column(j + lane)
        j += 8
    total = ((partial[0] + partial[1]) + (partial[2] + partial[3])) + ((partial[4] + partial[5]) + (partial[6] + partial[7]))
    for rest in range(j, k):
        total += column(rest)
    return 0.0 + total  # numpy adds the rows' sum to a zero: -0.0 becomes 0.0


def prepare_payload(points, payload, payload_type: PayloadType | str, num_classes: int) -> ScanPayload:
    """Validate a scan and derive its uncertainty from its payload (its probabilities and labels when an
    integrator asks for them)."""
    payload_type = PayloadType(payload_type)
    points = validate_points(points)
    n, k = len(points), num_classes
    payload = _numeric_array(payload, f"payload ({payload_type.value})")
    if payload_type is PayloadType.LABEL:
        if payload.shape != (n,):
            raise ValueError(f"payload: labels must have shape [{n}] (one per point), got {list(payload.shape)}")
        if n and not np.issubdtype(payload.dtype, np.integer):
            if not (np.isfinite(payload).all() and (payload == np.round(payload)).all()):
                raise ValueError("payload: labels must be integers")
        labels = payload.astype(np.int64)
        if n and (labels.min() < 0 or labels.max() >= k):
            raise ValueError(f"payload: label values must lie in [0, {k - 1}] for {k} classes, got {labels.min()}..{labels.max()}")
        return ScanPayload(points, np.zeros(n), labels, k)

    if payload.ndim != 2 or payload.shape[0] != n:
        raise ValueError(f"payload: {payload_type.value} must have shape [{n}, {k}], got {list(payload.shape)}")
    if payload.shape[1] != k:
        raise ValueError(f"payload: {payload.shape[1]} class columns, but the map has {k} classes")
    if payload.dtype not in (np.float32, np.float64):  # float32 stays as it is: each use converts the rows it reads
        payload = payload.astype(np.float64)
    if not np.isfinite(payload).all():
        raise ValueError(f"payload: {int((~np.isfinite(payload)).sum())} NaN/inf values in the {payload_type.value} array")
    if payload_type is PayloadType.ALPHA:
        if n and payload.min() < 1.0:
            row = int(np.argmin(payload.min(axis=1)))
            raise ValueError(f"payload: negative evidence: alpha must be >= 1 (alpha = evidence + 1), row {row} has {payload[row].min()}")
        total = row_sums(payload)
        return ScanPayload(points, k / total, payload, k, total)
    if n and payload.min() < 0:
        raise ValueError(f"payload: probabilities must be >= 0, got {payload.min()}")
    sums = row_sums(payload)
    if n and np.abs(sums - 1.0).max() > 1e-3:
        row = int(np.argmax(np.abs(sums - 1.0)))
        raise ValueError(f"payload: probability rows must sum to 1, row {row} sums to {sums[row]}")
    scan = ScanPayload(points, np.zeros(0), payload, k, sums)
    scan.uncertainty = 1.0 - scan.probabilities.max(axis=1) if n else np.zeros(0)
    return scan


class Mapper:
    """Owns the voxel map (as one shard per worker), its integrator and the post-pass.

    ``workers``: CPU threads that scatter in parallel, each into its own shard (default: up to 2 on
    the CPU, where one Warp launch uses one core; always 1 on CUDA). Results do not depend on it
    beyond float64 summation order. ``origin`` [3] (m): where the map's key range is centered; by
    default the first scan's bounding-box center. Either is snapped to a multiple of
    ORIGIN_STEP_VOXELS voxels; the map spans +-2^20 voxels around it. ``frame``: the world frame the
    points are in (recorded in the map file; maps of different frames do not merge); None when the
    caller does not say. ``max_memory``: bytes the voxel tables of all shards may take together
    (``voxel_map.TableBudget``; None: the memory available at each growth); a scan that would grow them
    past it is refused with ``limits.MemoryBudgetError``."""

    def __init__(
        self,
        config: MappingConfig,
        num_classes: int,
        *,
        class_names: list[str] | tuple[str, ...] | None = None,
        device: str | None = "cpu",
        initial_capacity: int = 1 << 16,
        workers: int | None = None,
        origin=None,
        frame: WorldFrame | None = None,
        max_memory: int | None = None,
    ):
        self.config = config
        self.memory_budget = TableBudget(None if max_memory is None else check_memory_bytes(max_memory, "max_memory"))
        if frame is not None and not isinstance(frame, WorldFrame):
            raise ValueError(f"frame must be a WorldFrame (evsemmap_warp.frames) or None, got {type(frame).__name__}")
        self.frame = frame
        self.num_classes = int(num_classes)
        if class_names is not None and len(class_names) != self.num_classes:
            raise ValueError(f"class_names has {len(class_names)} names for {self.num_classes} classes")
        self.class_names = tuple(class_names) if class_names else tuple(f"class_{i}" for i in range(self.num_classes))
        self.integrator = make_integrator(config, self.num_classes)
        self._kernels_loaded = False
        self.grid_offset_m = self.integrator.grid_offset_m
        self._initial_capacity = initial_capacity
        first = self._new_shard(device)
        self.device = first.device
        if workers is None:
            workers = min(2, os.cpu_count() or 1) if self.device == "cpu" else 1
        if workers < 1 or (workers > 1 and self.device != "cpu"):
            raise ValueError(f"workers must be >= 1, and 1 on a CUDA device; got {workers} on {self.device}")
        self.shards = [first] + [self._new_shard(self.device) for _ in range(workers - 1)]
        self._lanes = ShardLanes(workers) if workers > 1 else None
        # integrate_many prepares the next scans on threads while this scan's kernels run: with several
        # CPU workers, and on a GPU, where the one worker's launches return before the kernels end. A
        # CPU map with one worker prepares scan by scan (its rows are the one-thread figures).
        self.prepare_ahead = self._lanes is not None or self.device != "cpu"
        self.origin_index: np.ndarray | None = None  # [3] int64, global index of the origin voxel corner
        if origin is not None:
            self.origin_index = self._snap_origin(_validate_point(origin, "origin"))
        self.scans_integrated = 0
        self.points_integrated = 0
        # Fingerprints of the scans the map holds (scan_fingerprint): a merge refuses two maps holding one scan
        # (it would count twice). None: not known (a map file written before maps recorded them).
        self.scan_ids: set[str] | None = set()
        # Why the map may not change (a store's cached tile: its later queries would answer from the change); None: it may.
        self.read_only: str | None = None
        self._summary_cache: MapVoxels | None = None

    def _new_shard(self, device) -> VoxelMap:
        return VoxelMap(self.num_classes, self.config.resolution_m, prior=self.config.prior,
                        grid_offset_m=self.grid_offset_m, device=device, initial_capacity=self._initial_capacity,
                        memory_budget=self.memory_budget)

    def _snap_origin(self, point: np.ndarray) -> np.ndarray:
        step = ORIGIN_STEP_VOXELS * self.config.resolution_m
        return (np.round(point / step) * ORIGIN_STEP_VOXELS).astype(np.int64)

    @property
    def origin(self) -> np.ndarray:
        """The map origin (m, float64): a point of the voxel lattice, kernels work relative to it."""
        index = self.origin_index if self.origin_index is not None else np.zeros(3, np.int64)
        return index.astype(np.float64) * self.config.resolution_m

    def _local(self, points: np.ndarray) -> np.ndarray:
        return points - self.origin

    @property
    def voxel_count(self) -> int:
        """Number of voxels in the map (all shards, a voxel counted once)."""
        if len(self.shards) == 1:
            return self.shards[0].voxel_count
        return len(self.voxels().arrays.index)

    @property
    def device_bytes(self) -> int:
        """Device memory held by the map's tables and arrays."""
        return sum(shard.table_bytes for shard in self.shards)

    def integrate(self, points, payload, *, payload_type: PayloadType | str, sensor_origin=None) -> IntegrationStats:
        """Add one scan or bin. points [N, 3] world frame (m); payload [N, K] alpha or
        probabilities, or [N] integer labels, as ``payload_type`` says. An empty scan is a no-op.
        ``sensor_origin`` [3] is needed by the sbki mode (free-space rays)."""
        return self.launch(self.prepare(points, payload, payload_type=payload_type, sensor_origin=sensor_origin))

    def _load_kernels(self) -> None:
        """Compile or load the integrator's kernel modules once, in the calling thread, before its first
        scan: Warp's compiler keeps its precompiled headers per thread, so a first compile on each prepare
        and shard thread built them again; and a map that is only read compiles nothing of them. A GPU
        map loads them for the CPU as well: its host paths (the S-CSM and SEE-CSOM training data, the
        compat modes' fallbacks) launch them there."""
        if not self._kernels_loaded:
            devices = (self.device,) if self.device == "cpu" else (self.device, "cpu")
            for module in self.integrator.kernel_modules(self.device):
                for device in devices:
                    load_once(module, device)
            self._kernels_loaded = True

    def integrate_many(self, scans: Iterable, progress=None) -> list[IntegrationStats]:
        """Add scans in order, each an object with ``points``, ``payload``, ``payload_type`` and
        ``sensor_origin`` (the datasets' ``Scan``; a ``name``, when it has one, prefixes errors).

        The map is the one ``integrate`` gives scan by scan. With more than one worker, or on a GPU
        (``prepare_ahead``), the next scans are read from ``scans`` (in order, one at a time) and get
        their preparation (validation and, in the S-BKI and release modes, training data and block
        tables) on as many threads as there are workers, up to twice as many scans ahead, while this
        scan's kernels run; until the first
        non-empty scan has set the map origin, one scan ahead at most. Each shard works through the
        scans on its own thread (``ShardLanes``), up to LAUNCHES_IN_FLIGHT scans apart from the others.
        ``progress(scan, stats)`` is called after each scan, in order, once all its shards are done.

        A scan that fails is named in the error; the map then holds the scans before it, and may hold
        the next scan and part of the failing one (a shard can be a scan ahead). No shard job is left
        running when the error is raised."""
        self._load_kernels()
        results = []
        if not self.prepare_ahead:
            for scan in scans:
                results.append(self._named(scan, lambda scan=scan: self.launch(self._prepare_scan(scan))))
                if progress:
                    progress(scan, results[-1])
            return results
        # Launched scans whose shard jobs may still run: a shard moves on to the next scan while another
        # finishes this one, at most LAUNCHES_IN_FLIGHT scans behind the launches.
        in_flight = deque()

        def finish_oldest():
            scan, stats = in_flight.popleft()
            results.append(self._named(scan, lambda: self._finish(stats)))
            if progress:
                progress(scan, results[-1])

        iterator = iter(scans)
        turn = threading.Condition()
        next_to_read = 0

        def read_and_prepare(position: int):
            nonlocal next_to_read
            with turn:  # scans are read in order whichever thread gets there first
                turn.wait_for(lambda: next_to_read == position)
                try:
                    scan = next(iterator, None)
                finally:
                    next_to_read += 1
                    turn.notify_all()
            return (None, None) if scan is None else (scan, self._named(scan, lambda: self._prepare_scan(scan)))

        # Twice as many scans in the queue as threads, so that a thread that finishes its scan finds the next
        # one while the main thread waits on an earlier scan (it kept CPUs idle otherwise: the release mode's
        # utilisation went from 1.67 to 1.78 of 2 cores).
        depth = 2 * len(self.shards)
        try:
            with ThreadPoolExecutor(max_workers=len(self.shards), thread_name_prefix="evsemmap-prepare") as ahead:
                pending = deque([ahead.submit(read_and_prepare, 0)])
                submitted = 1
                while pending:
                    scan, prepared = pending.popleft().result()
                    if scan is None:
                        break
                    # The next scans, while this one's kernels run (one at a time until the origin is set).
                    while len(pending) < (depth if self.origin_index is not None else 1):
                        pending.append(ahead.submit(read_and_prepare, submitted))
                        submitted += 1
                    while len(in_flight) >= LAUNCHES_IN_FLIGHT:
                        finish_oldest()
                    in_flight.append((scan, self._named(scan, lambda: self.launch(prepared, wait=False))))
                while in_flight:
                    finish_oldest()
        finally:  # on an error, no shard job may still change the map after this returns
            for _, stats in in_flight:
                if isinstance(stats.voxel_updates, PendingUpdates):
                    stats.voxel_updates.wait()
        return results

    @staticmethod
    def _named(scan, step):
        try:
            return step()
        except ValueError as exc:  # the Mapper names the problem, this the scan it is in
            name = getattr(scan, "name", None)
            if name is None:
                raise
            raise ValueError(f"{name}: {exc}") from None

    def _prepare_scan(self, scan):
        return self.prepare(scan.points, scan.payload, payload_type=scan.payload_type, sensor_origin=scan.sensor_origin)

    def prepare(self, points, payload, *, payload_type: PayloadType | str, sensor_origin=None) -> PreparedScan | None:
        """Validation and the integrator's host work for one scan, ``integrate``'s first half (the map is
        not touched, except that the first non-empty scan sets the origin); returns the scan ready to
        ``launch``, None for an empty scan."""
        self._load_kernels()
        self._check_writable()
        scan = prepare_payload(points, payload, payload_type, self.num_classes)
        needs = self.integrator.needs
        if PayloadType(payload_type) not in needs.payload_types:
            raise ValueError(f"payload_type {PayloadType(payload_type).value}: {needs.payload_reason}")
        if len(scan.points) == 0:
            return None
        reads_sensor_origin = needs.sensor_origin is not SensorOrigin.UNUSED
        if needs.sensor_origin is SensorOrigin.REQUIRED and sensor_origin is None:
            raise ValueError(f"sensor_origin: {needs.sensor_origin_reason}; pass it")
        if reads_sensor_origin and sensor_origin is not None:
            sensor_origin = _validate_point(sensor_origin, "sensor_origin")
        scan_id = scan_fingerprint(scan.points, scan.payload)
        sets_origin = self.origin_index is None
        if sets_origin:
            self.origin_index = self._snap_origin((scan.points.min(axis=0) + scan.points.max(axis=0)) / 2)
        try:
            scan.points = self._local(scan.points)
            if reads_sensor_origin:  # the map origin stands in for an optional one not given
                scan.sensor_origin = self._local(self.origin if sensor_origin is None else sensor_origin)
            scan.check_room = self.check_room
            return PreparedScan(self.integrator.prepare(scan, self.device), scan_id, sets_origin)
        except BaseException:
            if sets_origin:  # a refused first scan leaves no origin behind: the next one picks it, as in a fresh map
                self.origin_index = None
            raise

    def launch(self, prepared: "PreparedScan | None", *, wait: bool = True) -> IntegrationStats:
        """Run a prepared scan's launch (``prepare``), ``integrate``'s second half; ``wait=False`` may
        return while its shard jobs still run (``_finish`` waits for them). A launch refused before any
        write (the key range, checked for the whole scan) changes nothing: no counts, no scan id, no
        origin it set."""
        if prepared is None:
            return IntegrationStats()
        try:
            with device_calls(self.device):
                stats = prepared.launch(self.shards, self._lanes)
        except BaseException:
            if prepared.sets_origin and self.scans_integrated == 0 and all(shard.voxel_count == 0 for shard in self.shards):
                self.origin_index = None
            raise
        self.scans_integrated += 1
        self.points_integrated += stats.input_points
        if self.scan_ids is not None:
            self.scan_ids.add(prepared.scan_id)
        self._summary_cache = None
        return self._finish(stats) if wait else stats

    @staticmethod
    def _finish(stats: IntegrationStats) -> IntegrationStats:
        if isinstance(stats.voxel_updates, PendingUpdates):
            stats.voxel_updates = stats.voxel_updates.result()
        return stats

    # ------------------------------------------------------------------ reading
    def shard_rows(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """A host copy of each shard's stored keys (relative to the map origin) and value rows
        (``VoxelMap.stored_rows``), for ``voxel_map.sum_shard_rows`` to merge."""
        with device_calls(self.device):
            return [shard.stored_rows() for shard in self.shards]

    def _local_voxels(self) -> VoxelArrays:
        return sum_shard_rows(self.shard_rows())

    def voxels(self) -> MapVoxels:
        """All stored voxels in key order, with global indices (``.arrays``), and their read-out
        (``.summary``); cached until the next integrate."""
        if self._summary_cache is None:
            arrays = self._local_voxels()
            if self.origin_index is not None:
                arrays.index = arrays.index + self.origin_index
            self._summary_cache = MapVoxels(arrays, self.summarize(arrays.evidence, arrays.touched))
        return self._summary_cache

    def concentrations(self, evidence: np.ndarray) -> np.ndarray:
        """Dirichlet concentrations alpha = prior + evidence (float64); for the Dempster-Shafer
        method, the belief masses (what the map file stores as ``alpha`` for it)."""
        if self.config.fusion is Fusion.DEMPSTER:
            return belief_masses(evidence)
        return self.config.prior + np.asarray(evidence, dtype=np.float64)

    def summarize(self, evidence: np.ndarray, touched: np.ndarray) -> DirichletSummary:
        """The read-out of voxels' ``evidence`` [V, K] and ``touched`` [V] with this map's prior and fusion:
        labels, probabilities, variance and states."""
        if self.config.fusion is Fusion.DEMPSTER:
            return summarize_beliefs(belief_masses(evidence), touched)
        return summarize_dirichlet(self.concentrations(evidence), touched)

    def voxel_centers(self, index: np.ndarray) -> np.ndarray:
        """World centers (m, float64) of global voxel indices."""
        return (np.asarray(index, dtype=np.float64) + 0.5) * self.config.resolution_m + self.grid_offset_m

    def query(self, points) -> QueryResult:
        """Label, probabilities, variance and state of the voxel containing each point [M, 3];
        label -1 (UNKNOWN state) for points in no stored voxel, however far away."""
        points = validate_points(points, "query points", far_ok=True)
        m = len(points)
        rows = np.zeros((m, self.num_classes + EXTRA_COLUMNS))
        found = np.zeros(m, dtype=bool)
        if self.origin_index is not None and m:
            local = self._local(points)
            for shard in self.shards:
                voxel_rows = shard.lookup_points(local)
                rows += shard.rows_at(voxel_rows)
                found |= voxel_rows >= 0
        arrays = VoxelArrays.from_rows(np.zeros((m, 3), np.int64), rows)
        summary = self.summarize(arrays.evidence, arrays.touched)
        label = np.where(found, summary.label, UNKNOWN_LABEL).astype(np.int32)
        origin_index = self.origin_index if self.origin_index is not None else np.zeros(3, np.int64)
        voxel_index = voxel_index_of(points, self.config.resolution_m, self.grid_offset_m, origin_index)
        return QueryResult(label, summary.probabilities, summary.variance, summary.state, voxel_index)

    def state_counts(self) -> dict[str, int]:
        """How many voxels are UNKNOWN, FREE and OCCUPIED, by state name."""
        summary = self.voxels().summary
        return {s.name: int((summary.state == s).sum()) for s in VoxelState}

    # ------------------------------------------------------------------ files and merging
    def save(self, path) -> Path:
        """Write the map file (schema in ``core/map_file.py``: the sums, not the read-out)."""
        return map_file.write_map_file(path, self.contents_of(self.voxels().arrays, read_out=False))

    def contents_of(self, arrays: VoxelArrays, summary: DirichletSummary | None = None, *, read_out: bool = True,
                    **meta) -> "map_file.MapContents":
        """What a map file of ``arrays`` (global indices) holds with this map's parameters, origin and
        frame, with (``read_out``) the read-out derived here (concentrations, centers, labels, states,
        variance; ``summary`` when already at hand); ``meta`` overrides keys of ``metadata()``."""
        contents = map_file.MapContents(
            meta=self.metadata() | meta, origin=self.origin, index=arrays.index, evidence=arrays.evidence,
            weight_sum=arrays.weight_sum, weighted_uncertainty_sum=arrays.weighted_uncertainty_sum, hits=arrays.hits,
            touched=arrays.touched, weighted_height_sum=arrays.weighted_height_sum, resolution=self.config.resolution_m, config=self.config,
            origin_index=self.origin_index, frame=self.frame)
        if read_out:
            contents.summary = summary if summary is not None else self.summarize(arrays.evidence, arrays.touched)
            contents.alpha, contents.centers = self.concentrations(arrays.evidence), self.voxel_centers(arrays.index)
        return contents

    def check_room(self, new_voxels: int) -> None:
        """Refuse (MemoryBudgetError) ``new_voxels`` more voxels, spread over the shards, where the memory
        budget does not hold the tables they need; changes nothing."""
        self.shards[0].check_room(-(-int(new_voxels) // len(self.shards)))

    def _check_writable(self) -> None:
        if self.read_only is not None:
            raise ValueError(f"this map is read-only: {self.read_only}")

    @classmethod
    def for_dataset(cls, dataset, config: MappingConfig, *, device: str | None = "cpu", workers: int | None = None,
                    origin=None, max_memory: int | None = None) -> "Mapper":
        """An empty map for ``dataset`` (what ``open_dataset`` returns, or any scan source with
        ``num_classes``, ``class_names`` and ``frame``): its classes, in its world frame.

        The one way data becomes a map: ``evsemmap map``, ``batch``, ``experiment`` and the viewer build
        their mappers here too. Building ``Mapper(config, dataset.num_classes, ...)`` by hand leaves the
        frame unrecorded, so the map could not be merged with a map the command line made of the same
        data (``check_same_frame``) and its exports would not say where they are."""
        return cls(config, dataset.num_classes, class_names=dataset.class_names or None, device=device, workers=workers,
                   origin=origin, frame=dataset.frame, max_memory=max_memory)

    @classmethod
    def load(cls, path, *, device: str | None = "cpu") -> "Mapper":
        """A map file (validated on reading) as a Mapper that can be queried, extended and merged."""
        return cls.from_contents(map_file.read_map_file(path), path, device=device)

    @classmethod
    def from_contents(cls, contents: "map_file.MapContents", path, *, device: str | None = "cpu") -> "Mapper":
        """A map file's validated contents (``map_file.read_map_file(path)``) as a Mapper."""
        meta = contents.meta
        mapper = cls(contents.config, int(meta["num_classes"]), class_names=meta["classes"], device=device, frame=contents.frame)
        if float(meta["grid_offset_m"]) != mapper.grid_offset_m:
            raise map_file.MapFileError(f"{path}: meta.grid_offset_m {meta['grid_offset_m']} disagrees with the method's grid offset "
                                        f"{mapper.grid_offset_m}")
        try:
            mapper.load_voxels(contents.voxels(), origin_index=contents.origin_index)
        except ValueError as exc:
            raise map_file.MapFileError(f"{path}: {exc}") from None
        mapper.scans_integrated = int(meta["scans_integrated"])
        mapper.points_integrated = int(meta["points_integrated"])
        mapper.scan_ids = None if meta.get("scan_ids") is None else set(meta["scan_ids"])
        return mapper

    def check_mergeable(self, other: "Mapper", *, same_frame: bool = False) -> None:
        """Raise ValueError naming what differs when the two maps cannot be added up, or when they hold
        a scan in common (its evidence would count twice: a map merged with itself, or with a part of it).
        ``same_frame``: the caller says two runs' frames of one name (``odom``) are one (``check_same_frame``)."""
        if not isinstance(other, Mapper):
            raise ValueError(f"merge: the second map must be a Mapper, got {type(other).__name__}")
        check_same_frame("merge", ("the first map", self.frame), ("the second", other.frame), same_frame=same_frame)
        if self.scan_ids and other.scan_ids:
            common = self.scan_ids & other.scan_ids
            if common:
                raise ValueError(f"merge: the maps hold {len(common)} scan(s) in common (the second holds {len(other.scan_ids)}, "
                                 f"{len(common)} of them already in the first): their evidence would count twice; merge maps of "
                                 f"disjoint scan sets (first common scan id {min(common)})")
        if self.class_names != other.class_names:
            raise ValueError(f"merge: the maps have different classes ({list(self.class_names)} vs {list(other.class_names)})")
        if self.config.resolution_m != other.config.resolution_m:
            raise ValueError(f"merge: the maps have different resolutions ({self.config.resolution_m} m vs {other.config.resolution_m} m)")
        if self.config.method != other.config.method:
            raise ValueError(f"merge: the maps come from different methods ({self.config.method} vs {other.config.method})")
        mine, theirs = flat_items(self.config.as_dict()), flat_items(other.config.as_dict())
        differing = sorted(k for k in mine if mine[k] != theirs[k])
        if differing:
            raise ValueError("merge: the maps' parameters differ: " + ", ".join(f"{k} {mine[k]!r} vs {theirs[k]!r}" for k in differing))

    def merge(self, other: "Mapper", *, same_frame: bool = False) -> "Mapper":
        """A new map holding the evidence of both (maps of disjoint scan sets): evidence (concentration
        above the prior), weights and counts add, touched is or-ed; a map with another origin on the
        same lattice is re-indexed. Exact up to float64 summation order: BKI updates are sums.
        ``same_frame``: two runs' ``odom`` frames are one (a drive cut into two logs); the new map
        records this map's frame and run."""
        self.check_mergeable(other, same_frame=same_frame)
        out = Mapper(self.config, self.num_classes, class_names=self.class_names, device=self.device, workers=len(self.shards),
                     frame=self.frame)
        out.origin_index = self.origin_index if self.origin_index is not None else other.origin_index
        parts = [m.voxels().arrays for m in (self, other) if m.origin_index is not None]
        if parts:
            index = np.concatenate([p.index for p in parts])
            merged = VoxelArrays.from_rows(index, np.concatenate([p.rows() for p in parts]))
            try:
                out.load_voxels(merged, origin_index=out.origin_index)
            except ValueError as exc:
                raise ValueError(f"merge: the maps lie too far apart for one map ({exc})") from None
        out.scans_integrated = self.scans_integrated + other.scans_integrated
        out.points_integrated = self.points_integrated + other.points_integrated
        out.scan_ids = None if self.scan_ids is None or other.scan_ids is None else self.scan_ids | other.scan_ids
        return out

    def load_voxels(self, voxels: VoxelArrays, *, origin_index=None) -> None:
        """Replace the map's contents with ``voxels`` (global indices; several rows of one voxel are
        added up), re-indexed around ``origin_index`` (default: the map's own, or the data's center)."""
        self._check_writable()
        if origin_index is None:
            origin_index = self.origin_index
        if origin_index is None and len(voxels.index):
            center = (voxels.index.min(axis=0) + voxels.index.max(axis=0)) // 2
            origin_index = self._snap_origin(center * self.config.resolution_m)
        self.origin_index = None if origin_index is None else np.asarray(origin_index, np.int64).reshape(3)
        local = voxels.index - (self.origin_index if self.origin_index is not None else 0)
        check_index_range(local, "voxel indices")
        self.shards[0].load_arrays(add_duplicate_voxels(local, voxels.rows()))
        for i in range(1, len(self.shards)):
            self.shards[i] = self._new_shard(self.device)
        self._summary_cache = None
        self.scan_ids = None  # which scans these voxels hold is the caller's to say (load, merge, a store's to_mapper)

    def metadata(self) -> dict:
        """What a map file records beside the arrays (its ``meta``): format, classes, method and every
        mapping parameter, grid offset, world frame, scan and point counts, scan ids and the writer's
        version."""
        return {
            "format": map_file.FORMAT_NAME,
            "classes": list(self.class_names),
            "num_classes": self.num_classes,
            "method": self.config.method,
            "mapping": self.config.as_dict(),
            "grid_offset_m": self.grid_offset_m,
            "frame": None if self.frame is None else self.frame.as_dict(),
            "scans_integrated": self.scans_integrated,
            "points_integrated": self.points_integrated,
            "scan_ids": None if self.scan_ids is None else sorted(self.scan_ids),
            "written_by": f"evsemmap_warp {__version__}",
        }


def save_map(path, mapper: Mapper) -> Path:
    """``mapper.save(path)``: write the map file; returns its path."""
    return mapper.save(path)


def load_map(path, *, device: str | None = "cpu") -> Mapper:
    """``Mapper.load(path)``: a map file as a Mapper on ``device``. Raises MapFileError naming the file when
    its content is missing, truncated or does not add up."""
    return Mapper.load(path, device=device)


def reader_mapper(contents: "map_file.MapContents") -> Mapper:
    """An empty Mapper with a map file's parameters, classes, frame and origin: the read-out of its voxels
    without a table of its own to speak of."""
    reader = Mapper(contents.config, int(contents.meta["num_classes"]), class_names=tuple(contents.meta["classes"]), workers=1,
                    initial_capacity=1, frame=contents.frame)
    reader.origin_index = None if contents.origin_index is None else np.asarray(contents.origin_index, np.int64)
    return reader


def with_read_out(contents: "map_file.MapContents") -> "map_file.MapContents":
    """``contents`` with its read-out (concentrations, centers, labels, states, variance) derived as a
    Mapper of its parameters derives them."""
    if contents.alpha is not None and contents.centers is not None and contents.summary is not None:
        return contents
    reader = reader_mapper(contents)
    return replace(contents, alpha=reader.concentrations(contents.evidence), centers=reader.voxel_centers(contents.index),
                   summary=reader.summarize(contents.evidence, contents.touched))


def read_map_arrays(path) -> tuple[dict[str, np.ndarray], dict]:
    """Every array of a map file (``map_file.file_arrays``: the read-out derived) and the parsed meta,
    validated (``core/map_file.py``)."""
    contents = map_file.read_map_file(Path(path))
    return map_file.file_arrays(with_read_out(contents)), contents.meta

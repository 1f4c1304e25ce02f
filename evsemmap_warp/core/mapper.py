"""The Mapper: one voxel map, one integrator, the Dirichlet post-pass, queries and merging.

    mapper = Mapper(load_config([...], method="ebs").mapping, num_classes=9)
    mapper.integrate(points_world, alpha, payload_type="alpha")      # one scan or bin
    result = mapper.query(query_points)                              # label, probs, variance, state
    mapper.save("map.npz")

Input checks live here, before any launch: shapes, NaN/inf, class counts, negative evidence.
"""

from __future__ import annotations

import enum
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .. import __version__
from ..config import Compat, Fusion, Kernel, MappingConfig, PayloadType
from .integrators import (ConvBkiIntegrator, IntegrationStats, KernelIntegrator, SbkiCompatIntegrator, ScanPayload,
                          SeeCsomIntegrator)
from .voxel_map import FLAG_TOUCHED, VoxelArrays, VoxelMap, sum_voxel_arrays


class VoxelState(enum.IntEnum):
    UNKNOWN = 0
    FREE = 1
    OCCUPIED = 2


UNKNOWN_LABEL = -1  # query label of a point whose voxel is not in the map
FREE_CLASS = 0  # label 0 (void) means free space


@dataclass
class DirichletSummary:
    """Post-pass per voxel: argmax label (lowest index on ties), probabilities, the variance of the
    winning class p (1 - p) / (S + 1), and the state (UNKNOWN if never touched, FREE iff label 0)."""

    label: np.ndarray
    probabilities: np.ndarray
    variance: np.ndarray
    state: np.ndarray


def summarize_dirichlet(alpha: np.ndarray, touched: np.ndarray) -> DirichletSummary:
    # float32 throughout, as the original code, so near-ties resolve the same way.
    alpha = np.asarray(alpha, dtype=np.float32)
    total = alpha.sum(axis=1, dtype=np.float32)
    probabilities = alpha / total[:, None]
    label = np.argmax(probabilities, axis=1)
    p = probabilities[np.arange(len(label)), label]
    variance = ((p - p * p) / (total + np.float32(1.0))).astype(np.float32)
    state = np.where(label == FREE_CLASS, VoxelState.FREE, VoxelState.OCCUPIED).astype(np.int8)
    state[~np.asarray(touched, dtype=bool)] = VoxelState.UNKNOWN
    return DirichletSummary(label.astype(np.int32), probabilities, variance, state)


def belief_masses(log_commonality: np.ndarray) -> np.ndarray:
    """Dempster-Shafer masses [V, K] on the singletons from the accumulated log commonality ratios
    D_k = sum_n log(1 + b'_nk / u'_n) (kernels/scatter.py): m_k = (e^D_k - 1) / (sum_j (e^D_j - 1) + 1);
    the frame keeps 1 / (same). Computed in float64 relative to max D, so no exponent overflows."""
    d = np.asarray(log_commonality, dtype=np.float64)
    if d.size == 0:
        return d.astype(np.float32)
    top = d.max(axis=1, keepdims=True)
    scaled = np.exp(d - top) - np.exp(-top)
    return (scaled / (scaled.sum(axis=1, keepdims=True) + np.exp(-top))).astype(np.float32)


def summarize_beliefs(masses: np.ndarray, touched: np.ndarray) -> DirichletSummary:
    """Spec 3.10 read-out: label = argmax of the masses (all zero -> 0, FREE), probabilities =
    masses / their sum, "variance" = the uncommitted mass 1 - sum m."""
    masses = np.asarray(masses, dtype=np.float32)
    committed = masses.sum(axis=1)
    probabilities = np.divide(masses, committed[:, None], out=np.zeros_like(masses), where=committed[:, None] > 0)
    label = np.argmax(masses, axis=1).astype(np.int32)
    state = np.where(label == FREE_CLASS, VoxelState.FREE, VoxelState.OCCUPIED).astype(np.int8)
    state[~np.asarray(touched, dtype=bool)] = VoxelState.UNKNOWN
    return DirichletSummary(label, probabilities, (1.0 - committed).astype(np.float32), state)


@dataclass
class QueryResult:
    """Per query point: label (-1 where the voxel is not in the map), probabilities [M, K],
    variance of the label's class, state (VoxelState values)."""

    label: np.ndarray
    probabilities: np.ndarray
    variance: np.ndarray
    state: np.ndarray


def _validate_points(points, what: str = "points") -> np.ndarray:
    try:
        points = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: cannot be read as a float array ({exc})") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{what}: expected shape [N, 3], got {list(points.shape)}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: {int(bad.sum())} of {len(points)} points have NaN/inf coordinates (first at row {first}: {points[first].tolist()})")
    return points


def prepare_payload(points, payload, payload_type: PayloadType | str, num_classes: int) -> ScanPayload:
    """Validate a scan and derive probabilities, uncertainty and labels from its payload."""
    payload_type = PayloadType(payload_type)
    points = _validate_points(points)
    n, k = len(points), num_classes
    payload = np.asarray(payload)
    if payload_type is PayloadType.LABEL:
        if payload.shape != (n,):
            raise ValueError(f"payload: labels must have shape [{n}] (one per point), got {list(payload.shape)}")
        if n and not np.issubdtype(payload.dtype, np.integer):
            if not (np.isfinite(payload).all() and (payload == np.round(payload)).all()):
                raise ValueError("payload: labels must be integers")
        labels = payload.astype(np.int64)
        if n and (labels.min() < 0 or labels.max() >= k):
            raise ValueError(f"payload: label values must lie in [0, {k - 1}] for {k} classes, got {labels.min()}..{labels.max()}")
        probabilities = np.zeros((n, k))
        probabilities[np.arange(n), labels] = 1.0
        return ScanPayload(points, probabilities, np.zeros(n), labels)

    if payload.ndim != 2 or payload.shape[0] != n:
        raise ValueError(f"payload: {payload_type.value} must have shape [{n}, {k}], got {list(payload.shape)}")
    if payload.shape[1] != k:
        raise ValueError(f"payload: {payload.shape[1]} class columns, but the map has {k} classes")
    payload = payload.astype(np.float64)
    if not np.isfinite(payload).all():
        raise ValueError(f"payload: {int((~np.isfinite(payload)).sum())} NaN/inf values in the {payload_type.value} array")
    if payload_type is PayloadType.ALPHA:
        if n and payload.min() < 1.0:
            row = int(np.argmin(payload.min(axis=1)))
            raise ValueError(f"payload: negative evidence: alpha must be >= 1 (alpha = evidence + 1), row {row} has {payload[row].min()}")
        total = payload.sum(axis=1)
        probabilities = payload / total[:, None]
        uncertainty = k / total
    else:
        if n and payload.min() < 0:
            raise ValueError(f"payload: probabilities must be >= 0, got {payload.min()}")
        sums = payload.sum(axis=1)
        if n and np.abs(sums - 1.0).max() > 1e-3:
            row = int(np.argmax(np.abs(sums - 1.0)))
            raise ValueError(f"payload: probability rows must sum to 1, row {row} sums to {sums[row]}")
        probabilities = payload / sums[:, None] if n else payload
        uncertainty = 1.0 - probabilities.max(axis=1) if n else np.zeros(0)
    return ScanPayload(points, probabilities, uncertainty, np.argmax(payload, axis=1) if n else np.zeros(0, np.int64))


class Mapper:
    """Owns the voxel map (as one shard per worker), its integrator and the post-pass.

    ``workers``: CPU threads that scatter in parallel, each into its own shard (default: up to 2 on
    the CPU, where one Warp launch uses one core; always 1 on CUDA). Results do not depend on it
    beyond float32 summation order."""

    def __init__(
        self,
        config: MappingConfig,
        num_classes: int,
        *,
        class_names: list[str] | tuple[str, ...] | None = None,
        device: str | None = "cpu",
        initial_capacity: int = 1 << 16,
        workers: int | None = None,
    ):
        self.config = config
        self.num_classes = int(num_classes)
        if class_names is not None and len(class_names) != self.num_classes:
            raise ValueError(f"class_names has {len(class_names)} names for {self.num_classes} classes")
        self.class_names = tuple(class_names) if class_names else tuple(f"class_{i}" for i in range(self.num_classes))
        self.grid_offset_m = 0.0
        if config.compat is Compat.SBKI:
            self.integrator = SbkiCompatIntegrator(config)
            self.grid_offset_m = SbkiCompatIntegrator.grid_offset_m(config)
        elif config.kernel is Kernel.CONVBKI:
            self.integrator = ConvBkiIntegrator(config, self.num_classes)
        elif config.kernel is Kernel.SEE_CSOM:
            self.integrator = SeeCsomIntegrator(config, self.num_classes)
        else:
            self.integrator = KernelIntegrator(config)
        self._initial_capacity = initial_capacity
        first = self._new_shard(device)
        self.device = first.device
        if workers is None:
            workers = min(2, os.cpu_count() or 1) if self.device == "cpu" else 1
        if workers < 1 or (workers > 1 and self.device != "cpu"):
            raise ValueError(f"workers must be >= 1, and 1 on a CUDA device; got {workers} on {self.device}")
        self.shards = [first] + [self._new_shard(self.device) for _ in range(workers - 1)]
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="evsemmap") if workers > 1 else None
        self.scans_integrated = 0
        self.points_integrated = 0
        self._summary_cache: tuple[VoxelArrays, DirichletSummary] | None = None

    def _new_shard(self, device) -> VoxelMap:
        return VoxelMap(self.num_classes, self.config.resolution_m, prior=self.config.prior,
                        grid_offset_m=self.grid_offset_m, device=device, initial_capacity=self._initial_capacity)

    @property
    def voxel_count(self) -> int:
        if len(self.shards) == 1:
            return self.shards[0].voxel_count
        return len(self.voxels()[0].index)

    @property
    def device_bytes(self) -> int:
        """Device memory held by the map's tables and arrays."""
        return sum(shard.table_bytes for shard in self.shards)

    def integrate(self, points, payload, *, payload_type: PayloadType | str, sensor_origin=None) -> IntegrationStats:
        """Add one scan or bin. points [N, 3] world frame (m); payload [N, K] alpha or
        probabilities, or [N] integer labels, as ``payload_type`` says. An empty scan is a no-op.
        ``sensor_origin`` [3] is needed by the sbki mode (free-space rays)."""
        scan = prepare_payload(points, payload, payload_type, self.num_classes)
        if len(scan.points) == 0:
            return IntegrationStats()
        if isinstance(self.integrator, (SbkiCompatIntegrator, SeeCsomIntegrator)):
            if sensor_origin is None:
                raise ValueError(f"sensor_origin: {self.config.method} adds the sensor origin (and free-space rays) as free samples; pass it")
            origin = _validate_points(np.asarray(sensor_origin, dtype=np.float64).reshape(1, 3), "sensor_origin")[0]
            stats = self.integrator.integrate(self.shards, scan, origin, self._executor)
        else:
            stats = self.integrator.integrate(self.shards, scan, self._executor)
        self.scans_integrated += 1
        self.points_integrated += len(scan.points)
        self._summary_cache = None
        return stats

    # ------------------------------------------------------------------ reading
    def voxels(self) -> tuple[VoxelArrays, DirichletSummary]:
        """All stored voxels in key order and their post-pass (cached until the next integrate)."""
        if self._summary_cache is None:
            arrays = sum_voxel_arrays([shard.arrays() for shard in self.shards])
            self._summary_cache = (arrays, self.summarize(arrays.evidence, arrays.touched))
        return self._summary_cache

    def concentrations(self, evidence: np.ndarray) -> np.ndarray:
        """Dirichlet concentrations alpha = prior + evidence, in float32; for the Dempster-Shafer
        method, the belief masses (what the map file stores as ``alpha`` for it)."""
        if self.config.fusion is Fusion.DEMPSTER:
            return belief_masses(evidence)
        return np.float32(self.config.prior) + np.asarray(evidence, dtype=np.float32)

    def summarize(self, evidence: np.ndarray, touched: np.ndarray) -> DirichletSummary:
        if self.config.fusion is Fusion.DEMPSTER:
            return summarize_beliefs(belief_masses(evidence), touched)
        return summarize_dirichlet(self.concentrations(evidence), touched)

    def voxel_centers(self, index: np.ndarray) -> np.ndarray:
        return (np.asarray(index, dtype=np.float64) + 0.5) * self.config.resolution_m + self.grid_offset_m

    def query(self, points) -> QueryResult:
        """Label, probabilities, variance and state of the voxel containing each point [M, 3]."""
        points = _validate_points(points, "query points")
        m, k = len(points), self.num_classes
        evidence = np.zeros((m, k), dtype=np.float32)
        touched = np.zeros(m, dtype=bool)
        found = np.zeros(m, dtype=bool)
        for shard in self.shards:
            slots = shard.lookup_points(points)
            hit = slots >= 0
            if hit.any():
                evidence[hit] += shard.evidence.numpy()[slots[hit]]
                touched[hit] |= shard.flags.numpy()[slots[hit], FLAG_TOUCHED] > 0
            found |= hit
        summary = self.summarize(evidence, touched)
        label = np.where(found, summary.label, UNKNOWN_LABEL).astype(np.int32)
        return QueryResult(label, summary.probabilities, summary.variance, summary.state)

    def state_counts(self) -> dict[str, int]:
        _, summary = self.voxels()
        return {s.name: int((summary.state == s).sum()) for s in VoxelState}

    # ------------------------------------------------------------------ files and merging
    def save(self, path) -> None:
        from .map_file import save_map

        save_map(path, self)

    @classmethod
    def load(cls, path, *, device: str | None = "cpu") -> "Mapper":
        from .map_file import load_map

        return load_map(path, device=device)

    def merge(self, other: "Mapper") -> "Mapper":
        """A new map holding the evidence of both: evidence (concentration above the prior), weights
        and counts add, touched is or-ed. Exact up to float32 summation order: BKI updates are sums."""
        if self.config != other.config or self.num_classes != other.num_classes:
            raise ValueError("merge: both maps must come from the same method, parameters and class count")
        merged = sum_voxel_arrays([self.voxels()[0], other.voxels()[0]])
        out = Mapper(self.config, self.num_classes, class_names=self.class_names, device=self.device, workers=len(self.shards))
        out.load_voxels(merged)
        out.scans_integrated = self.scans_integrated + other.scans_integrated
        out.points_integrated = self.points_integrated + other.points_integrated
        return out

    def load_voxels(self, voxels: VoxelArrays) -> None:
        """Replace the map's contents with ``voxels`` exactly (file loading, merging)."""
        self.shards[0].load_arrays(voxels)
        for i in range(1, len(self.shards)):
            self.shards[i] = self._new_shard(self.device)
        self._summary_cache = None

    def metadata(self) -> dict:
        return {
            "format": "evsemmap_warp.map",
            "classes": list(self.class_names),
            "num_classes": self.num_classes,
            "method": self.config.method,
            "mapping": self.config.as_dict(),
            "grid_offset_m": self.grid_offset_m,
            "scans_integrated": self.scans_integrated,
            "points_integrated": self.points_integrated,
            "written_by": f"evsemmap_warp {__version__}",
        }

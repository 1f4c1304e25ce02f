"""The Mapper: one voxel map, one integrator, the Dirichlet post-pass, queries and merging.

    mapper = Mapper(load_config([...], method="ebs").mapping, num_classes=9)
    mapper.integrate(points_world, alpha, payload_type="alpha")      # one scan or bin
    result = mapper.query(query_points)                              # label, probs, variance, state
    mapper.save("map.npz")

Input checks live here, before any launch: shapes, NaN/inf, class counts, negative evidence.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from . import __version__
from .config import Compat, MappingConfig, PayloadType
from .integrators import IntegrationStats, KernelIntegrator, SbkiCompatIntegrator, ScanPayload
from .voxel_map import FLAG_TOUCHED, VoxelArrays, VoxelMap


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
    def __init__(
        self,
        config: MappingConfig,
        num_classes: int,
        *,
        class_names: list[str] | tuple[str, ...] | None = None,
        device: str | None = "cpu",
        initial_capacity: int = 1 << 16,
    ):
        self.config = config
        self.num_classes = int(num_classes)
        if class_names is not None and len(class_names) != self.num_classes:
            raise ValueError(f"class_names has {len(class_names)} names for {self.num_classes} classes")
        self.class_names = tuple(class_names) if class_names else tuple(f"class_{i}" for i in range(self.num_classes))
        if config.compat is Compat.SBKI:
            self.integrator = SbkiCompatIntegrator(config)
            grid_offset = SbkiCompatIntegrator.grid_offset_m(config)
        else:
            self.integrator = KernelIntegrator(config)
            grid_offset = 0.0
        self.voxel_map = VoxelMap(
            self.num_classes, config.resolution_m, prior=config.prior, grid_offset_m=grid_offset,
            device=device, initial_capacity=initial_capacity,
        )
        self.scans_integrated = 0
        self.points_integrated = 0
        self._summary_cache: tuple[VoxelArrays, DirichletSummary] | None = None

    @property
    def device(self) -> str:
        return self.voxel_map.device

    @property
    def voxel_count(self) -> int:
        return self.voxel_map.voxel_count

    def integrate(self, points, payload, *, payload_type: PayloadType | str, sensor_origin=None) -> IntegrationStats:
        """Add one scan or bin. points [N, 3] world frame (m); payload [N, K] alpha or
        probabilities, or [N] integer labels, as ``payload_type`` says. An empty scan is a no-op.
        ``sensor_origin`` [3] is needed by the sbki mode (free-space rays)."""
        scan = prepare_payload(points, payload, payload_type, self.num_classes)
        if len(scan.points) == 0:
            return IntegrationStats()
        if isinstance(self.integrator, SbkiCompatIntegrator):
            if sensor_origin is None:
                raise ValueError("sensor_origin: the sbki compatibility mode casts free-space rays from the sensor origin; pass it")
            origin = _validate_points(np.asarray(sensor_origin, dtype=np.float64).reshape(1, 3), "sensor_origin")[0]
            stats = self.integrator.integrate(self.voxel_map, scan, origin)
        else:
            stats = self.integrator.integrate(self.voxel_map, scan)
        self.scans_integrated += 1
        self.points_integrated += len(scan.points)
        self._summary_cache = None
        return stats

    # ------------------------------------------------------------------ reading
    def voxels(self) -> tuple[VoxelArrays, DirichletSummary]:
        """All stored voxels in key order and their post-pass (cached until the next integrate)."""
        if self._summary_cache is None:
            arrays = self.voxel_map.arrays()
            self._summary_cache = (arrays, summarize_dirichlet(self.concentrations(arrays.evidence), arrays.touched))
        return self._summary_cache

    def concentrations(self, evidence: np.ndarray) -> np.ndarray:
        """Dirichlet concentrations alpha = prior + evidence, in float32."""
        return np.float32(self.config.prior) + np.asarray(evidence, dtype=np.float32)

    def voxel_centers(self, index: np.ndarray) -> np.ndarray:
        return (np.asarray(index, dtype=np.float64) + 0.5) * self.config.resolution_m + self.voxel_map.grid_offset_m

    def query(self, points) -> QueryResult:
        """Label, probabilities, variance and state of the voxel containing each point [M, 3]."""
        points = _validate_points(points, "query points")
        slots = self.voxel_map.lookup_points(points)
        found = slots >= 0
        m, k = len(points), self.num_classes
        evidence = np.zeros((m, k), dtype=np.float32)
        touched = np.zeros(m, dtype=bool)
        if found.any():
            evidence[found] = self.voxel_map.evidence.numpy()[slots[found]]
            touched[found] = self.voxel_map.flags.numpy()[slots[found], FLAG_TOUCHED] > 0
        summary = summarize_dirichlet(self.concentrations(evidence), touched)
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
        a, _ = self.voxels()
        b, _ = other.voxels()
        index = np.concatenate([a.index, b.index])
        uniq, inverse = np.unique(index, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        evidence = np.zeros((len(uniq), self.num_classes), dtype=np.float32)
        np.add.at(evidence, inverse, np.concatenate([a.evidence, b.evidence]))
        merged = VoxelArrays(
            index=uniq,
            evidence=evidence,
            weight_sum=np.bincount(inverse, np.concatenate([a.weight_sum, b.weight_sum]), len(uniq)).astype(np.float32),
            weighted_uncertainty_sum=np.bincount(inverse, np.concatenate([a.weighted_uncertainty_sum, b.weighted_uncertainty_sum]), len(uniq)).astype(np.float32),
            hits=np.bincount(inverse, np.concatenate([a.hits, b.hits]), len(uniq)).astype(np.int32),
            touched=np.bincount(inverse, np.concatenate([a.touched, b.touched]).astype(np.int64), len(uniq)) > 0,
        )
        out = Mapper(self.config, self.num_classes, class_names=self.class_names, device=self.device)
        out.voxel_map.load_arrays(merged)
        out.scans_integrated = self.scans_integrated + other.scans_integrated
        out.points_integrated = self.points_integrated + other.points_integrated
        return out

    def metadata(self) -> dict:
        return {
            "format": "evsemmap_warp.map",
            "classes": list(self.class_names),
            "num_classes": self.num_classes,
            "method": self.config.method,
            "mapping": self.config.as_dict(),
            "grid_offset_m": self.voxel_map.grid_offset_m,
            "scans_integrated": self.scans_integrated,
            "points_integrated": self.points_integrated,
            "written_by": f"evsemmap_warp {__version__}",
        }

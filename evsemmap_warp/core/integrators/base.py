"""What every integrator shares: the scan it is handed (``ScanPayload``), what it reports
(``IntegrationStats``), what it declares it needs of a scan (``ScanNeeds``), the protocol it follows
(``Integrator``), the launch its preparation returns (``Launch``, ``launch_step``), and the uncertainty
threshold of the clean mode."""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

import numpy as np
import warp as wp

from ...config import Fusion, MappingConfig, Media, PayloadType, ThresholdScope
from ...kernels import scatter as sc
from ..shards import ShardLanes
from ..voxel_map import VoxelMap


@dataclass
class ScanPayload:
    """A validated scan: points [N, 3] float64 (m, relative to the map origin when an integrator gets them),
    input uncertainty [N] (K / S for alpha, 1 - max p for probabilities, 0 for labels), the ``payload``
    as given ([N] labels, or [N, K] alpha or probabilities, float32 or float64), the class count K, the
    payload rows' sums [N] (float64, None for labels) and ``sensor_origin`` [3] (m, float64, same frame
    as the points): set for the integrators whose ``needs`` read it, None for the others.
    ``probabilities`` [N, K] and ``labels`` [N] are derived when first asked for (the release mode asks
    for the probabilities of the rows it keeps only, ``probability_rows``, and never for labels)."""

    points: np.ndarray
    uncertainty: np.ndarray
    payload: np.ndarray
    num_classes: int
    row_sums: np.ndarray | None = None
    sensor_origin: np.ndarray | None = None
    # The Mapper's check_room(new_voxels): refuses (MemoryBudgetError) a scan whose new voxels its tables'
    # memory budget cannot hold, so that a preparation sized by the voxels it makes asks before allocating for them.
    check_room: Callable[[int], None] | None = None

    @functools.cached_property
    def probabilities(self) -> np.ndarray:
        """[N, K] float64 class probabilities: alpha / S, the probabilities normalised, or one-hot labels."""
        return self.probability_rows(slice(None))

    def probability_rows(self, rows) -> np.ndarray:
        """``probabilities[rows]`` (an index array, a mask or a slice), computed for those rows only."""
        if "probabilities" in self.__dict__:
            return self.probabilities[rows]
        if self.row_sums is None:
            return np.eye(self.num_classes)[self.payload[rows]]
        return np.asarray(self.payload[rows], dtype=np.float64) / self.row_sums[rows][:, None]

    @functools.cached_property
    def labels(self) -> np.ndarray:
        """[N] class ids: the payload itself when it is [N] labels, else its row argmax (computed when
        first asked for)."""
        if self.payload.ndim == 1:
            return self.payload
        if len(self.payload) == 0:
            return np.zeros(0, np.int64)
        return np.argmax(self.payload, axis=1)


@dataclass
class IntegrationStats:
    """What one insertion did: its input points, the points kept (after the uncertainty threshold in the
    clean mode, training points in the sbki mode), the voxel updates made (point-voxel contributions), and
    the threshold u applied (None without one)."""

    input_points: int = 0
    kept_points: int = 0  # after the uncertainty threshold (clean) or as training points (sbki)
    voxel_updates: int = 0
    uncertainty_threshold: float | None = None


def dirichlet_beliefs(probabilities: np.ndarray, uncertainty: np.ndarray) -> np.ndarray:
    """The belief masses [N, K] the Dempster-Shafer fusion takes from Dirichlet points: b_k = (alpha_k - 1) / S
    = p_k - u / K (docs/algorithm.md §3.7), clipped to [0, 1]."""
    return np.clip(probabilities - uncertainty[:, None] / probabilities.shape[1], 0.0, 1.0)


def uncertainty_quantile_mask(uncertainty: np.ndarray, keep_quantile: float) -> tuple[np.ndarray, float]:
    """Keep u <= t with t the floor(N q)-th smallest u (0-based, clamped to N - 1); ties are kept."""
    n = len(uncertainty)
    k = min(int(np.floor(n * keep_quantile)), n - 1)
    threshold = float(np.partition(uncertainty, k)[k])
    return uncertainty <= threshold, threshold


def per_class_quantile_mask(uncertainty: np.ndarray, predicted: np.ndarray, keep_quantile: float) -> np.ndarray:
    """``uncertainty_quantile_mask`` within each predicted class: each class keeps its own surest share."""
    keep = np.ones(len(uncertainty), dtype=bool)
    for label in np.unique(predicted):
        rows = np.flatnonzero(predicted == label)
        keep[rows] = uncertainty_quantile_mask(uncertainty[rows], keep_quantile)[0]
    return keep


def threshold_mask(config: MappingConfig, uncertainty: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The points of one insertion that the uncertainty threshold keeps (``config.threshold_scope``: over the
    insertion, or per ``predicted`` class), and the threshold u when there is one (None per class)."""
    if config.threshold_scope is ThresholdScope.PREDICTED_CLASS:
        return per_class_quantile_mask(uncertainty, predicted, config.keep_quantile), None
    return uncertainty_quantile_mask(uncertainty, config.keep_quantile)


# What an integrator's ``prepare`` returns: the map update itself, launch(shards, lanes) -> stats (whose
# voxel_updates may be PendingUpdates).
Launch = Callable[[list[VoxelMap], Optional[ShardLanes]], IntegrationStats]


class SensorOrigin(enum.Enum):
    """Whether an integrator reads a scan's sensor origin."""

    UNUSED = "unused"  # never read (the scan's ``sensor_origin`` stays None)
    OPTIONAL = "optional"  # read when given (validated); else the map origin stands in
    REQUIRED = "required"  # a scan without one is refused


@dataclass(frozen=True)
class ScanNeeds:
    """What an integrator needs of a scan beyond points and payload, declared so that the Mapper checks
    every scan the same way: the sensor origin (and, when required, why: the refusal's reason), and the
    payload kinds it integrates (others are refused with ``payload_reason``)."""

    sensor_origin: SensorOrigin = SensorOrigin.UNUSED
    sensor_origin_reason: str = ""
    payload_types: frozenset = frozenset(PayloadType)
    payload_reason: str = ""


class Integrator(Protocol):
    """One integration method: made from (config, num_classes) by ``make_integrator``, it holds only its
    parameters. ``needs``: what it reads of a scan; ``grid_offset_m``: where its voxel lattice lies (m;
    0 but for S-CSM's half-shifted cells); ``prepare(scan, device)``: host work on a validated scan in map
    coordinates (no map access), returning the launch that updates the shards."""

    needs: ScanNeeds
    grid_offset_m: float

    def prepare(self, scan: ScanPayload, device: str) -> Launch:
        """Host work on a validated scan in map coordinates, without touching the map; returns the launch
        that updates the shards."""

    def kernel_modules(self, device: str) -> list:
        """The kernel modules its preparation and launches run for a map on ``device`` (modules of
        ``kernels``, or the Warp modules of the kernels its factories make): the Mapper compiles or loads
        them before its first scan, in the calling thread (``Mapper._load_kernels``)."""


def scatter_fusion(config: MappingConfig) -> int:
    """The kernels' fusion constant (``kernels.scatter.FUSION_*``) of the config's ``fusion``."""
    return sc.FUSION_DEMPSTER if config.fusion is Fusion.DEMPSTER else sc.FUSION_BAYES


def preprocesses_on_device(integrator, device: str) -> bool:
    """Whether a compat integrator's preparation runs on the map's ``device`` (its
    ``preprocess_on_device``; None: on a GPU) rather than on the host."""
    if integrator.preprocess_on_device is not None:
        return integrator.preprocess_on_device
    return wp.get_device(device).is_cuda


def integrate_at_launch(integrator, scan: ScanPayload) -> Launch:
    """The launch of an integrator whose host work runs with its kernels (``integrate``): only the scan's
    class probabilities for soft media are derived ahead, here, on the preparing thread (off the launch's
    path when scans are prepared ahead)."""
    if integrator.config.media is not Media.ONEHOT:
        _ = scan.probabilities
    return lambda shards, lanes=None: integrator.integrate(shards, scan, lanes)


def launch_step(stats: IntegrationStats, run=None) -> Launch:
    """The launch that runs ``run(shards, lanes) -> voxel updates`` (nothing when None) into ``stats``."""

    def launch(shards: list[VoxelMap], lanes: ShardLanes | None = None) -> IntegrationStats:
        if run is not None:
            stats.voxel_updates = run(shards, lanes)
        return stats

    return launch


def free_samples_need(method: str) -> ScanNeeds:
    """The needs of a method that adds the sensor origin (and free-space rays) to its training data."""
    return ScanNeeds(SensorOrigin.REQUIRED, f"{method} adds the sensor origin (and free-space rays) as free samples")

"""ConvBKI (docs/compatibility.md §2): per-class compound kernel on a voxel-center stencil, its length
scales (loaded from a file or learned), and the voxelisation that precedes the "convolution".

The dense depthwise conv3d of its authors equals, by linearity, a scatter of every occupied voxel's
summed evidence onto its (2h + 1)^3 neighbours with the weight of their offset (docs/compatibility.md §2.2), so
the map update is the engine's ordinary scatter in stencil mode; training needs the same sum
differentiably, which ``stencil_evidence_at`` computes in PyTorch on a sorted-key lookup.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import files
from ..config import read_yaml_file

INITIAL_LENGTH_M = 0.5  # the authors' initialisation ("max_dist")
LENGTH_RANGE_M = (0.01, 1.0)  # clamped after every training step, as the authors do


@dataclass
class ConvBkiLengths:
    """ConvBKI's per-class length scales: ``horizontal`` and ``vertical`` [K] (m)."""

    horizontal: np.ndarray  # [K] metres
    vertical: np.ndarray  # [K] metres

    def as_dict(self) -> dict:
        """``{"ell_h": [...], "ell_z": [...]}``, as length files store them."""
        return {"ell_h": self.horizontal.tolist(), "ell_z": self.vertical.tolist()}


def default_lengths(num_classes: int) -> ConvBkiLengths:
    """Every class at its authors' initial length (0.5 m), horizontal and vertical."""
    return ConvBkiLengths(np.full(num_classes, INITIAL_LENGTH_M), np.full(num_classes, INITIAL_LENGTH_M))


def load_lengths(path, num_classes: int) -> ConvBkiLengths:
    """ell_h and ell_z [K] from a .pt state dict (BKI_ROS weights), .json, .yaml or .npz."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such ConvBKI length-scale file")
    if path.suffix == ".pt":
        import torch

        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many types for files that are not state dicts
            raise ValueError(f"{path}: not a readable ConvBKI length-scale state dict ({type(exc).__name__})") from None
        if isinstance(data, dict):
            data = {k: np.asarray(v.detach().cpu().numpy() if hasattr(v, "detach") else v, np.float64) for k, v in data.items()}
    elif path.suffix == ".npz":
        try:
            data = dict(np.load(path, allow_pickle=False))
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{path}: not a readable ConvBKI length-scale npz ({type(exc).__name__}: {exc})") from None
    elif path.suffix in (".json", ".yaml", ".yml"):
        data = read_yaml_file(path, "ConvBKI length-scale file")  # JSON is YAML
    else:
        raise ValueError(f"{path}: ConvBKI length scales must be .pt, .npz, .json or .yaml, got {path.suffix!r}")
    if not isinstance(data, dict) or "ell_h" not in data or "ell_z" not in data:
        raise ValueError(f"{path}: expected the keys ell_h and ell_z (one length per class), got {sorted(data) if isinstance(data, dict) else type(data).__name__}")
    lengths = ConvBkiLengths(np.asarray(data["ell_h"], np.float64).ravel(), np.asarray(data["ell_z"], np.float64).ravel())
    for name, values in (("ell_h", lengths.horizontal), ("ell_z", lengths.vertical)):
        if len(values) != num_classes:
            raise ValueError(f"{path}: {name} has {len(values)} values, the map has {num_classes} classes")
        if not np.isfinite(values).all() or (values <= 0).any():
            raise ValueError(f"{path}: {name} must be finite and positive, got {values.tolist()}")
    return lengths


def save_lengths(path, lengths: ConvBkiLengths) -> None:
    """Write ``lengths`` as JSON (``ell_h``, ``ell_z``) to ``path``, atomically."""
    files.write_json_atomically(path, lengths.as_dict(), indent=1)


def _factor(d, length):
    """The sparse kernel with sigma0 = 1, clamped to [0, 1] (numpy or torch)."""
    r = d / length
    if isinstance(r, np.ndarray):
        k = (2 + np.cos(2 * np.pi * r)) * (1 - r) / 3 + np.sin(2 * np.pi * r) / (2 * np.pi)
        return np.where(r < 1, np.clip(k, 0, 1), 0.0)
    import torch

    k = (2 + torch.cos(2 * torch.pi * r)) * (1 - r) / 3 + torch.sin(2 * torch.pi * r) / (2 * torch.pi)
    return torch.where(r < 1, k.clamp(0, 1), torch.zeros_like(k))


def stencil_offsets(half: int) -> np.ndarray:
    """The (2 half + 1)^3 voxel offsets [S, 3] of the stencil, x slowest, z fastest."""
    r = np.arange(-half, half + 1)
    return np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)


def stencil_weights(lengths: ConvBkiLengths, resolution_m: float, half: int) -> np.ndarray:
    """[(2h + 1)^3, K] weight per offset (row order x, y, z as the kernel indexes it) and class:
    k(|(o_x, o_y)| s; l_h,c) * k(|o_z| s; l_z,c), lengths clamped to >= 0.01 m."""
    o = stencil_offsets(half) * resolution_m
    horizontal = np.hypot(o[:, 0], o[:, 1])[:, None]
    vertical = np.abs(o[:, 2])[:, None]
    lh = np.maximum(lengths.horizontal, LENGTH_RANGE_M[0])[None]
    lz = np.maximum(lengths.vertical, LENGTH_RANGE_M[0])[None]
    return _factor(horizontal, lh) * _factor(vertical, lz)


def class_gains(lengths: ConvBkiLengths, resolution_m: float, half: int) -> np.ndarray:
    """[K] each class's kernel mass (the sum of its stencil weights: the evidence one unit of that class's
    probability adds to the map) over the classes' mean. The lengths are learned with a class-weighted loss
    on labelled scans, so a class whose evidence is wrong there (a weak network's sky on vegetation) gets a
    short kernel, hence little mass: these gains carry that class weighting into another kernel
    (ebs-learned, docs/unseen.md)."""
    mass = stencil_weights(lengths, resolution_m, half).sum(axis=0)
    return mass / mass.mean()


def voxelise(points: np.ndarray, evidence: np.ndarray, resolution_m: float, grid_offset_m: float = 0.0):
    """Sum the evidence [N, K] of the points in each voxel: (voxel indices [V, 3], summed [V, K])."""
    from ..voxel_keys import pack_voxel_keys, unpack_voxel_keys

    index = np.floor((np.asarray(points, np.float64) - grid_offset_m) / resolution_m).astype(np.int64)
    # one int64 key per voxel: np.unique on them is far faster than on [N, 3] rows
    keys, inverse = np.unique(pack_voxel_keys(index), return_inverse=True)
    inverse = inverse.ravel()
    evidence = np.asarray(evidence, np.float64)
    summed = np.stack([np.bincount(inverse, weights=evidence[:, c], minlength=len(keys)) for c in range(evidence.shape[1])], axis=1)
    return unpack_voxel_keys(keys), summed.reshape(len(keys), evidence.shape[1])


# --- training (PyTorch) ----------------------------------------------------------------------------
def stencil_evidence_at(query_voxels, voxels, summed, ell_h, ell_z, resolution_m: float, half: int):
    """Differentiable ConvBKI evidence [M, K] at ``query_voxels`` [M, 3] from occupied ``voxels``
    [V, 3] with ``summed`` evidence [V, K]: sum over stencil offsets o of w_c(o) * summed[q - o]."""
    import torch

    offsets = torch.as_tensor(stencil_offsets(half), dtype=torch.int64)
    lo = torch.minimum(voxels.min(0).values, query_voxels.min(0).values) - half - 1
    span = torch.maximum(voxels.max(0).values, query_voxels.max(0).values) + half + 2 - lo

    def pack(v):
        v = v - lo
        return (v[..., 0] * span[1] + v[..., 1]) * span[2] + v[..., 2]

    keys = pack(voxels)
    order = torch.argsort(keys)
    sorted_keys = keys[order]
    sources = pack(query_voxels[:, None, :] - offsets[None])  # [M, O]
    pos = torch.searchsorted(sorted_keys, sources).clamp(max=len(sorted_keys) - 1)
    found = sorted_keys[pos] == sources
    gathered = summed[order][pos] * found[..., None]  # [M, O, K]
    o = offsets.to(summed.dtype) * resolution_m
    weights = _factor(torch.hypot(o[:, 0], o[:, 1])[:, None], ell_h.clamp(min=LENGTH_RANGE_M[0])[None]) * \
        _factor(o[:, 2].abs()[:, None], ell_z.clamp(min=LENGTH_RANGE_M[0])[None])  # [O, K]
    return (gathered * weights[None]).sum(dim=1)


@dataclass
class TrainingWindow:
    """One training window for the lengths: the points [N, 3] (m, world frame) and class probabilities [N, K]
    of its scans, and its last scan's points [M, 3] with their true labels [M], where the loss is taken."""

    points: np.ndarray  # [N, 3] world, all scans of the window
    evidence: np.ndarray  # [N, K] class probabilities (softmax / alpha / S) per point
    query_points: np.ndarray  # [M, 3] the window's last scan
    query_labels: np.ndarray  # [M] ground truth


def train_lengths(windows: list[TrainingWindow], num_classes: int, resolution_m: float, *, half: int = 2, epochs: int = 15,
                  lr: float = 0.007, decay: float = 0.96, prior: float = 1e-6, ignore_class: int = 0, seed: int = 0,
                  progress: bool = True) -> tuple[ConvBkiLengths, list[float]]:
    """Learn ell_h, ell_z per class as the authors do (docs/compatibility.md §2.3): each window's points go
    through one stencil update of an empty map; the normalised concentrations at the last scan's
    points are scored with a class-weighted NLL (weights 1 / ln(frequency), ``ignore_class``
    ignored); Adam, exponential decay, lengths clamped to [0.01, 1.0] m after every step."""
    import torch
    from tqdm import tqdm

    if not windows:
        raise ValueError("ConvBKI training needs at least one window of scans")
    torch.manual_seed(seed)
    counts = np.bincount(np.concatenate([w.query_labels for w in windows]), minlength=num_classes).astype(np.float64)
    frequency = counts / max(counts.sum(), 1)
    # 1 / ln(frequency) read as ENet's 1 / ln(1.02 + frequency), which stays positive and finite
    class_weight = np.where(counts > 0, 1.0 / np.log(1.02 + frequency), 0.0)
    class_weight[ignore_class] = 0.0
    class_weight = torch.as_tensor(class_weight, dtype=torch.float64)
    ell_h = torch.full((num_classes,), INITIAL_LENGTH_M, dtype=torch.float64, requires_grad=True)
    ell_z = torch.full((num_classes,), INITIAL_LENGTH_M, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([ell_h, ell_z], lr=lr, betas=(0.9, 0.999))
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=decay)
    prepared = []
    for w in windows:
        voxels, summed = voxelise(w.points, w.evidence, resolution_m)
        query = np.floor(np.asarray(w.query_points) / resolution_m).astype(np.int64)
        prepared.append((torch.as_tensor(voxels), torch.as_tensor(summed), torch.as_tensor(query), torch.as_tensor(w.query_labels, dtype=torch.int64)))
    history = []
    bar = tqdm(range(epochs), desc="convbki lengths", unit="epoch", disable=not progress)
    for _ in bar:
        losses = []
        for voxels, summed, query, labels in prepared:
            evidence = stencil_evidence_at(query, voxels, summed, ell_h, ell_z, resolution_m, half)
            alpha = evidence + prior
            log_p = torch.log(alpha / alpha.sum(dim=1, keepdim=True))
            loss = torch.nn.functional.nll_loss(log_p, labels, weight=class_weight)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            with torch.no_grad():
                ell_h.clamp_(*LENGTH_RANGE_M)
                ell_z.clamp_(*LENGTH_RANGE_M)
            losses.append(float(loss.detach()))
        scheduler.step()
        history.append(float(np.mean(losses)))
        bar.set_postfix(loss=f"{history[-1]:.4f}")
    return ConvBkiLengths(ell_h.detach().numpy().copy(), ell_z.detach().numpy().copy()), history


def training_windows(sequence, alpha_for_frame, projection, *, window_scans: int = 10, queries_per_window: int = 4000,
                     seed: int = 0) -> list[TrainingWindow]:
    """Windows of ``window_scans`` consecutive scans of a RELLIS-3D-layout ``sequence``: every scan's
    points carry the network's normalised alpha (``alpha_for_frame(frame)`` -> [K, h, w], projected),
    and the last scan's points (up to ``queries_per_window``) their own per-point labels (v3)."""
    from ..classes import original_to_v3_table
    from ..data.world_frame import Placement
    from ..frames import WorldFrame
    from ..geometry.projection import project_frames

    table = original_to_v3_table()
    rng = np.random.default_rng(seed)
    frames = [f for f in sequence.frames if f.point_labels is not None and f.image is not None]
    by_index = {f.index: f for f in frames}
    # Relative to the first scan: windows are local (the kernel is translation-invariant), and learning
    # in float32 stays exact however far the sequence's own frame puts them.
    local = Placement(WorldFrame("first-scan"), sequence.pose(sequence.frames[0]))
    projected = list(project_frames(sequence, frames, alpha_for_frame, projection, local))
    windows = []
    for start in range(0, len(projected) - window_scans + 1, window_scans):
        window = projected[start:start + window_scans]
        last = window[-1]
        truth = table[sequence.read_point_labels(by_index[last.frame_index])[last.scan_rows]]
        pick = rng.permutation(len(last.points))[:queries_per_window]
        values = np.concatenate([w.values for w in window]).astype(np.float64)
        windows.append(TrainingWindow(np.concatenate([w.points for w in window]), values / values.sum(axis=1, keepdims=True),
                                      last.points[pick], truth[pick]))
    return windows

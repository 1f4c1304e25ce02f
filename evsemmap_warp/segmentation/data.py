"""Image datasets for segmentation through one interface: items are (image uint8 [H, W, 3], v3 labels
[H, W]) at the dataset's own size; ``SegmentationTensors`` resizes and normalises them for a network.

* ``SyntheticOffroad``: procedural 2D off-road frames (sky, vegetation on the horizon, grass, a paved
  road, a dirt trail, puddles, objects, void rubble) with the synthetic world's appearance domains,
  seeded per index: cheap frames for quick tests. The synthetic world's rendered camera frames
  (``evsemmap synth``) are read by ``Rellis3DImages`` like real RELLIS-3D.
* ``Rellis3DImages``: ``<seq>/pylon_camera_node/*.jpg`` with ``pylon_camera_node_label_color/*.png``
  (or ``pylon_camera_node_label_id/*.png``) of the same stem, remapped to v3.
* ``RugdImages``: ``RUGD_frames-with-annotations/<scene>/*.png`` with ``RUGD_annotations/<scene>/*.png``
  and ``RUGD_annotations/RUGD_annotation-colormap.txt``, remapped to v3.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..classes import decode_color_labels, palette, read_rugd_colormap, remap_ids
from ..synthetic.appearance import DOMAINS

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CAFFE_MEAN = (103.939 / 255, 116.779 / 255, 123.68 / 255)  # the release's (BGR) means, applied to RGB

V3 = {"void": 0, "sky": 1, "water": 2, "object": 3, "paved": 4, "unpaved": 5, "dirt": 6, "grass": 7, "vegetation": 8}


class SyntheticOffroad:
    """``length`` procedural frames of ``size`` (H, W); frame i is the same for the same seed."""

    num_classes = 9

    def __init__(self, length: int = 200, size: tuple[int, int] = (128, 256), domain: str = "summer", seed: int = 0):
        if domain not in DOMAINS:
            raise ValueError(f"domain must be one of {sorted(DOMAINS)}, got {domain!r}")
        self.length, self.size, self.domain, self.seed = length, tuple(size), domain, seed

    def __len__(self) -> int:
        return self.length

    def name(self, i: int) -> str:
        """Frame ``i``'s name, unique per domain and seed."""
        return f"synthetic_{self.domain}_{self.seed}_{i:05d}"

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        if not 0 <= i < self.length:
            raise IndexError(i)
        rng = np.random.default_rng([self.seed, i])
        h, w = self.size
        y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
        label = np.full((h, w), V3["grass"], np.int64)
        horizon = 0.35 + 0.1 * rng.random() + 0.03 * np.sin(2 * np.pi * (x * rng.uniform(1, 3) + rng.random()))
        label[y < horizon] = V3["sky"]
        for _ in range(rng.integers(3, 8)):  # tree crowns and bushes across the horizon
            cx, cy, rx, ry = rng.random(), horizon.mean() + rng.uniform(-0.1, 0.05), rng.uniform(0.05, 0.2), rng.uniform(0.05, 0.2)
            label[((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2 < 1] = V3["vegetation"]
        ground = y >= horizon
        vx = rng.uniform(0.3, 0.7)  # the road or trail runs to a vanishing point on the horizon
        half_width = rng.uniform(0.15, 0.35) * (y - horizon) / (1 - horizon)
        lane = ground & (np.abs(x - (vx + (0.5 - vx) * (y - horizon) / (1 - horizon))) < half_width)
        label[lane] = V3["paved"] if rng.random() < 0.5 else V3["unpaved"]
        for cls, count in (("dirt", rng.integers(0, 3)), ("water", rng.integers(0, 3)), ("void", rng.integers(0, 2))):
            for _ in range(count):
                cx, cy = rng.uniform(0.1, 0.9), rng.uniform(horizon.mean() + 0.1, 0.95)
                rx, ry = rng.uniform(0.04, 0.15), rng.uniform(0.02, 0.06)
                label[ground & (((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2 < 1)] = V3[cls]
        for _ in range(rng.integers(0, 4)):  # poles, barrels, boxes
            cx, bottom = rng.uniform(0.05, 0.95), rng.uniform(horizon.mean() + 0.05, 0.9)
            half, height = rng.uniform(0.01, 0.05), rng.uniform(0.05, 0.3)
            label[(np.abs(x - cx) < half) & (y < bottom) & (y > bottom - height)] = V3["object"]
        return self._render(label, rng, y), label

    def _render(self, label: np.ndarray, rng, y: np.ndarray) -> np.ndarray:
        style = DOMAINS[self.domain]
        table = np.zeros((9, 3))
        for name, cls in V3.items():
            table[cls] = style[name]
        h, w = label.shape
        coarse = rng.normal(0, 1, (h // 8 + 1, w // 8 + 1, 3)).repeat(8, 0).repeat(8, 1)[:h, :w]
        image = table[label] * (1 + 0.08 * coarse) + rng.normal(0, 12, (h, w, 3))  # texture + sensor noise
        image *= style["light"] * (0.85 + 0.3 * (1 - y))[..., None]  # light falls off towards the bottom
        return np.clip(image, 0, 255).astype(np.uint8)


def _open_rgb(path: Path) -> np.ndarray:
    with Image.open(path) as img:
        if img.mode not in ("RGB", "RGBA") or (img.mode == "RGBA" and np.asarray(img)[..., 3].min() < 255):
            raise ValueError(f"{path}: expected an RGB image, got mode {img.mode}")
        return np.asarray(img.convert("RGB"))


def _pair_check(image: np.ndarray, label: np.ndarray, image_path, label_path) -> None:
    if image.shape[:2] != label.shape[:2]:
        raise ValueError(f"{image_path} is {image.shape[1]}x{image.shape[0]} but its label {label_path} is {label.shape[1]}x{label.shape[0]}")


class Rellis3DImages:
    """RELLIS-3D camera images with their 2D labels (color or id images), remapped to the 9 mapping classes:
    one sequence folder, or every sequence under a root (``sequences`` picks some). Items are (image [H,
    W, 3] uint8, labels [H, W]); unknown colors or ids, non-RGB images and label images of another size
    raise ValueError naming the file."""

    num_classes = 9

    def __init__(self, root, sequences: list[str] | None = None):
        root = Path(root)
        if (root / "pylon_camera_node").is_dir():  # the root is one sequence
            seq_dirs = [root]
        elif sequences:
            seq_dirs = [root / s for s in sequences]
        else:
            seq_dirs = sorted(p for p in root.iterdir() if (p / "pylon_camera_node").is_dir())
        self.items = []
        for seq in seq_dirs:
            for image in sorted((seq / "pylon_camera_node").glob("*.jpg")) + sorted((seq / "pylon_camera_node").glob("*.png")):
                color = seq / "pylon_camera_node_label_color" / f"{image.stem}.png"
                ids = seq / "pylon_camera_node_label_id" / f"{image.stem}.png"
                if color.exists() or ids.exists():
                    self.items.append((image, color if color.exists() else ids, color.exists()))
        if not self.items:
            raise ValueError(f"{root}: no RELLIS-3D frames with labels (expected <seq>/pylon_camera_node/*.jpg and pylon_camera_node_label_color/*.png)")
        self.colors = palette("rellis3d_colors")

    def __len__(self) -> int:
        return len(self.items)

    def name(self, i: int) -> str:
        """Item ``i``'s name: its image file's stem."""
        return self.items[i][0].stem

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        image_path, label_path, is_color = self.items[i]
        image = _open_rgb(image_path)
        with Image.open(label_path) as img:
            raw = np.asarray(img.convert("RGB") if is_color else img)
        original = decode_color_labels(raw, self.colors, str(label_path)) if is_color else raw
        if not is_color and original.ndim != 2:
            raise ValueError(f"{label_path}: an id label image must have one channel, got shape {list(original.shape)}")
        _pair_check(image, original, image_path, label_path)
        return image, remap_ids(original, str(label_path))


class SequenceImages:
    """The labelled camera frames of an opened sequence (a robot log, or a folder): what
    Rellis3DImages gives for a folder of files, read through the sequence's own readers."""

    num_classes = 9

    def __init__(self, sequence):
        self.sequence = sequence
        self.frames = [f for f in sequence.frames if f.label_image is not None]
        if not self.frames:
            raise ValueError(f"{sequence.root}: no camera frame has a 2D label image to train on")

    def __len__(self) -> int:
        return len(self.frames)

    def name(self, i: int) -> str:
        """Item ``i``'s name: ``frameNNNNNN`` of its frame index."""
        return f"frame{self.frames[i].index:06d}"

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        frame = self.frames[i]
        return self.sequence.read_image(frame), remap_ids(self.sequence.read_label_ids(frame), f"{self.sequence.root} frame {frame.index}")


class RugdImages:
    """RUGD frames with their color annotations, remapped to the 9 mapping classes (``scenes`` picks some).
    Raises ValueError when the root lacks RUGD's two folders or holds no annotated frames."""

    num_classes = 9

    def __init__(self, root, scenes: list[str] | None = None):
        root = Path(root)
        frames, annotations = root / "RUGD_frames-with-annotations", root / "RUGD_annotations"
        if not frames.is_dir() or not annotations.is_dir():
            raise ValueError(f"{root}: expected RUGD_frames-with-annotations/ and RUGD_annotations/")
        scene_dirs = [frames / s for s in scenes] if scenes else sorted(p for p in frames.iterdir() if p.is_dir())
        self.items = [(img, annotations / img.parent.name / img.name) for d in scene_dirs for img in sorted(d.glob("*.png"))]
        self.items = [(i, a) for i, a in self.items if a.exists()]
        if not self.items:
            raise ValueError(f"{root}: no RUGD frames with annotations")
        colormap = annotations / "RUGD_annotation-colormap.txt"
        self.colors = read_rugd_colormap(colormap) if colormap.exists() else palette("rugd_colors")

    def __len__(self) -> int:
        return len(self.items)

    def name(self, i: int) -> str:
        """Item ``i``'s name: its image file's stem."""
        return self.items[i][0].stem

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        image_path, label_path = self.items[i]
        image = _open_rgb(image_path)
        with Image.open(label_path) as img:
            original = decode_color_labels(np.asarray(img.convert("RGB")), self.colors, str(label_path))
        _pair_check(image, original, image_path, label_path)
        return image, remap_ids(original, str(label_path))


def resize_pair(image: np.ndarray, label: np.ndarray | None, size: tuple[int, int]):
    """One resize path for training and inference: antialiased bilinear for the uint8 image,
    nearest for labels (docs/compatibility.md §5.1)."""
    h, w = size
    out = np.asarray(Image.fromarray(image).resize((w, h), Image.BILINEAR, reducing_gap=None)) if image.shape[:2] != (h, w) else image
    if label is None:
        return out, None
    lab = label if label.shape == (h, w) else np.asarray(Image.fromarray(label.astype(np.int32)).resize((w, h), Image.NEAREST)).astype(np.int64)
    return out, lab


def to_tensor(image: np.ndarray, mean, std) -> torch.Tensor:
    """An RGB image [H, W, 3] uint8 as a normalised float tensor [3, H, W] ((x / 255 - mean) / std); raises
    ValueError for any other shape or dtype."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected uint8 RGB images [H, W, 3], got {image.dtype} {list(image.shape)}")
    t = torch.from_numpy(np.array(image)).permute(2, 0, 1).float() / 255.0  # a copy: inputs may be read-only
    return (t - torch.tensor(mean)[:, None, None]) / torch.tensor(std)[:, None, None]


class SegmentationTensors(torch.utils.data.Dataset):
    """(normalised image [3, H, W], labels [H, W]) at the network's input size."""

    def __init__(self, source, indices, size: tuple[int, int], mean=IMAGENET_MEAN, std=IMAGENET_STD):
        self.source, self.indices, self.size, self.mean, self.std = source, list(indices), tuple(size), mean, std

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int):
        image, label = self.source[self.indices[k]]
        image, label = resize_pair(image, label, self.size)
        return to_tensor(image, self.mean, self.std), torch.from_numpy(label.astype(np.int64))

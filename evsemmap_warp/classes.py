"""Class sets, colors and id remapping, read from the data files in ``configs/classes/``.

``remap_v3.yaml`` holds the 9 mapping classes (docs/algorithm.md §5.1) and the original-id -> v3 table shared by
RELLIS-3D and RUGD (docs/algorithm.md §5.2); ``rellis3d_colors.yaml`` and ``rugd_colors.yaml`` hold the color-label
palettes (docs/algorithm.md §5.2). Unknown colors and ids are errors that name the file and the values.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np
import yaml


def classes_dir() -> Path:
    """The folder of the class-set files (``configs/classes/``, installed as
    ``evsemmap_warp.configs.classes``)."""
    return Path(str(resources.files("evsemmap_warp.configs") / "classes"))


@cache
def _read(name: str) -> dict:
    return yaml.safe_load((classes_dir() / f"{name}.yaml").read_text())


@dataclass(frozen=True)
class ClassSet:
    """A class set: the class ``names`` in id order (id = position) and their display ``colors`` [K, 3] uint8
    RGB."""
    names: tuple[str, ...]
    colors: np.ndarray  # [K, 3] uint8

    def __len__(self) -> int:
        return len(self.names)


def class_set(name: str = "remap_v3") -> ClassSet:
    """The class set ``configs/classes/NAME.yaml`` (default ``remap_v3``, the 9 mapping classes); raises
    ValueError when its ids are not 0..K-1."""
    entries = sorted(_read(name)["classes"], key=lambda e: e["id"])
    if [e["id"] for e in entries] != list(range(len(entries))):
        raise ValueError(f"configs/classes/{name}.yaml: class ids must be 0..K-1")
    return ClassSet(tuple(e["name"] for e in entries), np.array([e["rgb"] for e in entries], np.uint8))


def named_colors() -> dict[str, tuple[int, int, int]]:
    """Color of every class name defined in configs/classes (for displays)."""
    out = {}
    for path in sorted(classes_dir().glob("*.yaml")):
        for entry in _read(path.stem).get("classes", []):
            out.setdefault(entry["name"].lower(), tuple(entry["rgb"]))
    return out


def original_to_v3_table() -> np.ndarray:
    """[256] int16 lookup: original RELLIS-3D/RUGD id -> v3 id, -1 where the id is not in the table."""
    table = np.full(256, -1, np.int16)
    for original, v3 in _read("remap_v3")["original_to_v3"].items():
        table[int(original)] = int(v3)
    return table


def palette(name: str) -> dict[tuple[int, int, int], int]:
    """RGB -> original id for a color-label palette ('rellis3d_colors' or 'rugd_colors')."""
    return {tuple(e["rgb"]): int(e["id"]) for e in _read(name)["colors"]}


def read_rugd_colormap(path) -> dict[tuple[int, int, int], int]:
    """RUGD_annotation-colormap.txt: lines 'id name R G B'."""
    out = {}
    try:
        text = Path(path).read_text()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (a RUGD color map was expected)") from None
    for n, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 5:
            raise ValueError(f"{path}:{n}: expected 'id name R G B', got {line!r}")
        out[tuple(int(v) for v in parts[2:])] = int(parts[0])
    return out


def remap_ids(ids: np.ndarray, source: str) -> np.ndarray:
    """Original ids -> v3 ids; unknown ids raise, naming ``source`` and the ids."""
    ids = np.asarray(ids)
    table = original_to_v3_table()
    bad = (ids < 0) | (ids > 255)
    mapped = np.where(bad, -1, table[np.clip(ids, 0, 255)])
    if (mapped < 0).any():
        unknown = sorted(set(np.unique(ids[mapped < 0]).tolist()))
        raise ValueError(f"{source}: label ids {unknown[:10]} are not in the RELLIS-3D/RUGD ontology table (configs/classes/remap_v3.yaml)")
    return mapped.astype(np.int64)


def decode_color_labels(rgb: np.ndarray, colors: dict[tuple[int, int, int], int], source: str) -> np.ndarray:
    """[H, W, 3] color label image -> [H, W] original ids; colors not in the palette raise."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        raise ValueError(f"{source}: a color label image must be [H, W, 3], got {list(rgb.shape)}")
    packed = (rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2].astype(np.int64)
    keys = np.array([(r << 16) | (g << 8) | b for r, g, b in colors], np.int64)
    values = np.array(list(colors.values()), np.int64)
    order = np.argsort(keys)
    keys, values = keys[order], values[order]
    pos = np.clip(np.searchsorted(keys, packed), 0, len(keys) - 1)
    known = keys[pos] == packed
    if not known.all():
        unknown = np.unique(packed[~known])[:5]
        shown = [((int(k) >> 16) & 255, (int(k) >> 8) & 255, int(k) & 255) for k in unknown]
        raise ValueError(f"{source}: {int((~known).sum())} pixels have colors that are not in the label palette, e.g. {shown}")
    return values[pos]

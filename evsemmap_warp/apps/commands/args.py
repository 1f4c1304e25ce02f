"""The argument types and flag groups the ``evsemmap`` commands share: each type answers a bad value with
argparse's one-line usage error (exit code 2)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ... import limits


def port(text: str) -> int:
    """A TCP port, 1..65535."""
    value = whole_number(text)
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port {value} is outside 1..65535")
    return value


def whole_number(text: str) -> int:
    """A whole number."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def non_negative(text: str) -> int:
    """A whole number >= 0."""
    value = whole_number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative")
    return value


def positive(text: str) -> int:
    """A whole number >= 1."""
    value = whole_number(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be at least 1")
    return value


def _limit_type(check, flag: str):
    """An argparse type from a ``limits`` check: the flag's value as the check returns it, or argparse's
    one-line usage error with the check's message (the same limit the writers and readers hold to)."""
    def parse(text: str):
        try:
            return check(text if check is limits.parse_memory_size else whole_number(text), flag)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return parse


TILE_VOXELS = _limit_type(limits.check_tile_voxels, "--tile-voxels")
CHUNK_FRAMES = _limit_type(limits.check_chunk_frames, "--chunk-frames")
MAX_MEMORY = _limit_type(limits.parse_memory_size, "--max-memory")
MAX_MEMORY_HELP = ("the memory the map's voxel table may take (512M, 4G; with batch: each worker's); a scan that would grow it "
                   "further is refused (default: the memory available when the table grows)")


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be a finite number > 0")
    return value


def add_frame_args(p) -> None:
    """``--frame`` and ``--crs``: the world frame a command maps or places scans in."""
    p.add_argument("--frame", default=None, help="the world frame to map in (dataset.frame): by default the data's own (a log's fixed "
                                                 "frame, a folder's poses.txt frame, point files' frame); a NAME names a folder's poses "
                                                 "frame (a log's must be its fixed frame); first-scan: relative to the first scan's pose")
    p.add_argument("--crs", default=None, help="EPSG code of georeferenced coordinates, e.g. EPSG:32617 (dataset.crs); exports carry it")


def add_dataset_args(p, frames: int, seed: int, size_help: str) -> None:
    """The segmentation commands' dataset flags (``segmentation_source`` reads them); ``frames``, ``seed``: the command's defaults."""
    p.add_argument("--dataset", choices=("synthetic", "rellis3d", "rugd"), default="synthetic")
    p.add_argument("--data", type=Path, help="dataset root (RELLIS-3D sequences folder or RUGD root)")
    p.add_argument("--synthetic-frames", type=positive, default=frames)
    p.add_argument("--input-size", type=positive, nargs=2, default=[128, 256], metavar=("H", "W"), help=size_help)
    p.add_argument("--domain", default="summer", help="synthetic appearance domain: summer, autumn, dusk")
    p.add_argument("--seed", type=int, default=seed, help="seed of the split, the initialisation and synthetic frames")


def segmentation_source(args):
    """The images the ``add_dataset_args`` flags name: synthetic frames, RELLIS-3D or RUGD."""
    from ...segmentation.data import Rellis3DImages, RugdImages, SyntheticOffroad

    if args.dataset == "synthetic":
        return SyntheticOffroad(args.synthetic_frames, tuple(args.input_size), domain=args.domain, seed=args.seed)
    if args.data is None:
        raise ValueError(f"--data DIR is needed for the {args.dataset} dataset")
    return (Rellis3DImages if args.dataset == "rellis3d" else RugdImages)(args.data)

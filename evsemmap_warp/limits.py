"""Every limit a map, a store or a run is held to, defined once: the voxel key range, the tile size,
the chunk size, the memory a map's voxel table may take and how long a batch run waits. The writers,
the readers and the command line's flags all check through the functions here, so a writer never
accepts what a reader refuses.

Each ``check_*`` raises ValueError naming ``what`` (a flag, a file's key) and the range; the command
line turns them into argparse types (``apps/commands/args.py``)."""

from __future__ import annotations

import numbers
import os
import re
import resource
from pathlib import Path

from .kernels.hash_table import INDEX_LIMIT

__all__ = ["CHUNK_TIMEOUT_S", "INDEX_LIMIT", "MAX_FOLD_LANE_RESTARTS", "MAX_TILE_VOXELS", "MIN_CHUNK_FRAMES", "MemoryBudgetError", "RAY_CONNECT_TIMEOUT_S",
           "available_memory", "check_chunk_frames", "check_memory_bytes", "check_tile_voxels", "describe_bytes", "parse_memory_size"]

# A voxel index lies in [-INDEX_LIMIT, INDEX_LIMIT) on every axis (21 bits a key field, kernels/hash_table.py),
# so a tile wider than INDEX_LIMIT voxels holds nothing a tile of INDEX_LIMIT cannot. The limit also keeps the
# store's tile-local arithmetic exact: a voxel's index inside its tile fits the codec's uint32, and its
# tile-local key (x t + y) t + z stays below 2^63 (at t = 2^32 it wrapped: tile_codec read its own file back
# as "voxels out of key order").
MAX_TILE_VOXELS = INDEX_LIMIT
MIN_CHUNK_FRAMES = 1
# How long a batch run's --ray-address host:port may take to accept a connection (--ray-connect-timeout-s): ray.init
# retries an address where nothing answers for many minutes ("Failed to connect to GCS").
RAY_CONNECT_TIMEOUT_S = 30.0
# How long a batch run waits for some chunk to finish before it stops as stuck (--chunk-timeout-s: a worker or node
# that hangs); a chunk of the default size maps in seconds, one labelled by a network on the CPU in minutes.
CHUNK_TIMEOUT_S = 3600.0
# How often a batch run on Ray starts a fold lane again, its node lost, before it stops (a rerun resumes): each
# restart sends the lane's tiles' partials since their last write again (ray_fold.RayFoldLanes).
MAX_FOLD_LANE_RESTARTS = 8


def _whole_number(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{what} {value!r} must be a whole number")
    return int(value)


def check_tile_voxels(value, what: str = "tile_voxels") -> int:
    """``value`` as a tile edge in voxels, or ValueError unless it lies in 1..MAX_TILE_VOXELS."""
    value = _whole_number(value, what)
    if not 1 <= value <= MAX_TILE_VOXELS:
        raise ValueError(f"{what} {value} must lie in 1..{MAX_TILE_VOXELS}")
    return value


def check_chunk_frames(value, what: str = "chunk_frames") -> int:
    """``value`` as frames per batch chunk, or ValueError unless it is at least MIN_CHUNK_FRAMES."""
    value = _whole_number(value, what)
    if value < MIN_CHUNK_FRAMES:
        raise ValueError(f"{what} {value} must be at least {MIN_CHUNK_FRAMES}")
    return value


class MemoryBudgetError(ValueError):
    """A voxel table refused to grow past its memory budget; the message names the budget and the need."""


_SIZE = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*([kmgt]?)i?b?\s*$", re.IGNORECASE)
_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def parse_memory_size(text: str, what: str = "max_memory") -> int:
    """Bytes of a size written as a number with an optional unit (binary: 512M, 4G, 1.5GiB, 4096): ValueError
    for anything else or for less than 1 MiB (no map fits in less)."""
    match = _SIZE.match(str(text))
    if not match:
        raise ValueError(f"{what} {text!r} is not a size (a number of bytes, or with a unit: 512M, 4G)")
    return check_memory_bytes(int(float(match.group(1)) * _UNITS[match.group(2).lower()]), what)


def check_memory_bytes(value, what: str = "max_memory") -> int:
    """``value`` as a memory budget in bytes, or ValueError below 1 MiB."""
    value = _whole_number(value, what)
    if value < 2**20:
        raise ValueError(f"{what} {value} bytes is below 1 MiB: no voxel table fits")
    return value


def describe_bytes(count: float) -> str:
    """A byte count for messages: 13.0 GB, 512 MB (binary units)."""
    return f"{count / 2**30:.1f} GB" if count >= 2**30 else f"{count / 2**20:.0f} MB"


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_room() -> int | None:
    """Bytes left under this process's cgroup (v2) memory limit, None where it has none."""
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit == "max":
            return None
        return max(0, int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        return None


def _address_space_room() -> int | None:
    """Bytes of address space left under RLIMIT_AS (``ulimit -v``), None where it is unlimited."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY:
        return None
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return max(0, limit - int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    return limit


def available_memory() -> int:
    """Bytes this process may still allocate: the system's available memory (MemAvailable; the free
    physical pages where that is not known), less where a cgroup limit or RLIMIT_AS leaves less."""
    have = _meminfo_available()
    if have is None:
        have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    for room in (_cgroup_room(), _address_space_room()):
        if room is not None:
            have = min(have, room)
    return have

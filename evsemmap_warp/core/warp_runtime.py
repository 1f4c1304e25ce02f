"""Warp start-up in one place: a predictable kernel cache, quiet logs, device choice.

Kernel inputs are made from numpy with ``wp.array(..., copy=False)`` throughout: on the CPU the kernels then
read numpy's memory in place (Warp keeps a reference to it) instead of a copy per launch; on a GPU Warp copies
them, as it must, except a scan's inputs to the clean-mode kernels, which a shard stages through pinned
buffers it keeps (``core._staging``).
"""

from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path

_initialised = False
_device_locks: dict[str, threading.RLock] = {}
_device_locks_made = threading.Lock()


def default_kernel_cache_dir() -> Path:
    """WARP_CACHE_PATH when set, else ~/.cache/evsemmap_warp/warp (XDG_CACHE_HOME honoured)."""
    if os.environ.get("WARP_CACHE_PATH"):
        return Path(os.environ["WARP_CACHE_PATH"])
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "evsemmap_warp" / "warp"


def init_warp():
    """Import and initialise Warp once; returns the ``warp`` module."""
    global _initialised
    import warp as wp

    if not _initialised:
        if not os.environ.get("WARP_CACHE_PATH") and wp.config.kernel_cache_dir is None:
            wp.config.kernel_cache_dir = str(default_kernel_cache_dir() / wp.config.version)
        wp.config.log_level = wp.LOG_WARNING
        wp.init()
        _initialised = True
    return wp


def resolve_device(device: str | None) -> str:
    """'cpu', 'cuda', 'cuda:N', or None/'auto' for the first CUDA device when present, else 'cpu'."""
    wp = init_warp()
    if device in (None, "auto"):
        device = "cuda:0" if wp.is_cuda_available() else "cpu"
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"device {device!r} was asked for, but Warp sees no CUDA device here; use device='cpu'")
    if device == "cuda":
        device = "cuda:0"
    if device != "cpu" and not device.startswith("cuda:"):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {device!r}")
    if device != "cpu" and wp.get_device(device).arch < 70:
        # The hash table's readers wait for a row another thread of their warp publishes (kernels.hash_table.slot_row).
        raise ValueError(f"device {device!r} has compute capability {wp.get_device(device).arch / 10:.1f}; the map's kernels need 7.0 or newer")
    return device


def device_calls(device: str):
    """The lock a thread holds while it calls Warp for ``device``, when that is a GPU (a null context on
    the CPU): a GPU map prepares its next scan on a thread while the main thread launches, and Warp's CUDA
    calls are not safe from two threads at once (``array.numpy()`` switches the device's current stream
    for its copy; the radix sort keeps one scratch buffer per stream, unlocked). Re-entrant: a launch that
    rebuilds its scan's inputs takes it again. It orders the calls, not the GPU's work: kernels a call
    queued may still run after it is released."""
    if device == "cpu":
        return contextlib.nullcontext()
    with _device_locks_made:
        return _device_locks.setdefault(device, threading.RLock())

"""A shard's uploads of scan inputs to its device, through buffers it keeps from scan to scan.

On the CPU a kernel reads numpy's memory in place (``wp.array(..., copy=False)``): nothing is copied or
allocated. On a GPU each input has a device buffer and two pinned host buffers, used in turn: the host
writes a scan's values into one pinned buffer and the copy to the device is queued on the device's stream
without waiting (copies from pinned memory are asynchronous), so the host goes on to the next scan's work
while this scan's copies and kernels run. Before a pinned buffer is written again the host waits for the
event recorded after its last copy; kernels on the same stream run after the copies they read. Buffers
grow by half again when a scan outgrows them, so a warm map allocates nothing per scan.

``reuse_on_cpu`` makes the CPU take the GPU's path without pinning (device buffers reused, the values
copied in): the tests use it to check that path's buffers and results on the CPU backend.
"""

from __future__ import annotations

import numpy as np
import warp as wp

_GROWTH = 1.5


class Staging:
    """Uploads of named scan inputs (one buffer set per name) to ``device``."""

    def __init__(self, device: str, *, reuse_on_cpu: bool = False):
        self.device = device
        self.cuda = wp.get_device(device).is_cuda
        self.reuse = self.cuda or reuse_on_cpu
        self._device_buffers: dict[str, wp.array] = {}
        self._pinned: dict[str, list[wp.array | None]] = {}
        self._copied: dict[str, list[wp.Event | None]] = {}
        self._turn: dict[str, int] = {}

    def upload(self, name: str, values: np.ndarray, dtype, numpy_dtype) -> wp.array:
        """``values`` as a device array of their length: rows of a vector ``dtype`` (a row's columns its
        components), or of a scalar ``dtype`` (an [N, K] table stays 2-D); on the CPU without
        ``reuse_on_cpu``, numpy's memory itself."""
        values = np.ascontiguousarray(values, dtype=numpy_dtype)
        if not self.reuse:
            return wp.array(values, dtype=dtype, device=self.device, copy=False)
        n = len(values)
        if n == 0:
            return wp.empty(0, dtype=dtype, device=self.device)
        row_shape = () if wp.types.type_is_vector(dtype) else values.shape[1:]
        target = self._grown(self._device_buffers, name, n, row_shape, dtype, self.device, pinned=False)
        if not self.cuda:
            source = wp.array(values, dtype=dtype, device="cpu", copy=False)
            wp.copy(target, source, count=source.size)
            return target[:n]
        turn = self._turn[name] = 1 - self._turn.get(name, 1)
        pinned = self._pinned.setdefault(name, [None, None])
        copied = self._copied.setdefault(name, [None, None])
        if copied[turn] is not None:
            wp.synchronize_event(copied[turn])  # the last copy out of this pinned buffer has been made
        host = self._grown(pinned, turn, n, row_shape, dtype, "cpu", pinned=True)
        host_rows = host.numpy()[:n]
        host_rows[...] = values.reshape(host_rows.shape)
        wp.copy(target, host, count=target[:n].size)
        copied[turn] = wp.get_stream(self.device).record_event()
        return target[:n]

    @staticmethod
    def _grown(buffers, key, n: int, row_shape: tuple, dtype, device: str, *, pinned: bool) -> wp.array:
        """buffers[key] (a dict or a list), replaced by a larger one when it holds fewer than n rows of
        row_shape."""
        buffer = buffers[key] if isinstance(buffers, list) else buffers.get(key)
        if buffer is None or buffer.shape[0] < n or buffer.shape[1:] != row_shape:
            buffer = wp.empty((_capacity(n, buffer), *row_shape), dtype=dtype, device=device, pinned=pinned)
            buffers[key] = buffer
        return buffer


def _capacity(n: int, old: wp.array | None) -> int:
    return max(n, int((0 if old is None else old.shape[0]) * _GROWTH))

"""numpy twin of ``kernels/microbench.py``."""

import numpy as np


def stream_copy(src: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.microbench.stream_copy``: a copy of ``src``."""
    return src.copy()


def add_rows64(rows: np.ndarray, weights: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.microbench.add_rows64``: ``data`` with weights[t] added to every column of row
    rows[t], in float64."""
    out = np.array(data, dtype=np.float64)
    np.add.at(out, rows, np.asarray(weights, np.float64)[:, None])
    return out


def add_rows32(rows: np.ndarray, weights: np.ndarray, data: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.microbench.add_rows32``: the same in float32."""
    out = np.array(data, dtype=np.float32)
    np.add.at(out, rows, np.asarray(weights, np.float32)[:, None])
    return out


def radix_scatter_form(values: np.ndarray, shift: int, digit_bits: int) -> np.ndarray:
    """Twin of every form of ``kernels.microbench.radix_scatter_form``: one radix pass, ``values`` stably
    ordered by their digit (bits shift ... shift + digit_bits - 1), as ``radix_scatter`` leaves them when
    next_slot starts at the digits' exclusive prefix sum."""
    values = np.asarray(values, np.int64)
    digits = (values >> shift) & ((1 << digit_bits) - 1)
    return values[np.argsort(digits, kind="stable")]

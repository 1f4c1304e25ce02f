"""numpy twin of ``kernels/microbench.py``."""

import numpy as np


def stream_copy(src: np.ndarray) -> np.ndarray:
    return src.copy()


def add_rows64(rows: np.ndarray, weights: np.ndarray, data: np.ndarray) -> np.ndarray:
    out = np.array(data, dtype=np.float64)
    np.add.at(out, rows, np.asarray(weights, np.float64)[:, None])
    return out


def add_rows32(rows: np.ndarray, weights: np.ndarray, data: np.ndarray) -> np.ndarray:
    out = np.array(data, dtype=np.float32)
    np.add.at(out, rows, np.asarray(weights, np.float32)[:, None])
    return out

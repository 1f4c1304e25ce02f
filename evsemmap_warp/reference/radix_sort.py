"""numpy twin of ``evsemmap_warp.kernels.radix_sort``."""

from __future__ import annotations

import numpy as np


def _digits(values, shift: int, digit_bits: int) -> np.ndarray:
    return (np.asarray(values, np.int64) >> shift) & ((1 << digit_bits) - 1)


def digit_histograms(values: np.ndarray, lowest_bit: int, digit_bits: int, passes: int) -> np.ndarray:
    """[passes, 2^digit_bits] counts of each pass's digit."""
    return np.stack([np.bincount(_digits(values, lowest_bit + p * digit_bits, digit_bits), minlength=1 << digit_bits)
                     for p in range(passes)]).reshape(passes, 1 << digit_bits)


def radix_scatter(values: np.ndarray, shift: int, digit_bits: int, next_slot: np.ndarray) -> np.ndarray:
    """One pass, literally: each value in input order to the next free slot of its digit's range."""
    out = np.empty_like(np.asarray(values, np.int64))
    slot = np.array(next_slot, dtype=np.int64)
    for value, digit in zip(values, _digits(values, shift, digit_bits)):
        out[slot[digit]] = value
        slot[digit] += 1
    return out


def radix_sort(values: np.ndarray, lowest_bit: int, digit_bits: int, passes: int) -> np.ndarray:
    """The values stably sorted by bits lowest_bit .. lowest_bit + passes * digit_bits."""
    values = np.asarray(values, np.int64)
    for p in range(passes):
        values = values[np.argsort(_digits(values, lowest_bit + p * digit_bits, digit_bits), kind="stable")]
    return values

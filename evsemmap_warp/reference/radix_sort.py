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


def sorted_runs(packed: np.ndarray, position_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``sorted_runs``: the positions of sorted packed values (key << position_bits | position) and
    the starts of their runs of equal keys, then the value count [R + 1] (int64)."""
    packed = np.asarray(packed, np.int64)
    keys = packed >> position_bits
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])[:len(packed)] if len(packed) else np.zeros(0, np.int64)
    return packed & ((1 << position_bits) - 1), np.r_[starts, len(packed)].astype(np.int64)

"""tools/terrain_truth.py's measures (docs/terrain.md §7): the error rate by decile of an uncertainty band."""

from __future__ import annotations

import sys

import numpy as np
from conftest import REPO

sys.path.insert(0, str(REPO / "tools"))
import terrain_truth  # noqa: E402


def test_tied_band_values_share_their_error_rate_whatever_the_cells_order():
    # a band that is 0 in 90 % of the cells, its errors first in the cells' order: the ties must not rank them
    values = np.r_[np.zeros(900), np.linspace(0.1, 0.9, 100)]
    correct = np.ones(1000, bool)
    correct[:9] = False  # 1 % of the tied cells
    correct[900::2] = False  # half of the cells of the top decile
    rates, edges = terrain_truth.class_error_by_decile(values, correct)
    assert rates[:9] == [0.01] * 9 and rates[9] == 0.5
    assert edges[0] == edges[8] == 0.0 and edges[10] == 0.9
    # the order of the cells changes nothing
    order = np.random.default_rng(0).permutation(1000)
    assert terrain_truth.class_error_by_decile(values[order], correct[order]) == (rates, edges)


def test_the_error_rate_follows_a_band_without_ties():
    values = np.arange(100.0)
    correct = np.arange(100) % 10 >= np.arange(100) // 10  # decile d holds d wrong cells of 10
    rates, _ = terrain_truth.class_error_by_decile(values, correct)
    assert rates == [d / 10 for d in range(10)]

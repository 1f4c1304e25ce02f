"""Evaluation (docs/algorithm.md §4) on a hand-built map with hand-computed scores."""

import dataclasses

import numpy as np
import pytest

from evsemmap_warp.classes import class_set
from evsemmap_warp.config import load_config
from evsemmap_warp.apps.evaluation import evaluate_map, markdown_table
from evsemmap_warp.core.mapper import Mapper

GRASS, DIRT, PAVED, SKY, VOID = 7, 6, 4, 1, 0


@pytest.fixture
def mapper():
    config = dataclasses.replace(load_config([], method="s-csm").mapping, resolution_m=1.0)
    m = Mapper(config, 9, class_names=class_set().names, workers=1)
    points = np.array([[0.5, 0.5, 0.5]] * 3 + [[1.5, 0.5, 0.5], [2.5, 0.5, 0.5]])
    m.integrate(points, np.array([GRASS, GRASS, GRASS, PAVED, VOID]), payload_type="label")
    return m


def test_scores_by_hand(mapper):
    gt_points = np.array([[0.2, 0.2, 0.2], [0.8, 0.8, 0.8], [1.5, 0.5, 0.5], [2.5, 0.5, 0.5], [9.5, 9.5, 9.5], [0.5, 0.5, 0.5]])
    gt_labels = np.array([GRASS, DIRT, PAVED, GRASS, GRASS, SKY])  # free voxel, unknown voxel, unscored sky
    s = evaluate_map(mapper, gt_points, gt_labels)
    assert s.scored_queries == 5 and s.occupied_queries == 3
    assert s.occupied_accuracy == pytest.approx(3 / 5)
    assert s.accuracy == pytest.approx(2 / 3)
    assert s.iou["grass"] == pytest.approx(1 / 2) and s.iou["dirt"] == 0.0 and s.iou["paved"] == 1.0
    assert s.iou["water"] is None and s.iou["vegetation"] is None  # absent from the ground truth: "-"
    assert s.miou == pytest.approx((0.5 + 0.0 + 1.0) / 3)
    assert s.confusion[DIRT, GRASS] == 1 and s.confusion.sum() == 3
    # Brier: voxel A (majority of grass/dirt tie -> dirt, lowest id) is wrong, B right.
    var_a = (4 / 12) * (8 / 12) / 13  # alpha grass 1 + 3, S = 12
    var_b = (2 / 10) * (8 / 10) / 11
    assert s.scored_voxels == 2
    assert s.brier_minmax == pytest.approx(100 * ((0 - 0) ** 2 + (1 - 1) ** 2) / 2)
    bound = 1 / (4 * (9 + 1))
    assert s.brier_analytic == pytest.approx(100 * ((0 - (1 - var_a / bound)) ** 2 + (1 - (1 - var_b / bound)) ** 2) / 2)
    row = s.row()
    assert row["mIoU"] == pytest.approx(50.0) and row["water"] is None
    table = markdown_table({"s-csm": row}, ["water", "grass", "mIoU"])
    assert "| s-csm | - | 50.0 | 50.0 |" in table


def test_bad_ground_truth_is_an_error(mapper):
    with pytest.raises(ValueError, match="labels must lie in 0..8"):
        evaluate_map(mapper, np.zeros((2, 3)), np.array([3, 12]))
    with pytest.raises(ValueError, match=r"need points \[M, 3\] and labels \[M\]"):
        evaluate_map(mapper, np.zeros((2, 3)), np.array([3]))
    empty = evaluate_map(mapper, np.zeros((0, 3)), np.zeros(0, int))
    assert empty.scored_queries == 0 and empty.miou == 0.0 and empty.brier_minmax is None


def test_pooled_scores_equal_scoring_the_union(mapper):
    from evsemmap_warp.apps.evaluation import pool_scores

    a_points, a_labels = np.array([[0.2, 0.2, 0.2], [1.5, 0.5, 0.5]]), np.array([GRASS, PAVED])
    b_points, b_labels = np.array([[0.8, 0.8, 0.8], [2.5, 0.5, 0.5], [9.5, 9.5, 9.5]]), np.array([DIRT, GRASS, GRASS])
    pooled = pool_scores([evaluate_map(mapper, a_points, a_labels), evaluate_map(mapper, b_points, b_labels)])
    whole = evaluate_map(mapper, np.concatenate([a_points, b_points]), np.concatenate([a_labels, b_labels]))
    assert (pooled.confusion == whole.confusion).all()
    assert pooled.iou == whole.iou and pooled.miou == pytest.approx(whole.miou)
    assert pooled.accuracy == pytest.approx(whole.accuracy) and pooled.occupied_accuracy == pytest.approx(whole.occupied_accuracy)

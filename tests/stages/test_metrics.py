"""Plan metrics against a 3x3 example worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from stages.common.blueprint import Blueprint, Grid
from stages.common.errors import BlunfError
from stages.common.plan_metrics import evaluate_plan, plan_metrics

CLASSES = {0: "floor", 1: "wall", 2: "chair", 3: "table"}
GT = np.array([[0, 0, 1], [0, 2, 1], [255, 2, 2]], np.uint8)
PRED = np.array([[0, 1, 1], [0, 0, 1], [1, 0, 255]], np.uint8)
# The 8 known GT cells (all but the bottom-left 255, whose prediction 1 is not counted):
#   (0,0) 0/0 ok   (0,1) 0/1      (0,2) 1/1 ok   (1,0) 0/0 ok
#   (1,1) 2/0      (1,2) 1/1 ok   (2,1) 2/0      (2,2) 2/255 (unknown: wrong)
# pAcc = 4 / 8 = 50 %.
# floor: inter 2; |gt| 3; |pred| 4 ((0,0) (1,0) (1,1) (2,1)) -> IoU 2 / (3 + 4 - 2) = 0.4
# wall:  inter 2; |gt| 2; |pred| 3 ((0,1) (0,2) (1,2); (2,0) is outside the known cells) -> 2/3
# chair: never predicted -> IoU 0; table: in neither -> not scored.
# fwIoU = 3/8 * 0.4 + 2/8 * 2/3 + 3/8 * 0 = 0.15 + 0.1667 = 31.667 %
# mIoU = (0.4 + 0.6667 + 0) / 3 = 35.556 %; completeness = 7 / 8 = 87.5 %.
EXPECT = {
    "pacc": 50.0,
    "fwiou": 100 * (0.15 + 1 / 6),
    "miou": 100 * (0.4 + 2 / 3) / 3,
    "completeness": 87.5,
}


def _check(m: dict) -> None:
    for k, v in EXPECT.items():
        assert m[k] == pytest.approx(v, abs=1e-9), k
    assert m["per_class"] == pytest.approx({"floor": 40.0, "wall": 200 / 3, "chair": 0.0})
    assert m["cells"] == 8


def test_plan_metrics_by_hand():
    _check(plan_metrics(PRED, GT, CLASSES))


def test_perfect_prediction_scores_100():
    m = plan_metrics(np.where(GT == 255, 3, GT), GT, CLASSES)
    assert (m["pacc"], m["fwiou"], m["miou"], m["completeness"]) == (100.0, 100.0, 100.0, 100.0)


def test_shape_mismatch_and_empty_gt_are_errors():
    with pytest.raises(BlunfError, match="differ in shape"):
        plan_metrics(PRED[:2], GT)
    with pytest.raises(BlunfError, match="no known cell"):
        plan_metrics(PRED, np.full_like(GT, 255))


def test_evaluate_plan_resamples_and_maps_classes_by_name():
    gt = Blueprint(GT, Grid((0.0, 0.0), 0.5, (3, 3)), CLASSES)
    # The prediction: the same cells inside a 5x5 raster one cell larger on every side
    # (origin (-0.5, -0.5)), with other ids and names in another case.
    big = np.full((5, 5), 255, np.uint8)
    ids = {0: 10, 1: 11, 255: 255}
    big[1:4, 1:4] = np.vectorize(ids.get)(PRED)
    pred = Blueprint(big, Grid((-0.5, -0.5), 0.5, (5, 5)), {10: "Floor", 11: "WALL", 12: "chair"})
    _check(evaluate_plan(pred, gt))


def test_evaluate_plan_refuses_an_unknown_class_name():
    gt = Blueprint(GT, Grid((0.0, 0.0), 0.5, (3, 3)), CLASSES)
    pred = Blueprint(PRED, gt.grid, {0: "floor", 1: "window"})
    with pytest.raises(BlunfError, match="'window' is not in the ground truth"):
        evaluate_plan(pred, gt)

"""Score a predicted blueprint against a ground-truth blueprint on the GT's own grid."""

from __future__ import annotations

import logging

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.evaluate.metrics import plan_metrics

log = logging.getLogger(__name__)


def evaluate_plan(pred: Blueprint, gt: Blueprint) -> dict:
    """Metrics of `pred` read at the cell centres of `gt`'s grid (see metrics.plan_metrics).

    Class ids are matched by class NAME when the two tables differ; a class the prediction
    uses whose name the GT table lacks is an error.
    """
    labels = pred.resample(gt.grid)  # [H, W] on the GT grid
    lut = class_map(pred, gt)
    return plan_metrics(lut[labels], gt.labels, gt.classes)


def class_map(pred: Blueprint, gt: Blueprint) -> np.ndarray:
    """uint8 [256] lookup: prediction id -> GT id (identity when the tables agree)."""
    lut = np.arange(256, dtype=np.uint8)
    used = [int(c) for c in np.unique(pred.labels) if c != UNKNOWN]
    if not pred.classes or not gt.classes:
        log.warning("evaluate: a class table is missing; comparing class ids as they are")
        return lut
    by_name = {_key(n): i for i, n in gt.classes.items()}
    for c in used:
        name = pred.classes.get(c)
        if name is None:
            raise BlunfError(f"predicted blueprint: class id {c} has no name in its class table")
        if _key(name) not in by_name:
            raise BlunfError(
                f"predicted class {name!r} is not in the ground truth's class table "
                f"({', '.join(sorted(gt.classes.values()))})"
            )
        lut[c] = by_name[_key(name)]
    return lut


def _key(name: str) -> str:
    return name.strip().lower()

"""Plan metrics as in the paper (percent), over the ground-truth cells that are known, and a
predicted plan scored against a ground-truth plan on the GT's own grid.

With V the GT cells that are not unknown (255):
  pAcc = |pred = gt| / |V|  (an unknown prediction counts as wrong)
  IoU_c = |pred = c and gt = c| / |pred = c or gt = c|, both counted inside V
  fwIoU = sum_c freq_c IoU_c with freq_c = |gt = c| / |V|
  mIoU = mean IoU_c over the classes present in the GT
  completeness = |pred != 255| / |V|
"""

from __future__ import annotations

import logging

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import CATCH_ALL, KEPT
from stages.common.errors import BlunfError

log = logging.getLogger(__name__)


def plan_metrics(pred: np.ndarray, gt: np.ndarray, classes: dict[int, str] | None = None) -> dict:
    """pacc, fwiou, miou, completeness (percent), per_class IoU by name and the cell count.

    Args:
        pred: uint8 [H, W] predicted class ids (255 = unknown).
        gt: uint8 [H, W] ground-truth class ids (255 = not scored).
        classes: id -> name for `per_class` (ids without a name are named by their id).
    """
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.shape != gt.shape:
        raise BlunfError(
            f"plan metrics: prediction {pred.shape} and ground truth {gt.shape} differ in shape"
        )
    valid = gt != UNKNOWN
    n = int(valid.sum())
    if n == 0:
        raise BlunfError("plan metrics: the ground truth has no known cell")
    p = pred[valid].astype(np.int64)  # [V]
    g = gt[valid].astype(np.int64)  # [V]
    # confusion[g, p] over 256 ids (255 = unknown prediction)
    conf = np.bincount(g * 256 + p, minlength=256 * 256).reshape(256, 256)
    inter = np.diag(conf)  # [256]
    gt_n = conf.sum(axis=1)  # [256]
    pred_n = conf.sum(axis=0)  # [256]
    present = np.flatnonzero(gt_n)  # classes in the GT (never 255)
    iou = inter[present] / (gt_n[present] + pred_n[present] - inter[present])
    freq = gt_n[present] / n
    names = classes or {}
    return {
        "pacc": 100.0 * float(inter[present].sum()) / n,
        "fwiou": 100.0 * float((freq * iou).sum()),
        "miou": 100.0 * float(iou.mean()),
        "completeness": 100.0 * float((p != UNKNOWN).sum()) / n,
        "per_class": {
            names.get(int(c), str(int(c))): 100.0 * float(v)
            for c, v in zip(present, iou, strict=True)
        },
        "cells": n,
    }


def evaluate_plan(pred: Blueprint, gt: Blueprint, pred_to_gt: np.ndarray | None = None) -> dict:
    """Metrics of `pred` read at the cell centres of `gt`'s grid (see plan_metrics).

    Class ids are matched by class NAME when the two tables differ; a class the prediction
    uses whose name the GT table lacks is an error, except the catch-all classes of plans
    labelled without per-class labels ("object" of the semantics stage, "occupied" of height
    bands): the GT is then coarsened to the prediction's classes (see coarse_gt).

    Args:
        pred: the predicted plan, in its own world frame.
        gt: the ground-truth plan.
        pred_to_gt: 4x4 similarity from the prediction's world to the GT's (e.g. estimated
            from camera centres when the poses were reconstructed); None = the same frame.
            The GT cell centres (x, y, 0) are mapped by its inverse and the prediction is
            read there (nearest cell).
    """
    if pred_to_gt is None:
        labels = pred.resample(gt.grid)  # [H, W] on the GT grid
    else:
        labels = pred.sample(to_frame(gt.grid.centers().reshape(-1, 2), pred_to_gt))
        labels = labels.reshape(gt.grid.shape)  # [H, W]
    gt = coarse_gt(pred, gt)
    lut = class_map(pred, gt)
    return plan_metrics(lut[labels], gt.labels, gt.classes)


# CATCH_ALL: coarse classes standing for every GT class but the KEPT ones (when the
# prediction has them; else they fall in it too)


def coarse_gt(pred: Blueprint, gt: Blueprint) -> Blueprint:
    """`gt` relabelled into the prediction's coarse table when the prediction has a catch-all
    class the GT lacks (e.g. floor / wall / object against floor / wall / table / chair...):
    a GT class named like one of the prediction's KEPT classes keeps it, every other known
    GT class becomes the catch-all. Otherwise `gt` itself."""
    names = {_key(n): i for i, n in pred.classes.items()}
    gt_names = {_key(n) for n in gt.classes.values()}
    catch = next((names[c] for c in CATCH_ALL if c in names and c not in gt_names), None)
    if catch is None:
        return gt
    lut = np.full(256, catch, np.uint8)
    lut[UNKNOWN] = UNKNOWN
    for i, n in gt.classes.items():
        if _key(n) in KEPT and _key(n) in names and 0 <= i < UNKNOWN:
            lut[i] = names[_key(n)]
    return Blueprint(lut[gt.labels], gt.grid, dict(pred.classes))


def to_frame(xy: np.ndarray, pred_to_gt: np.ndarray) -> np.ndarray:
    """GT floor points (x, y, 0) [N, 2] in the prediction's frame: inverse similarity. [N, 2]"""
    m = np.asarray(pred_to_gt, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3])) < 1e-12:
        raise BlunfError(
            f"plan evaluation: pred_to_gt must be an invertible 4x4 similarity, got shape {m.shape}"
        )
    p = np.concatenate([np.asarray(xy, np.float64), np.zeros((len(xy), 1))], axis=1)  # [N, 3]
    return np.linalg.solve(m[:3, :3], (p - m[:3, 3]).T).T[:, :2]


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

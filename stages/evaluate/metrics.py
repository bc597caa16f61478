"""Plan metrics as in the paper (percent), over the ground-truth cells that are known.

With V the GT cells that are not unknown (255):
  pAcc = |pred = gt| / |V|  (an unknown prediction counts as wrong)
  IoU_c = |pred = c and gt = c| / |pred = c or gt = c|, both counted inside V
  fwIoU = sum_c freq_c IoU_c with freq_c = |gt = c| / |V|
  mIoU = mean IoU_c over the classes present in the GT
  completeness = |pred != 255| / |V|
"""

from __future__ import annotations

import numpy as np

from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError


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

"""Edit metrics (DESIGN.md `metrics.edit`): changed_iou and psnr_outside.

- changed_iou: the pixels whose render changed by more than a threshold (any channel), against
  the ground-truth mask of the selected object(s), pooled over the views that have one:
  sum of intersections / sum of unions. changed_iou_views gives it view by view (the bar
  "in every rendered view" is read there), None for a view where both masks are empty.
- psnr_outside: PSNR of the edited render against the unedited one over the pixels outside
  the selection's mask, pooled over the views; capped at PSNR_CAP when nothing changed.

The selection is matched to ground-truth instances through its masks: the instance its
masks overlap most, plus every instance at least half covered by them (a class or polygon
selection picks several objects) with an overlap of at least MIN_OF_BEST of the best one's
(an object barely in view, a few pixels at a mask's edge, is not matched). Instance 0
(floor, walls, ceiling) is never matched.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image

from stages.common.io import read_json, read_label

PSNR_CAP = 100.0  # dB reported when the two renders are equal outside the selection
MIN_OF_BEST = 0.05  # a further instance needs at least this fraction of the best one's overlap


def changed(before: np.ndarray, after: np.ndarray, threshold: float) -> np.ndarray:
    """Pixels where a channel moved by more than `threshold`. [H, W, 3] x2 -> bool [H, W]."""
    return np.abs(after.astype(np.float64) - before.astype(np.float64)).max(axis=-1) > threshold


def pooled_iou(pred: list[np.ndarray], gt: list[np.ndarray]) -> float | None:
    """IoU of bool masks pooled over views; None when both are empty everywhere."""
    inter = sum(int((p & g).sum()) for p, g in zip(pred, gt, strict=True))
    union = sum(int((p | g).sum()) for p, g in zip(pred, gt, strict=True))
    return inter / union if union else None


def match_instances(masks: list[np.ndarray], instances: list[np.ndarray]) -> list[int]:
    """Ground-truth instance ids (> 0) a selection picks, from its masks and the instance maps
    (int [H, W] each) of the same views: the most overlapped one, and every one at least half
    inside the masks with MIN_OF_BEST of its overlap. Empty when no instance overlaps."""
    overlap: dict[int, int] = {}
    total: dict[int, int] = {}
    for m, inst in zip(masks, instances, strict=True):
        ids, counts = np.unique(inst, return_counts=True)
        for i, n in zip(ids.tolist(), counts.tolist(), strict=True):
            total[i] = total.get(i, 0) + n
        ids, counts = np.unique(inst[m], return_counts=True)
        for i, n in zip(ids.tolist(), counts.tolist(), strict=True):
            overlap[i] = overlap.get(i, 0) + n
    overlap.pop(0, None)
    if not overlap:
        return []
    best = max(overlap, key=lambda i: (overlap[i], -i))
    floor = MIN_OF_BEST * overlap[best]
    return sorted({best} | {i for i, n in overlap.items() if 2 * n >= total[i] and n >= floor})


class EditScore:
    """One edit's metrics, accumulated view by view (renders are not kept, masks are)."""

    def __init__(self, threshold: float) -> None:
        self.threshold = threshold  # change threshold (RGB in [0, 1])
        self.se = 0.0  # squared error outside the selection
        self.n = 0  # values (pixels x channels) outside the selection
        self.changed: list[np.ndarray] = []  # bool [H, W] per view
        self.sel: list[np.ndarray] = []  # bool [H, W] per view
        self.inst: list[np.ndarray | None] = []  # GT instance map per view, or None

    def add(
        self, before: np.ndarray, after: np.ndarray, sel: np.ndarray, inst: np.ndarray | None
    ) -> None:
        """One view: renders [H, W, 3] without / with the edit, its mask, GT instances."""
        out = ~sel
        d = after[out].astype(np.float64) - before[out].astype(np.float64)
        self.se += float((d**2).sum())
        self.n += d.size
        self.changed.append(changed(before, after, self.threshold))
        self.sel.append(sel)
        self.inst.append(inst)

    def result(self, names: dict[int, str]) -> dict:
        """changed_iou pooled and per view (None without GT for every view or without a
        matched instance), psnr_outside, the matched GT instances, pixel counts and a note."""
        psnr = PSNR_CAP if self.n == 0 or self.se == 0 else -10 * math.log10(self.se / self.n)
        m: dict = {"psnr_outside": round(min(PSNR_CAP, psnr), 3), "changed_iou": None}
        m["changed_iou_views"] = None
        m["gt_instances"], m["note"] = [], ""
        inst = [i for i in self.inst if i is not None]
        if not inst or len(inst) < len(self.inst):
            m["note"] = "no ground-truth instance masks for these views"
        elif ids := match_instances(self.sel, inst):
            gts = [np.isin(i, ids) for i in inst]
            ious = [pooled_iou(self.changed, gts)]
            ious += [pooled_iou([c], [g]) for c, g in zip(self.changed, gts, strict=True)]
            r = [None if v is None else round(v, 4) for v in ious]
            m["changed_iou"], m["changed_iou_views"] = r[0], r[1:]
            m["gt_instances"] = [{"id": i, "name": names.get(i, "")} for i in ids]
        else:
            m["note"] = "the selection's masks overlap no ground-truth instance"
        m["changed_pixels"] = int(sum(int(c.sum()) for c in self.changed))
        m["selected_pixels"] = int(sum(int(c.sum()) for c in self.sel))
        return m


def gt_instances(gt: Path, stem: str, width: int, height: int) -> np.ndarray | None:
    """The frame's ground-truth instance map (gt/instances/<stem>.png) at width x height
    (nearest neighbour when the render is smaller), int32 [H, W]; None when absent."""
    p = Path(gt) / "instances" / f"{stem}.png"
    if not p.is_file():
        return None
    inst = read_label(p)
    if inst.shape != (height, width):
        img = Image.fromarray(inst.astype(np.int32), mode="I")
        inst = np.asarray(img.resize((width, height), Image.Resampling.NEAREST), np.int32)
    return inst


def gt_instance_names(gt: Path | None) -> dict[int, str]:
    """Instance id -> name from gt/instances.json ({} when absent)."""
    p = None if gt is None else Path(gt) / "instances.json"
    if p is None or not p.is_file():
        return {}
    d = read_json(p)
    if not isinstance(d, dict):
        return {}
    return {int(k): str(v.get("name", "")) for k, v in d.items() if isinstance(v, dict)}

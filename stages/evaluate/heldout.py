"""Held-out view accuracy: a plan read under the pixels of views it was not built from.

Each labelled pixel with depth of a held-out view is lifted to the world (Π, pinhole) and
the plan's label at its (x, y) cell is compared with the pixel's own label:

  heldout_pacc = |plan label = pixel label| / |pixels scored|  (percent)

Pixels whose label is ignored (e.g. ceiling) or unknown are not scored. A pixel falling on
an unknown cell, outside the plan, or whose class the plan does not have counts as wrong
(as for completeness). Labels are matched by class name between the frames' table and the
plan's. The plan is a top view, so a held-out pixel of floor under a table top scores
against the table: no plan reaches 100 on a furnished room.
"""

from __future__ import annotations

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.camera import depth_to_points
from stages.common.capture import UNKNOWN, Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_label


def heldout_pacc(plan: Blueprint, cap: Capture, stems: list[str], stride: int = 1) -> dict:
    """pAcc (percent) of `plan` on the labelled pixels of the frames named `stems`.

    Args:
        plan: the blueprint, in the frames' world.
        cap: the frames (poses, depth, labels) and their class table.
        stems: the held-out frames.
        stride: score every stride-th pixel in u and v.
    Returns:
        {"heldout_pacc": percent or None when no pixel was scored, "heldout_pixels": count,
        "heldout_views": number of views}.
    """
    xy, lab = heldout_pixels(cap, stems, stride)
    return score_pixels(plan, cap, xy, lab, len(stems))


def heldout_pixels(
    cap: Capture, stems: list[str], stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """The scored pixels of the frames named `stems` (labelled, not ignored), lifted with their
    depth: (world xy [N, 2], frame label id [N]). Independent of any plan: lift once, score
    every method's plan with `score_pixels`."""
    by_stem = {f.stem: f for f in cap.frames}
    xys, labs = [np.zeros((0, 2))], [np.zeros(0, np.int64)]
    for stem in stems:
        f = by_stem.get(stem)
        if f is None:
            raise BlunfError(f"held-out view {stem!r} is not among the frames of {cap.root}")
        if f.label is None or f.depth is None or f.pose is None:
            raise BlunfError(f"held-out view {stem!r} needs a label map, depth and a pose")
        depth = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)  # [H, W] metres
        label = read_label(f.label)  # [H, W]
        if label.shape != depth.shape:
            raise BlunfError(
                f"{f.label}: label map is {label.shape[1]}x{label.shape[0]} but its depth "
                f"{f.depth.name} is {depth.shape[1]}x{depth.shape[0]}"
            )
        intr = f.intrinsics
        if (intr.width, intr.height) != (depth.shape[1], depth.shape[0]):
            intr = intr.scaled(depth.shape[1], depth.shape[0])
        xyz, idx = depth_to_points(depth, intr.K, np.asarray(f.pose, np.float64), stride)
        lab = label[stride // 2 :: stride, stride // 2 :: stride].reshape(-1)[idx]  # [N]
        keep = (lab >= 0) & (lab < UNKNOWN)
        keep[keep] = ~np.isin(lab[keep], cap.ignore)
        xys.append(xyz[keep, :2])
        labs.append(lab[keep].astype(np.int64))
    return np.concatenate(xys), np.concatenate(labs)


def score_pixels(
    plan: Blueprint, cap: Capture, xy: np.ndarray, lab: np.ndarray, views: int
) -> dict:
    """heldout_pacc's result for pixels lifted by `heldout_pixels` (`views` of them)."""
    want = _to_plan(cap, plan)[lab]  # [N] the plan id each pixel should read
    got = plan.sample(xy).astype(np.int64)  # [N] UNKNOWN outside / unseen
    scored = len(want)
    correct = int(((want == got) & (got != UNKNOWN)).sum())
    return {
        "heldout_pacc": 100.0 * correct / scored if scored else None,
        "heldout_pixels": scored,
        "heldout_views": views,
    }


def _to_plan(cap: Capture, plan: Blueprint) -> np.ndarray:
    """int64 [256] lookup from the frames' label ids to the plan's ids, by class name (an id
    the frames' table does not name is "class <id>", as the project stage names it; the ids
    themselves when the plan has no table); -1 for a class the plan does not have."""
    if not plan.classes:
        return np.arange(256, dtype=np.int64)
    by_name = {name.strip().lower(): i for i, name in plan.classes.items()}
    names = [cap.classes.get(i, f"class {i}").strip().lower() for i in range(256)]
    return np.array([by_name.get(n, -1) for n in names], np.int64)

"""Held-out view accuracy: a plan read under the pixels of views it was not built from.

Each labelled pixel with depth of a held-out view is lifted to the world (Π, pinhole) and
the plan's label at its (x, y) cell is compared with the pixel's own label:

  heldout_pacc = |plan label = pixel label| / |pixels scored|  (percent)

A pixel on a steep surface (its normal within 30 degrees of horizontal: a wall, a cabinet's
front) is right when the plan has its class either in the cell under its surface point or
half a plan cell behind it, along the surface's horizontal normal: the face runs through a
cell, and two conventions place it. The ground truth's (one ray down through each cell
centre) makes a cell wall when its centre lies behind the face, so the face's own cell may
rightly be floor, and half a cell behind the face lies always in the first cell whose
centre is behind it (for faces along the grid's axes); a plan drawn from the points alone
(MVR) puts the wall in the cell holding the face. Read on the surface only, the office's
plan with `blueprint.blunf.wall_face` at margin 0 (drawn to the first) scored 68.65; read
behind only, MVR's fell from 95.29 to 75.64. `heldout_pacc_surface` and
`heldout_pacc_behind` give the two readings alone. Floor, table tops and other flat
surfaces read the cell under their point either way.

Pixels whose label is ignored (e.g. ceiling) or unknown are not scored. A pixel falling on
an unknown cell, outside the plan, or whose class the plan does not have counts as wrong
(as for completeness). Labels are matched by class name between the frames' table and the
plan's. The plan is a top view, so a held-out pixel of floor under a table top scores
against the table: no plan reaches 100 on a furnished room.
"""

from __future__ import annotations

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.camera import depth_to_points, unproject
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
        {"heldout_pacc": percent or None when no pixel was scored, "heldout_pacc_surface" and
        "heldout_pacc_behind": the surface point's cell alone and the cell half a cell behind
        it alone, "heldout_pixels": count, "heldout_views": number of views}.
    """
    xy, lab, inward = heldout_pixels(cap, stems, stride)
    return score_pixels(plan, cap, xy, lab, len(stems), inward)


def heldout_pixels(
    cap: Capture, stems: list[str], stride: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scored pixels of the frames named `stems` (labelled, not ignored), lifted with their
    depth: (world xy [N, 2], frame label id [N], inward [N, 2]: the unit horizontal direction
    into a steep surface, 0 on flat ones and where no normal is found). Independent of any
    plan: lift once, score every method's plan with `score_pixels`."""
    by_stem = {f.stem: f for f in cap.frames}
    xys, labs = [np.zeros((0, 2))], [np.zeros(0, np.int64)]
    ins = [np.zeros((0, 2))]
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
        c2w = np.asarray(f.pose, np.float64)
        xyz, idx = depth_to_points(depth, intr.K, c2w, stride)
        lab = label[stride // 2 :: stride, stride // 2 :: stride].reshape(-1)[idx]  # [N]
        keep = (lab >= 0) & (lab < UNKNOWN)
        keep[keep] = ~np.isin(lab[keep], cap.ignore)
        inward = _inward(depth, intr.K, c2w, stride)
        xys.append(xyz[keep, :2])
        labs.append(lab[keep].astype(np.int64))
        ins.append(inward.reshape(-1, 2)[idx][keep])
    return np.concatenate(xys), np.concatenate(labs), np.concatenate(ins)


STEEP = 0.5  # |normal z| under this: a steep surface (within 30 degrees of vertical)
NORMAL_STEP = 2  # pixels either side the normal is taken over
NORMAL_JUMP = 0.05  # a neighbour whose depth differs by more than this share: an edge, no normal


def _inward(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, stride: int = 1) -> np.ndarray:
    """[H', W', 2] float64 on the strided pixel grid (pixel_grid's): the unit horizontal
    direction into the surface at each pixel (away from the camera, along the surface's normal
    from its full-resolution neighbours NORMAL_STEP pixels away, one-sided at the image's
    border), 0 where the surface is flatter than STEEP, at depth edges and where depth is
    missing. Only the scored pixels and their neighbours are lifted."""
    h, w = depth.shape
    v, u = np.arange(stride // 2, h, stride), np.arange(stride // 2, w, stride)
    out = np.zeros((len(v), len(u), 2))
    if h < 2 or w < 2:
        return out
    d = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    u0, u1 = np.clip(u - NORMAL_STEP, 0, w - 1), np.clip(u + NORMAL_STEP, 0, w - 1)
    v0, v1 = np.clip(v - NORMAL_STEP, 0, h - 1), np.clip(v + NORMAL_STEP, 0, h - 1)

    def lift(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:  # [len(rows), len(cols), 3]
        uu, vv = np.meshgrid(cols.astype(np.float64), rows.astype(np.float64))
        uv = np.stack([uu, vv], axis=-1).reshape(-1, 2)
        z = np.nan_to_num(d[np.ix_(rows, cols)]).reshape(-1)
        return unproject(uv, z, K, c2w).reshape(len(rows), len(cols), 3)

    dc = d[np.ix_(v, u)]
    ok = np.isfinite(dc)
    with np.errstate(invalid="ignore"):
        for dn in (d[np.ix_(v, u0)], d[np.ix_(v, u1)], d[np.ix_(v0, u)], d[np.ix_(v1, u)]):
            ok &= np.isfinite(dn) & (np.abs(dn - dc) <= NORMAL_JUMP * dc)
    p = lift(v, u)
    n = np.cross(lift(v, u1) - lift(v, u0), lift(v1, u) - lift(v0, u))  # [H', W', 3]
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n / np.maximum(norm, 1e-12)[..., None]
    facing = np.einsum("hwk,hwk->hw", n, c2w[:3, 3] - p) >= 0
    n = np.where(facing[..., None], n, -n)  # the normal towards the camera
    horiz = np.linalg.norm(n[..., :2], axis=-1)
    ok &= (np.abs(n[..., 2]) < STEEP) & (horiz > 0)
    out[ok] = -n[ok, :2] / horiz[ok, None]
    return out


def score_pixels(
    plan: Blueprint,
    cap: Capture,
    xy: np.ndarray,
    lab: np.ndarray,
    views: int,
    inward: np.ndarray | None = None,
) -> dict:
    """heldout_pacc's result for pixels lifted by `heldout_pixels` (`views` of them); without
    `inward` every pixel reads only the cell under its surface point."""
    want = _to_plan(cap, plan)[lab]  # [N] the plan id each pixel should read
    scored = len(want)

    def right(at: np.ndarray) -> np.ndarray:
        got = plan.sample(at).astype(np.int64)  # [N] UNKNOWN outside / unseen
        return (want == got) & (got != UNKNOWN)

    def pct(ok: np.ndarray) -> float | None:
        return 100.0 * int(ok.sum()) / scored if scored else None

    surface = right(xy)
    behind = surface if inward is None else right(xy + 0.5 * plan.grid.cell * inward)
    return {
        "heldout_pacc": pct(surface | behind),
        "heldout_pacc_surface": pct(surface),
        "heldout_pacc_behind": pct(behind),
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

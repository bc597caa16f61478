"""Where the photos-only run put each wall, against where the sensor-depth reference did.

A plan's wall cell is 2 cm; a reference wall drawn one cell thick is missed whole by a wall
that lies 2 cm off it, so a wall IoU says little about how far off the walls are. This
gives the distance, per wall of the reference's layout (its plan.json, the room's outline),
signed so that + is into the reference's room (the photos-only room is smaller there):
  layout       the nearest parallel wall (within 10 degrees) of the photos-only run's layout
               whose middle lies along the reference wall and within 0.3 m of it,
  plan_points  where the photos-only run's wall points (its projected points.npz, what the
               plan's field is fitted to) pile up within a band round the wall: the
               outermost high peak of their offsets, then the median of those within 2 cm
               of it (what stands in front of a wall, a shelf or a picture, does not pull
               it in: `_peak`),
  sfm_points   the same for its SfM points (the poses stage's sparse.ply in the aligned
               world): the geometry the depth stage starts from, which the depth maps
               cannot be truer than. When these lie off as far as the wall points do, the
               walls are off because SfM's model is, not because of the depth;
  ref_points   the reference's own wall points: its drawing against its points (near 0).
Each is taken through the similarity between the two runs' whole poses (`pred_to_ref`, the
one the plan is scored through). Walls of the reference shorter than 0.5 m are left out.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy import ndimage

from pipeline.bench.runs import stage_file
from stages.common.classes import WALL_NAME, ids_named
from stages.common.errors import BlunfError
from stages.common.points import read_points

PARALLEL_DEG = 10.0  # a layout wall matches a reference wall this close in direction...
MATCH_M = 0.3  # ...with its middle this close to the reference wall's line
BAND_M = 0.15  # points this close to a reference wall's line count for it...
END_M = 0.2  # ...away from its ends (corners hold the other wall's points) by this much
MIN_POINTS = 20  # a wall's offset needs this many points
PEAK_BIN_M = 0.005  # the offsets' histogram bins...
PEAK_SMOOTH_M = 0.01  # ...smoothed by a Gaussian this wide
PEAK_KEEP_M = 0.02  # the points this close to the peak give the wall's offset
PEAK_SHARE = 0.5  # a peak this high against the highest may be the wall's
MIN_WALL_M = 0.5  # reference walls shorter than this are left out


def _walls(plan: dict) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(start [2], unit direction [2], unit normal into its room [2]) of each wall of a
    plan.json (its room's polygon centroid gives the room's side)."""
    rooms = plan.get("rooms") or []
    out = []
    for w in plan.get("walls") or []:
        a, b = np.asarray(w["start"], float), np.asarray(w["end"], float)
        length = float(np.linalg.norm(b - a))
        if length < MIN_WALL_M:
            continue
        t = (b - a) / length
        n = np.array([-t[1], t[0]])
        room = w.get("room")
        if room is not None and 0 <= room < len(rooms):
            centre = np.asarray(rooms[room]["polygon"], float).mean(0)
            if (centre - a) @ n < 0:
                n = -n
        out.append((a, b, n))
    return out


def _to_ref(xy: np.ndarray, pred_to_ref: np.ndarray) -> np.ndarray:
    """Floor points (x, y, 0) [N, 2] of the photos-only run in the reference's frame."""
    m = np.asarray(pred_to_ref, float)
    p = np.concatenate([np.asarray(xy, float).reshape(-1, 2), np.zeros((len(xy), 1))], 1)
    return (p @ m[:3, :3].T + m[:3, 3])[:, :2]


def layout_offsets(ref: dict, pred: dict, pred_to_ref: np.ndarray) -> list[float | None]:
    """Per reference wall (MIN_WALL_M or longer): the signed offset (metres, + into the
    reference's room) of the nearest matching photos-only layout wall, None when none."""
    segs = []
    for w in pred.get("walls") or []:
        s, e = _to_ref(np.array([w["start"], w["end"]], float), pred_to_ref)
        if np.linalg.norm(e - s) > 0:
            segs.append((s, e))
    out: list[float | None] = []
    cos = np.cos(np.deg2rad(PARALLEL_DEG))
    for a, b, n in _walls(ref):
        t, length = (b - a) / np.linalg.norm(b - a), float(np.linalg.norm(b - a))
        best = None
        for s, e in segs:
            if abs((e - s) @ t) < cos * np.linalg.norm(e - s):
                continue
            mid = (s + e) / 2
            along, off = float((mid - a) @ t), float((mid - a) @ n)
            if -END_M <= along <= length + END_M and abs(off) <= MATCH_M:
                if best is None or abs(off) < abs(best):
                    best = off
        out.append(best)
    return out


def point_offsets(ref: dict, xy: np.ndarray) -> list[float | None]:
    """Per reference wall: the signed offset (metres, + into its room) where the points xy
    [N, 2] (the reference's frame) within BAND_M of its line and END_M inside its ends pile
    up (`_peak`); None with fewer than MIN_POINTS there."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    out: list[float | None] = []
    for a, b, n in _walls(ref):
        t, length = (b - a) / np.linalg.norm(b - a), float(np.linalg.norm(b - a))
        d = xy - a
        along, off = d @ t, d @ n
        sel = (along > END_M) & (along < length - END_M) & (np.abs(off) < BAND_M)
        out.append(_peak(off[sel]) if sel.sum() >= MIN_POINTS else None)
    return out


def _peak(off: np.ndarray) -> float:
    """The offset [N] of the wall's surface among the points round it: of the peaks of their
    histogram (PEAK_BIN_M bins smoothed by PEAK_SMOOTH_M) holding at least PEAK_SHARE of the
    highest's count, the outermost (a wall bounds the room: a shelf, a picture or a chair
    stands in front of it, and may pile up higher), then the median of the points within
    PEAK_KEEP_M of it. A median of them all is pulled in by what stands in front."""
    edges = np.arange(-BAND_M, BAND_M + PEAK_BIN_M / 2, PEAK_BIN_M)
    hist, _ = np.histogram(off, bins=edges)
    smooth = ndimage.gaussian_filter1d(hist.astype(np.float64), PEAK_SMOOTH_M / PEAK_BIN_M)
    pad = np.r_[-1.0, smooth, -1.0]
    tops = np.nonzero((smooth >= pad[:-2]) & (smooth > pad[2:]))[0]
    tops = tops[smooth[tops] >= PEAK_SHARE * smooth.max()]
    i = int(tops.min()) if len(tops) else int(np.argmax(smooth))
    top = (edges[i] + edges[i + 1]) / 2
    near = off[np.abs(off - top) <= PEAK_KEEP_M]
    return float(np.median(near)) if len(near) else float(top)


def _summary(offsets: list[float | None]) -> dict:
    """{"offsets_cm": per wall (None: not found), "found", "median_cm" (signed),
    "median_abs_cm"}."""
    got = np.array([o for o in offsets if o is not None], float) * 100
    return {
        "offsets_cm": [None if o is None else round(o * 100, 2) for o in offsets],
        "found": int(len(got)),
        "median_cm": round(float(np.median(got)), 2) if len(got) else None,
        "median_abs_cm": round(float(np.median(np.abs(got))), 2) if len(got) else None,
    }


def _wall_points(run: Path) -> np.ndarray:
    """The run's projected wall points, floor xy [N, 2] in its world."""
    path = stage_file(run, "project", "points.npz")
    if path is None:
        raise BlunfError(f"{run}: no project/*/points.npz (not a finished run folder)")
    xyz, label, _, classes = read_points(path)
    return xyz[np.isin(label, ids_named(classes, WALL_NAME)), :2]


def sfm_points(run: Path) -> np.ndarray | None:
    """The run's SfM points (poses/<key>/sparse.ply) in the aligned world, floor xy [N, 2];
    None when the run has none (poses given) or no align transform."""
    ply, align = stage_file(run, "poses", "sparse.ply"), stage_file(run, "align", "align.json")
    if ply is None or align is None:
        return None
    import trimesh  # the project's mesh reader; the PLY is COLMAP's point export

    cloud = trimesh.load(ply, process=False)
    pts = np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), np.float64)
    T = np.asarray(json.loads(align.read_text())["T"], np.float64)
    if len(pts) == 0 or T.shape != (4, 4):
        return None
    return (pts @ T[:3, :3].T + T[:3, 3])[:, :2]


def wall_offsets(ref_run: Path, pred_run: Path, pred_to_ref: np.ndarray) -> dict | None:
    """The module's figures for the two runs (see the module doc); None when either run has
    no plan.json (no layout stage)."""
    rp, pp = Path(ref_run) / "plan.json", Path(pred_run) / "plan.json"
    if not rp.is_file() or not pp.is_file():
        return None
    ref, pred = json.loads(rp.read_text()), json.loads(pp.read_text())
    res = {
        "walls": len(_walls(ref)),
        "layout": _summary(layout_offsets(ref, pred, pred_to_ref)),
        "plan_points": _summary(point_offsets(ref, _to_ref(_wall_points(pred_run), pred_to_ref))),
        "ref_points": _summary(point_offsets(ref, _wall_points(ref_run))),
    }
    sfm = sfm_points(pred_run)
    if sfm is not None:
        res["sfm_points"] = _summary(point_offsets(ref, _to_ref(sfm, pred_to_ref)))
    return res

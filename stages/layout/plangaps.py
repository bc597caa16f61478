"""Openings of the walls the mesh does not hold, read off the plan.

A partition between two rooms may stand in the plan from the views' readings alone (the
semantics stage's inner walls: planes of readings no ray crossed) while stereo fused neither
of its faces: no ray cast along its line meets anything (openings.held), so the mesh shows no
gap in it either. Its openings are then read off the blueprint raster: between the faces of
two rooms that run back to back (the wall's band), a run of steps along the wall where the
band is floor or unseen, not wall or furniture, at least `min_opening` long, with the plan's
field's floor in it and each room's floor in front of it. Up to `door_max` it is a door,
wider a passage, as the mesh route tells them.
"""

from __future__ import annotations

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import FLOOR_NAME, ids_named
from stages.layout.config import LayoutConfig

HELD = 0.25  # share of a wall met by the mesh's rays under which the plan reads its openings
#              (the 3-room home from photos: 0.02 on both faces of its unfused partition; the
#              fused walls of the homes and single rooms 0.4 or more, a wall with a passage)
BACK_TO_BACK = 0.999  # |cos| of the angle between two faces of one wall (opposite directions)
FREE = 0.5  # share of the band across a step that must be floor or unseen for it to be open
GAP_FLOOR = 0.5  # share of a gap's band cells that must be floor (the field ran through it)
REACH = 0.3  # metres in front of each face where the room's floor is looked for
ROOM_FLOOR = 0.5  # share of those cells that must be floor, on each side


def plan_openings(
    walls: list[dict], held: np.ndarray, bp: Blueprint, cfg: LayoutConfig
) -> list[dict]:
    """plan.json openings (world metres) of the walls whose `held` share [W] is under HELD,
    read off the plan `bp` where two such faces of different rooms run back to back within
    `max_thickness` (each opening once, on the first face's wall)."""
    fid = ids_named(bp.classes, FLOOR_NAME)
    out = []
    loose = [i for i in range(len(walls)) if held[i] < HELD]
    for k, wi in enumerate(loose):
        for vi in loose[k + 1 :]:
            if walls[wi]["room"] != walls[vi]["room"]:
                out += _gaps(walls, wi, vi, bp, fid, cfg)
    return out


def face_line(w: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(start, unit direction, outward normal, length) of a wall's face."""
    a, b = np.asarray(w["start"], np.float64), np.asarray(w["end"], np.float64)
    length = float(np.linalg.norm(b - a))
    d = (b - a) / max(length, 1e-12)
    return a, d, np.array([d[1], -d[0]]), length


def _labels(bp: Blueprint, pts: np.ndarray) -> np.ndarray:
    """The plan's labels at world points [..., 2] (UNKNOWN off the grid)."""
    row, col, ok = bp.grid.cell_of(pts.reshape(-1, 2))
    return np.where(ok, bp.labels[row, col], UNKNOWN).reshape(pts.shape[:-1])


def _gaps(
    walls: list[dict], wi: int, vi: int, bp: Blueprint, fid: list[int], cfg: LayoutConfig
) -> list[dict]:
    """The openings between face wi and face vi when they run back to back (see plan_openings):
    [] otherwise."""
    a, d, n, length = face_line(walls[wi])
    b, e, _, _ = face_line(walls[vi])
    depth = float((b - a) @ n)  # how far the other face lies beyond this one
    if d @ e > -BACK_TO_BACK or not 0 < depth <= cfg.max_thickness:
        return []
    ends = sorted(float((np.asarray(walls[vi][k], np.float64) - a) @ d) for k in ("start", "end"))
    lo, hi = max(0.0, ends[0]), min(length, ends[1])  # where the faces overlap along wi
    cell = bp.grid.cell
    steps = int((hi - lo) / cell)
    if steps * cell < cfg.min_opening:
        return []
    s = lo + (np.arange(steps) + 0.5) * cell  # [S] along the face
    u = np.arange(cell / 4, depth, cell / 2) if depth > cell / 2 else np.array([depth / 2])
    line = a + s[:, None] * d  # [S, 2]
    band = _labels(bp, line[:, None] + u[None, :, None] * n)  # [S, U]
    floor = np.isin(band, fid)
    free = (floor | (band == UNKNOWN)).mean(1) >= FREE
    r = np.arange(cell / 2, REACH, cell)
    mine = np.isin(_labels(bp, line[:, None] - r[None, :, None] * n), fid)  # [S, R]
    theirs = np.isin(_labels(bp, line[:, None] + (depth + r)[None, :, None] * n), fid)
    out = []
    edges = np.diff(np.concatenate([[0], free.astype(np.int8), [0]]))
    for i, j in zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0], strict=True):
        width = (j - i) * cell
        if (
            width < cfg.min_opening
            or (i == 0 and j == steps)  # no wall beside it: no opening in a wall
            or floor[i:j].mean() < GAP_FLOOR
            or min(mine[i:j].mean(), theirs[i:j].mean()) < ROOM_FLOOR
        ):
            continue
        p, q = a + (lo + i * cell) * d, a + (lo + j * cell) * d
        out.append(
            {
                "kind": "door" if width <= cfg.door_max else "passage",
                "wall": wi,
                "start": np.round(p, 4).tolist(),
                "end": np.round(q, 4).tolist(),
                "width": round(width, 4),
            }
        )
    return out

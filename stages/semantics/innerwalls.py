"""Walls between rooms from the points the views saw: every plane of readings that no ray
crossed.

pointwalls.py finds a room's bounding walls, one per direction: the cameras stand on one
side of each. A home has walls with cameras on both sides (the rooms either side), several
along each axis, each with its own stretch (a wall between two rooms ends where a third
begins; a doorway cuts it). Here each face of such a wall is found where it holds:

- Candidates: along each of the room's two axes and for the cameras on either side, the
  offsets at which the readings above the floor taken from that side pile up (local maxima
  of the count within `dist` / 2, over `2 dist`, moved to the median of the readings within
  `dist`): the two faces of a wall 12 cm thick.
- A face is what the cameras on one side saw of the plane: the readings on it (within
  `dist`) taken from a camera on that side. A ray from such a camera to a reading beyond
  the plane (by more than `dist`) crossed the plane, between the floor and `top`: the plane
  is open there (a doorway, the room beyond a counter, the space above a cabinet).
- Along the plane, on cells of COVER_CELL: a cell is solid where the face has readings and
  at most `max_beyond` crossings per reading, open where it has more (an open run shorter
  than MIN_OPENING is closed: stray readings seen past it). The face's
  stretches are the runs of cells that are not open, trimmed to solid cells at both ends.
- A stretch is a wall when its readings span the wall bounds (`min_length` along it,
  `min_height` in z, `min_area` of cells along it x height), reach `top` - 0.5 m, no more
  than `max_beyond` rays crossed the plane over its readings (their TOP_PCT-th percentile of
  height, per COVER_CELL along it) per reading in their top TOP_BAND
  (a wall reaches the ceiling; a wardrobe's top has the wall behind it seen over it), and no
  other such face looking the same way lies behind it (away from its
  cameras) within `behind` along half its length (a wardrobe before a wall). On a plane
  that holds such a wall, shorter stretches of at least MIN_STUB count too (the wall beside
  a doorway).

A single room's plane of readings inside it (a counter front, a table side, a cabinet) has
readings beyond it seen over or past it, or stays low: no wall is invented there. The faces
of a wall the bounding walls already hold (pointwalls.py) are left to them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from stages.common.classes import WALL_NAME
from stages.common.rows import unique_rows
from stages.semantics.pointwalls import COVER_CELL, PointWallOptions

ABOVE_FLOOR = 0.1  # metres: readings this close to the floor are floor, not a wall's
REACH_BELOW_TOP = 0.5  # metres: a wall's readings reach at least `top` minus this
MAX_CANDIDATES = 40  # offsets tried per axis and side, the most supported first
MIN_OPENING = 0.4  # metres: a shorter open run between solid cells is closed (stray readings)
MIN_STUB = 0.3  # metres: on a plane that holds a wall, a stretch this long is one too
TOP_BAND = 0.3  # metres: rays crossing over a face weigh against its readings this near its top
TOP_PCT = 90.0  # a face's top, per cell along it: this percentile of its readings' heights


def inner_walls(
    points: np.ndarray,
    cams: np.ndarray,
    directions: np.ndarray,
    floor_z: float,
    opt: PointWallOptions,
    behind: float,
    have: Sequence[dict] = (),
) -> list[dict]:
    """The faces of the walls among the points that no ray crossed (see the module doc).

    Args:
        points: [N, 3] readings (world, z up). cams: [N, 3] the centre of the camera each
            reading was taken from.
        directions: [>= 2, 3] the room's horizontal directions (the first two: its axes).
        floor_z: the floor's height. opt: the wall bounds (pointwalls.py).
        behind: metres: a face with another looking the same way behind it this close,
            along half its length, is no wall (0: off).
        have: walls found already (plane dicts): a face within 2 dist of one is theirs.

    Returns:
        plane dicts as pointwalls.point_walls gives (kind "wall", normal facing the cameras
        that saw it, d, area_m2, box [s0, z0, s1, z1], span, source "points").
    """
    faces = []
    high = points[:, 2] > floor_z + ABOVE_FLOOR
    for n in directions[:2]:
        n = np.asarray(n, np.float64)
        s, cs = points @ n, cams @ n
        for side in (1.0, -1.0):  # the faces seen from the cameras on either side
            seen = high & (side * (cs - s) > opt.dist)
            for s0 in _candidates(s[seen], opt.dist):
                faces += _faces(points, cams, n, s0, side, floor_z, opt)
    faces = _distinct(faces, opt.dist)
    faces = [f for f in faces if not any(_near(f, h, 2 * opt.dist) for h in have)]
    keep = [not _behind(f, [g for g in faces if g is not f] + list(have), behind) for f in faces]
    return [f["wall"] for f, k in zip(faces, keep, strict=True) if k]


def _candidates(s: np.ndarray, dist: float) -> np.ndarray:
    """Offsets along an axis where readings s [N] pile up: local maxima of the count within
    dist, over 2 dist either side, the most supported first (at most MAX_CANDIDATES)."""
    if len(s) == 0:
        return np.zeros(0)
    step = dist / 2.0
    edges = np.arange(s.min() - dist, s.max() + dist + step, step)
    h = np.histogram(s, edges)[0].astype(np.float64)
    w = int(round(dist / step / 2))  # window: +-dist / 2
    win = np.convolve(h, np.ones(2 * w + 1), mode="same")
    r = int(round(2 * dist / step))  # suppression radius in bins: 2 dist
    pad = np.pad(win, r, constant_values=-1.0)
    local = np.stack([pad[i : i + len(win)] for i in range(2 * r + 1)]).max(axis=0)
    peak = np.flatnonzero((win >= local) & (win >= 10))
    peak = peak[np.argsort(-win[peak], kind="stable")][:MAX_CANDIDATES]
    return (edges[peak] + step / 2.0).astype(np.float64)


def _faces(
    p: np.ndarray,
    cams: np.ndarray,
    n: np.ndarray,
    s0: float,
    side: float,
    floor_z: float,
    opt: PointWallOptions,
) -> list[dict]:
    """The stretches of the face of plane n.x = s0 seen from the cameras on `side` (+1: where
    n.x > s0) that are walls, as {"wall": plane dict, "s": s0, "n": normal, "lo", "hi" (along
    the normal's axis)}."""
    along = np.array([-n[1], n[0], 0.0])
    s, cs = p @ n - s0, cams @ n - s0  # [N] offsets of the readings and their cameras
    mine = side * cs > opt.dist  # taken from this side
    near = mine & (np.abs(s) < opt.dist) & (p[:, 2] > floor_z + ABOVE_FLOOR)
    if near.sum() < 10:
        return []
    shift = float(np.median(s[near]))  # the plane through them
    s0, s, cs = s0 + shift, s - shift, cs - shift
    on = mine & (np.abs(s) < opt.dist) & (p[:, 2] > floor_z + ABOVE_FLOOR)
    if on.sum() < 10:
        return []
    cross = mine & (side * s < -opt.dist)  # beyond the plane, seen through it
    t = cs[cross] / (cs[cross] - s[cross])  # where the ray from the camera meets the plane
    x = cams[cross] + t[:, None] * (p[cross] - cams[cross])
    over = np.stack([x @ along, x[:, 2]], 1)  # [M, 2] the crossings (along, z), any height
    x = x[(x[:, 2] > floor_z + ABOVE_FLOOR) & (x[:, 2] < opt.top)]
    u_on, u_x = p[on] @ along, x @ along
    lo_u = min(u_on.min(), u_x.min()) if len(u_x) else u_on.min()
    edges = np.arange(lo_u, max(u_on.max(), u_x.max() if len(u_x) else lo_u) + 2 * COVER_CELL,
                      COVER_CELL)  # fmt: skip
    n_on = np.histogram(u_on, edges)[0]
    n_x = np.histogram(u_x, edges)[0]
    solid = (n_on > 0) & (n_x <= opt.max_beyond * n_on)
    open_ = _bridged(n_x > opt.max_beyond * n_on)
    runs = []
    i = 0
    while i < len(solid):
        if not solid[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(solid) and not open_[j + 1]:
            j += 1
        while not solid[j]:
            j -= 1
        runs.append((edges[i], edges[j + 1]))
        i = j + 1
    walls = [_stretch(p[on], u_on, over, a, b, n, s0, side, floor_z, opt, 0.0) for a, b in runs]
    if not any(walls):
        return []
    # the plane holds a wall: its shorter stretches (beside a doorway, by a corner) count too
    stub = [_stretch(p[on], u_on, over, a, b, n, s0, side, floor_z, opt, MIN_STUB) for a, b in runs]
    return [wt for w, t in zip(walls, stub, strict=True) if (wt := w or t)]


def _bridged(open_: np.ndarray) -> np.ndarray:
    """open_ [C] with the runs shorter than MIN_OPENING between other cells closed: a few
    stray readings seen past a wall are no doorway."""
    out = open_.copy()
    i, short = 0, max(int(round(MIN_OPENING / COVER_CELL)), 1)
    while i < len(out):
        if not out[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(out) and out[j + 1]:
            j += 1
        if j - i + 1 < short and i > 0 and j + 1 < len(out):
            out[i : j + 1] = False
        i = j + 1
    return out


def _stretch(
    q: np.ndarray,
    u: np.ndarray,
    over: np.ndarray,
    a: float,
    b: float,
    n: np.ndarray,
    s0: float,
    side: float,
    floor_z: float,
    opt: PointWallOptions,
    stub: float,
) -> dict | None:
    """The stretch [a, b] along the face (readings q [K, 3] at u [K] along it; the rays'
    crossings over [M, 2] as (along, z)) as a face dict, or None when it fails the wall
    bounds (stub > 0: a stub of at least this length, its area in proportion, on a plane that
    holds a wall) or rays crossed it over its readings (it stands lower than the room)."""
    k = (u >= a) & (u <= b)
    if k.sum() < 10:
        return None
    # per cell along it: its readings' top, the readings near it, the rays crossing over it
    cell = np.floor((u[k] - a) / COVER_CELL).astype(np.int64)
    m = int(cell.max()) + 1
    top_z = _top(cell, q[k, 2], m)
    band = int((q[k, 2] > top_z[cell] - TOP_BAND).sum())
    x = over[(over[:, 0] >= a) & (over[:, 0] < a + m * COVER_CELL)]
    xc = np.floor((x[:, 0] - a) / COVER_CELL).astype(np.int64)
    if int((x[:, 1] > top_z[xc] + opt.dist).sum()) > opt.max_beyond * band:
        return None
    lo_u, hi_u = np.percentile(u[k], [5, 95])
    lo_z, hi_z = np.percentile(q[k, 2], [5, 95])
    cells = unique_rows(np.floor(np.stack([u[k], q[k, 2]], 1) / COVER_CELL).astype(np.int64))[0]
    if (
        hi_u - lo_u < (stub or opt.min_length)
        or hi_z - lo_z < opt.min_height
        or len(cells) * COVER_CELL**2 < opt.min_area * (stub or opt.min_length) / opt.min_length
        or q[k, 2].max() < opt.top - REACH_BELOW_TOP
    ):
        return None
    normal = side * n  # facing the cameras that saw it: normal.x + d = 0 on the plane
    # the segmentation's axis along a plane of normal m is (-m_y, m_x): side * along here
    box_s = sorted([side * a, side * b])
    top = max(float(q[k, 2].max()), opt.top)
    wall = {
        "kind": WALL_NAME,
        "normal": [round(float(x), 4) for x in normal],
        "d": round(float(-side * s0), 4),
        "area_m2": round(len(cells) * COVER_CELL**2, 3),
        "triangles": 0,
        "box": [round(box_s[0], 4), round(floor_z, 4), round(box_s[1], 4), round(top, 4)],
        "span": [round(float(hi_u - lo_u), 3), round(float(hi_z - lo_z), 3)],
        "source": "points",
        "dist": opt.dist,
    }
    return {"wall": wall, "n": normal, "s": float(side * s0), "lo": box_s[0], "hi": box_s[1]}


def _top(cell: np.ndarray, z: np.ndarray, m: int) -> np.ndarray:
    """Per cell 0..m-1 the TOP_PCT-th percentile of the z [K] of its readings (cell [K]), -inf
    where none: a ceiling or a floor crossing the plane adds a strip too thin to move it."""
    order = np.lexsort((z, cell))
    c, zs = cell[order], z[order]
    start = np.searchsorted(c, np.arange(m))
    count = np.bincount(c, minlength=m)
    pick = start + np.floor((count - 1) * TOP_PCT / 100.0).astype(np.int64)
    return np.where(count > 0, zs[np.clip(pick, 0, len(zs) - 1)], -np.inf)


def _distinct(faces: list[dict], dist: float) -> list[dict]:
    """The faces less those another face (found earlier, from a better supported candidate)
    already holds: looking the same way, within dist / 2, overlapping."""
    out: list[dict] = []
    for f in faces:
        if not any(
            float(f["n"] @ g["n"]) > 0.99
            and abs(f["s"] - g["s"]) < dist / 2
            and min(f["hi"], g["hi"]) > max(f["lo"], g["lo"])
            for g in out
        ):
            out.append(f)
    return out


def _plane_of(w: dict) -> tuple[np.ndarray, float, float, float]:
    """(unit normal, offset along it, box along it lo, hi) of a plane dict."""
    normal = np.asarray(w["normal"], np.float64)
    return normal, -float(w["d"]), float(w["box"][0]), float(w["box"][2])


def _near(f: dict, w: dict, dist: float) -> bool:
    """Whether face f lies on wall w: parallel (either way), within dist, overlapping."""
    nw, sw, lo, hi = _plane_of(w)
    c = float(f["n"] @ nw)
    if abs(c) < np.cos(np.radians(15.0)):
        return False
    sign = 1.0 if c > 0 else -1.0
    a, b = sorted([sign * lo, sign * hi])
    overlap = min(f["hi"], b) - max(f["lo"], a)
    return abs(f["s"] - sign * sw) < dist and overlap > 0


def _behind(f: dict, others: list[dict], behind: float) -> bool:
    """Whether another face or wall looking the same way lies behind f (away from the
    cameras that saw it) by 2 cm to `behind` along at least half f's length."""
    if behind <= 0:
        return False
    for g in others:
        ng, sg, lo, hi = (g["n"], g["s"], g["lo"], g["hi"]) if "n" in g else _plane_of(g)
        if float(f["n"] @ ng) < np.cos(np.radians(15.0)):
            continue
        off = sg - f["s"]  # along f's normal (towards its cameras): > 0 is behind
        # with n.x + d = 0 on a plane, s = n.x = -d; behind f lies at a smaller n.x
        if 0.02 <= -off <= behind and min(f["hi"], hi) - max(f["lo"], lo) >= 0.5 * (
            f["hi"] - f["lo"]
        ):
            return True
    return False

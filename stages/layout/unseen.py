"""Room outlines closed over space no view saw as a surface follow what the views saw: a
convex corner between two unseen edges is cut back to the room's cells, and so is a recess in
the middle of an unseen edge (the shortest Manhattan outline round the seen floor on the plan
grid, as in Cabral & Furukawa, CVPR 2014, where it runs over unseen space; along seen walls
the traced outline stays). Unseen space between two rooms of one home is not cut: beyond it
lies the other room, so it belongs to one of them (the room stays a rectangle there)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from shapely import contains_xy
from shapely.geometry import Polygon, box
from shapely.geometry.polygon import orient

from stages.common.capture import UNKNOWN
from stages.layout.extract import Frame

NOTCH_MIN = 0.5  # metres: the least side of a corner cut off an outline over unseen space
NOTCH_EMPTY = 0.9  # share of a cut-off corner that must lie outside the room's cells
NEIGHBOUR_REACH = 0.5  # metres: another room this close beyond a cut's edge keeps the cut
#                       (an inner wall's band and its ragged faces; the 3-room home's are
#                       0.12 m, its photos' faces up to 0.2 m apart)
NEIGHBOUR_SHARE = 0.5  # share of a cut's edge that must face another room within the reach
BETWEEN_UNSEEN = 0.5  # least share of unseen cells in a step filled between two rooms (the
#                      3-room home from photos: 0.72 and 0.90 in its two steps)
BETWEEN_WALL = 0.15  # most share of wall cells there (0.04 and 0.09): no wall runs through it
BETWEEN_FACE = 0.2  # metres from a side facing another room within which wall cells are that
#                    partition's ragged face, not a wall through the step (the 3-room home
#                    from photos on the walk that looks down 20-35 degrees: all 593 wall
#                    cells of its step by the partition lie within 0.2 m of it, 18.6 % of
#                    the step, 0 % past that band)
RECESS_MIN = 1.0  # metres: the least width of a recess in an open side (0.84 m on the 3-room
#                  home from photos was floor the photos' mesh missed, not the room's edge)


def notched(
    poly: np.ndarray,
    mask: np.ndarray,
    fr: Frame,
    seen: Callable[[np.ndarray, np.ndarray], bool],
    others: np.ndarray | None = None,
) -> np.ndarray:
    """The outline poly (frame xy, counter-clockwise, edges along the frame's axes) with each
    convex corner between two edges no view saw as a surface (`seen`(a, b) false for both)
    cut back to the room's cells (`mask`, the frame's grid): the largest rectangle at the
    corner, at least NOTCH_MIN on each side and at most 90 % of either edge, with at least
    NOTCH_EMPTY of it outside the mask, is cut off: three corners for one. An outline closed
    over open sides is a Manhattan polygon round what the views saw, not the box of it.

    A corner whose cut would face another room's cells (`others`, the frame's grid) across
    either of its two edges, within NEIGHBOUR_REACH along NEIGHBOUR_SHARE of the edge, stays:
    the unseen space lies inside the home, between two rooms, not beyond an open side."""
    cell = fr.grid.cell
    flags = [seen(poly[i], poly[(i + 1) % len(poly)]) for i in range(len(poly))]
    least = int(np.ceil(NOTCH_MIN / cell))
    i = 0
    while i < len(poly):
        c, prev, nxt = poly[i], poly[i - 1], poly[(i + 1) % len(poly)]
        e0, e1 = c - prev, nxt - c
        l0, l1 = float(np.linalg.norm(e0)), float(np.linalg.norm(e1))
        convex = e0[0] * e1[1] - e0[1] * e1[0] > 0
        axis = abs(e0 @ e1) < 1e-6 * l0 * l1  # a right angle
        if flags[i - 1] or flags[i] or not convex or not axis:
            i += 1
            continue
        u, v = e1 / l1, -e0 / l0  # along the next edge, back along the previous one
        nw, nh = int(0.9 * l1 / cell), int(0.9 * l0 / cell)
        if min(nw, nh) < least:
            i += 1
            continue
        jw, jh = np.meshgrid(np.arange(nw) + 0.5, np.arange(nh) + 0.5)
        pts = c + (jw[..., None] * u + jh[..., None] * v) * cell  # [nh, nw, 2]
        row, col, ok = fr.grid.cell_of(pts.reshape(-1, 2))
        full = (mask[row, col] & ok).reshape(nh, nw).astype(np.int64)
        count = full.cumsum(0).cumsum(1)  # room cells in the rectangle of (h + 1, w + 1)
        size = np.outer(np.arange(1, nh + 1), np.arange(1, nw + 1))
        good = (1 - count / size >= NOTCH_EMPTY) & (size > 0)
        good[: least - 1] = False
        good[:, : least - 1] = False
        if not good.any():
            i += 1
            continue
        ih, iw = np.unravel_index(np.argmax(np.where(good, size, 0)), size.shape)
        h, w = (ih + 1) * cell, (iw + 1) * cell
        if others is not None and (
            _faces(others, fr, c, v, h, -u) or _faces(others, fr, c, u, w, -v)
        ):
            i += 1
            continue
        step = [c + h * v, c + h * v + w * u, c + w * u]
        poly = (
            np.concatenate([poly[:i], step, poly[i + 1 :]]) if i else np.array([*step, *poly[1:]])
        )
        flags = flags[:i] + [False, False] + flags[i:]
        i += 3
    return poly


def filled_between(poly: np.ndarray, fr: Frame, others: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """The outline poly (frame xy, counter-clockwise, edges along the frame's axes) with each
    step cut out of its bounding box filled where the step is space no view saw between this
    room and another: at least NOTCH_MIN on each side, at least BETWEEN_UNSEEN of its cells
    unknown, none of another room's (`others`), facing another room across one of its sides
    on the box's edge (within NEIGHBOUR_REACH), and at most BETWEEN_WALL of its cells wall
    farther than BETWEEN_FACE from those sides (nearer, they are the partition's own face).
    Inside a home the floor by an unseen inner wall is the room's, up to the line of its seen
    walls; beyond an open side of the home (nothing faces it) the outline keeps what the
    views saw."""
    if others is None or not others.any():
        return poly
    cell = fr.grid.cell
    room = Polygon(poly)
    bx0, by0, bx1, by1 = room.bounds
    missing = box(bx0, by0, bx1, by1).difference(room)
    filled = room
    xy = fr.grid.centers()  # [H, W, 2] frame xy of every cell
    for g in getattr(missing, "geoms", [missing]):
        x0, y0, x1, y1 = g.bounds
        if g.is_empty or min(x1 - x0, y1 - y0) < NOTCH_MIN:
            continue
        inside = contains_xy(g, xy[..., 0], xy[..., 1])
        if not inside.any() or others[inside].any():
            continue
        if (fr.labels[inside] == UNKNOWN).mean() < BETWEEN_UNSEEN:
            continue
        e = cell / 2  # the sides of the step on the box's edge, each with its outward normal
        sides = [
            (np.array([x0, y0]), np.array([0.0, 1.0]), y1 - y0, np.array([-1.0, 0.0]), x0 - bx0),
            (np.array([x1, y0]), np.array([0.0, 1.0]), y1 - y0, np.array([1.0, 0.0]), bx1 - x1),
            (np.array([x0, y0]), np.array([1.0, 0.0]), x1 - x0, np.array([0.0, -1.0]), y0 - by0),
            (np.array([x0, y1]), np.array([1.0, 0.0]), x1 - x0, np.array([0.0, 1.0]), by1 - y1),
        ]
        facing = [(a, out) for a, u, n_, out, gap in sides
                  if gap < e and _faces(others, fr, a, u, n_, out)]  # fmt: skip
        if not facing:
            continue
        # wall cells within BETWEEN_FACE of a facing side are that partition's face
        at = xy[inside]  # [K, 2]
        face = np.zeros(len(at), bool)
        for a, out in facing:
            face |= (at - a) @ out > -BETWEEN_FACE
        if wall[inside][~face].sum() > BETWEEN_WALL * len(at):
            continue
        filled = filled.union(g)
    if filled is room or filled.geom_type != "Polygon":
        return poly
    out = orient(filled.simplify(0.0), 1.0)
    return np.asarray(out.exterior.coords)[:-1]


def _faces(
    others: np.ndarray, fr: Frame, a: np.ndarray, along: np.ndarray, length: float, out: np.ndarray
) -> bool:
    """Whether the edge from a, `length` along the unit vector `along`, has another room's
    cells (`others`) within NEIGHBOUR_REACH beyond it (the unit vector `out`) along at least
    NEIGHBOUR_SHARE of its steps."""
    cell = fr.grid.cell
    t = (np.arange(max(1, int(length / cell))) + 0.5) * cell
    s = (np.arange(max(1, int(NEIGHBOUR_REACH / cell))) + 0.5) * cell
    pts = a + t[None, :, None] * along + s[:, None, None] * out  # [S, T, 2]
    row, col, ok = fr.grid.cell_of(pts.reshape(-1, 2))
    hit = (others[row, col] & ok).reshape(len(s), len(t))
    return bool(hit.any(0).mean() >= NEIGHBOUR_SHARE)


def _largest_run(depth: np.ndarray, least: int) -> tuple[int, int, int]:
    """The largest rectangle under the histogram `depth` [T] (cells) at least `least` wide
    and deep: (start, width, height) in cells; width 0 when there is none."""
    best = (0, 0, 0)
    for h in np.unique(depth[depth >= least]):
        on = np.concatenate([[0], (depth >= h).astype(np.int8), [0]])
        edges = np.flatnonzero(np.diff(on))
        starts, stops = edges[::2], edges[1::2]
        k = int(np.argmax(stops - starts))
        w = int(stops[k] - starts[k])
        if w >= least and w * h > best[1] * best[2]:
            best = (int(starts[k]), w, int(h))
    return best


def recessed(
    poly: np.ndarray,
    mask: np.ndarray,
    fr: Frame,
    seen: Callable[[np.ndarray, np.ndarray], bool],
    others: np.ndarray | None = None,
) -> np.ndarray:
    """The outline poly (frame xy, counter-clockwise) with a recess in each edge along the
    frame's axes that no view saw as a surface (`seen`(a, b) false) where the room's cells
    (`mask`) stop short of it in its middle: the largest rectangle on the edge, at least
    RECESS_MIN wide and NOTCH_MIN deep, NOTCH_MIN or more from both its ends, whose cells
    lie outside the mask (each step along the edge empty with its neighbours across), is cut
    off: four corners more. An open side is drawn where the views stopped along it, not straight
    across the gap. A recess facing another room's cells (`others`) across the edge, as
    notched() asks of a corner, stays: the unseen space lies between two rooms (the 3-room
    home from photos: the strip between a cabinet and the partition behind it, which no
    view fused, cut a recess 1.9 m wide into its room)."""
    cell = fr.grid.cell
    least = int(np.ceil(NOTCH_MIN / cell))
    out = []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        out.append(a)
        e = b - a
        length = float(np.linalg.norm(e))
        if length < 3 * NOTCH_MIN or min(abs(e[0]), abs(e[1])) > 1e-6 * length or seen(a, b):
            continue
        u = e / length
        v = np.array([-u[1], u[0]])  # into the room
        n_t = int(length / cell)
        n_s = int(min(length, 5.0) / cell)
        if n_s <= least:  # too few rows to hold a recess NOTCH_MIN deep (a world not in metres)
            continue
        t = (np.arange(n_t) + 0.5) * cell
        s = (np.arange(n_s) + 0.5) * cell
        pts = a + t[None, :, None] * u + s[:, None, None] * v  # [S, T, 2]
        row, col, ok = fr.grid.cell_of(pts.reshape(-1, 2))
        full = (mask[row, col] & ok).reshape(n_s, n_t)
        # how deep each step along the edge stays empty: the first row where it or a
        # neighbour along the edge is a room cell
        filled = np.stack([np.roll(full, k, axis=1) for k in (-1, 0, 1)]).any(0)
        depth = np.where(filled.any(0), filled.argmax(0), n_s)
        depth[:least] = 0  # away from the edge's ends: corners are notched()'s
        depth[-least:] = 0
        start, w, h = _largest_run(depth, least)
        if w * cell < RECESS_MIN or w * cell > 0.9 * length:
            continue
        p0 = a + start * cell * u
        if others is not None and _faces(others, fr, p0, u, w * cell, -v):
            continue
        p1 = a + (start + w) * cell * u
        out += [p0, p0 + h * cell * v, p1 + h * cell * v, p1]
    return np.array(out)

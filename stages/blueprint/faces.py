"""Wall cells behind the wall's face only: the plan's convention for the cell a face crosses.

A plan cell is wall when its centre lies inside the wall, behind the face the views saw (the
ground-truth raster of a procedural room casts one ray down through each cell centre). The
points of a face lie on its surface, so the cell that holds them is wall or not by where the
face crosses it: a face 3 mm behind a cell's centre leaves that cell on the room's side, yet
the field, fitted to the face's points, draws it wall, and draws wall over cells in front of
the face where few points lie (floor next to a wall is hidden from most views).

Per plan cell holding wall points, the face is the line through their mean with the normal
of the wall points round it (the least direction of their spread over `window` cells); the
normal faces the room, the side the views' rays came from (observed.npz "free"). Each wall
cell of the plan is judged by the nearest cell holding wall points: when its centre lies in
front of that cell's face it is made floor. A face that is no thin line (a corner, a band of
noisy readings) or has free cells on both sides (stereo reads through walls) judges nothing:
the field's label stands there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from stages.common.blueprint import Grid, observed_layer
from stages.common.capture import UNKNOWN
from stages.common.classes import FLOOR_NAME, WALL_NAME, ids_named

FLAT = 0.2  # a face's spread across / along (eigenvalue ratio) above which it is no line
ONE_SIDED = 0.25  # a face's free cells behind it at most this share of those in front
THIN = 0.5  # cells: the spread (standard deviation) across a face above which it is left


def face_frames(
    grid: Grid, xy: np.ndarray, free: np.ndarray, window: int = 2, side: int = 5
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(face, point [H, W, 2], normal [H, W, 2], held) of the wall points xy [N, 2] on `grid`.

    face: bool [H, W], the cells holding wall points whose face is known; point: the mean
    of the wall points within `window` cells (a thick cloud of noisy points gives its middle
    line, not a line per cell); normal: the unit normal of the points within `window` cells,
    pointing to the side where more free cells (bool [H, W]) lie within `side` cells, when
    at most ONE_SIDED as many lie on the other; held: bool [H, W], the cells holding wall
    points.
    """
    h, w = grid.shape
    row, col, on = grid.cell_of(xy)
    row, col, p = row[on], col[on], np.asarray(xy, np.float64)[on]
    idx = row * w + col
    centres = grid.centers()  # [H, W, 2]
    d = p - centres.reshape(-1, 2)[idx]  # [N, 2] offsets from the cell centre: small numbers
    n = np.bincount(idx, minlength=h * w).reshape(h, w).astype(np.float64)
    sums = [
        np.bincount(idx, v, minlength=h * w).reshape(h, w)
        for v in (d[:, 0], d[:, 1], d[:, 0] ** 2, d[:, 0] * d[:, 1], d[:, 1] ** 2)
    ]
    has = n > 0
    # moments of the points within `window` cells about this cell's centre: a neighbour's
    # offsets are moved by its centre's (dj cell, -di cell) from ours
    m: dict[str, float | np.ndarray] = dict.fromkeys(("n", "x", "y", "xx", "xy", "yy"), 0.0)
    for di in range(-window, window + 1):
        for dj in range(-window, window + 1):
            ox, oy = dj * grid.cell, -di * grid.cell
            cnt, sx, sy, sxx, sxy, syy = (_shift(a, -di, -dj) for a in (n, *sums))
            m["n"] = m["n"] + cnt
            m["x"] = m["x"] + sx + ox * cnt
            m["y"] = m["y"] + sy + oy * cnt
            m["xx"] = m["xx"] + sxx + 2 * ox * sx + ox * ox * cnt
            m["xy"] = m["xy"] + sxy + ox * sy + oy * sx + ox * oy * cnt
            m["yy"] = m["yy"] + syy + 2 * oy * sy + oy * oy * cnt
    k = np.maximum(m["n"], 1)
    mx, my = m["x"] / k, m["y"] / k  # the mean of the points round, from the cell's centre
    point = centres + np.stack([mx, my], -1)
    cxx, cxy, cyy = m["xx"] / k - mx * mx, m["xy"] / k - mx * my, m["yy"] / k - my * my
    # the least eigenvector of [[cxx, cxy], [cxy, cyy]]
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    lo, hi = tr / 2 - disc, tr / 2 + disc
    nx, ny = cxy, lo - cxx  # (A - lo I) v = 0  ->  v = (cxy, lo - cxx) or (lo - cyy, cxy)
    alt = np.hypot(nx, ny) < 1e-12
    nx = np.where(alt, lo - cyy, nx)
    ny = np.where(alt, cxy, ny)
    norm = np.hypot(nx, ny)
    # a line, and a thin one: points spread across it by more than half a cell (stereo's
    # readings; the two faces of a partition merged into one band) cannot tell on which
    # side of a cell's centre the face passes
    thin = lo <= (THIN * grid.cell) ** 2
    line = has & (m["n"] >= 3) & (norm > 0) & thin & (lo <= FLAT * np.maximum(hi, 1e-12))
    normal = np.zeros((h, w, 2))
    normal[line, 0] = nx[line] / norm[line]
    normal[line, 1] = ny[line] / norm[line]
    # orient: the free cells (not holding wall points) within `side` cells count on either
    # side; the face turns to the side with more. A face with free cells on both sides
    # (stereo reads through walls; rays graze a thin partition) has no known room side
    f = (free & ~has).astype(np.float64)
    ahead, behind = np.zeros((h, w)), np.zeros((h, w))
    off = mx * normal[..., 0] + my * normal[..., 1]
    for di in range(-side, side + 1):
        for dj in range(-side, side + 1):
            if di == 0 and dj == 0:
                continue
            fx, fy = dj * grid.cell, -di * grid.cell  # the free cell's centre, relative
            s = fx * normal[..., 0] + fy * normal[..., 1] - off
            g = _shift(f, -di, -dj)
            ahead += g * (s > 0)
            behind += g * (s < 0)
    more, fewer = np.maximum(ahead, behind), np.minimum(ahead, behind)
    face = line & (more > 0) & (fewer <= ONE_SIDED * more)
    normal[behind > ahead] *= -1
    normal[~face] = 0
    return face, point, normal, has


def behind_faces(
    labels: np.ndarray,
    classes: dict[int, str],
    grid: Grid,
    xy: np.ndarray,
    label: np.ndarray,
    observed: Path,
    margin: float = 0.0,
    fill: str = "floor",
) -> tuple[np.ndarray, int]:
    """wall_fronts of the plan labels [H, W] with the wall points among the points xy
    [N, 2] (world metres) labelled `label` [N] and the free cells of observed.npz (the plan
    unchanged when the file has none)."""
    free = observed_layer(observed, "free", grid.shape)
    if free is None:
        return labels, 0
    wall = np.isin(label, ids_named(classes, WALL_NAME))
    return wall_fronts(labels, classes, grid, np.asarray(xy)[wall, :2], free > 0, margin, fill)


def wall_fronts(
    labels: np.ndarray,
    classes: dict[int, str],
    grid: Grid,
    xy: np.ndarray,
    free: np.ndarray,
    margin: float = 0.0,
    fill: str = "floor",
) -> tuple[np.ndarray, int]:
    """(The plan [H, W] with every wall cell whose centre lies more than `margin` cells in
    front of its nearest face made floor, or the nearest class that is not wall, how many
    cells changed).

    In front of a face is the room's open space: the field drew wall there from the face's
    own points (a top view keeps the wall's points, the highest, in the cells that hold
    them and drops the floor's). fill "floor": the strip between a wall and a bed or sofa
    standing a little off it is floor (home3 with sensor depth and free_floor: fwIoU 89.46
    with floor, 88.01 with the nearest class: bed 92.4 and sofa 83.4 against 96.7 and 88.3;
    measured before faces needed one-sided free cells). fill "nearest": the class of the
    nearest cell the field drew neither wall nor unknown, so furniture standing against the
    wall reaches it (real rooms from photos, blueprint.blunf.wall_face_fill). A plan without
    a floor class gets the nearest class that is not wall either way.

    xy [N, 2]: the wall points (world metres); free: bool [H, W], the cells rays crossed.
    margin: 0 cuts to the ground truth's convention; 0.5 keeps the cell the face crosses (its
    centre within half a cell of the face) and cuts only the cells wholly in front of it.
    """
    wall = np.isin(labels, ids_named(classes, WALL_NAME))
    if not wall.any() or len(xy) == 0:
        return labels, 0
    face, point, normal, held = face_frames(grid, xy, free)
    if not face.any():
        return labels, 0
    # the nearest cell holding wall points decides; when its face has no known room side (or
    # is no thin line) the field's label stands
    _, (fr, fc) = ndimage.distance_transform_edt(~held, return_indices=True)
    centres = grid.centers()
    s = ((centres - point[fr, fc]) * normal[fr, fc]).sum(-1)  # [H, W] metres, + = in front
    front = wall & face[fr, fc] & (s > margin * grid.cell)
    other = ~wall & (labels != UNKNOWN)
    if not front.any() or not other.any():
        return labels, 0
    out = labels.copy()
    floor = ids_named(classes, FLOOR_NAME)
    if floor and fill == "floor":
        out[front] = floor[0]
    else:
        _, (r, c) = ndimage.distance_transform_edt(~other, return_indices=True)
        out[front] = labels[r[front], c[front]]
    return out, int(front.sum())


def _shift(a: np.ndarray, di: int, dj: int) -> np.ndarray:
    """b[r, c] = a[r - di, c - dj] (zero where that falls outside)."""
    b = np.zeros_like(a)
    h, w = a.shape
    rs, rd = (slice(0, h - di), slice(di, h)) if di >= 0 else (slice(-di, h), slice(0, h + di))
    cs, cd = (slice(0, w - dj), slice(dj, w)) if dj >= 0 else (slice(-dj, w), slice(0, w + dj))
    b[rd, cd] = a[rs, cs]
    return b

"""What the views observed on the plan grid: cells near a projected point, and cells the rays
crossed on their way to the surfaces they met (free space).

A cell is *near* (seen) when a projected point lies within `radius` metres of its centre. A
cell is *free* when the plan projection of some camera ray (camera centre to the point it
met) passes over it: a view looked through the space above it. Neither reads the grid's
extent. The room's extent (*inside*) is what the views observed or looked through, closed
over small gaps, its holes filled; within it the plan is *labelled* up to `fill_radius` of a
point (BluNF fills the gaps between observations) and left unknown farther off: free space
above a floor no view saw (the camera's own footprint) is in the room but not guessed.

Of the free cells that hold no point, *past* counts the views that looked past the point half
the cameras' height above the cell's floor (looked_past): nothing tall stands there, so the
cell is floor no view saw (round the cameras' path), not the inside of an object whose top
no view saw (blueprint.blunf.free_floor reads it).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy import ndimage

from stages.common.blueprint import Grid
from stages.common.camera import depth_at

# cells between samples along a ray's plan projection (kitchen: 0.5 took 3x the time for 3
# cells more inside, of 37 076)
RAY_STEP = 1.0
RAY_CHUNK = 1 << 18  # samples along rays held at once: memory bounded, whatever the views


def point_distance(grid: Grid, xy: np.ndarray) -> np.ndarray:
    """Metres from each cell's centre to the nearest point of xy [N, 2] (world metres), read
    to the nearest point's cell centre and made an upper bound (a point lies up to half a
    cell's diagonal off its cell's centre). float64 [H, W], inf without points."""
    row, col, inside = grid.cell_of(xy)
    occ = np.zeros(grid.shape, bool)
    occ[row[inside], col[inside]] = True
    if not occ.any():
        return np.full(grid.shape, np.inf)
    return (ndimage.distance_transform_edt(~occ) + 0.5 * np.sqrt(2.0)) * grid.cell


def ray_cells(grid: Grid, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Cells crossed by the plan segments start [R, 2] -> end [R, 2] (world metres), sampled
    every RAY_STEP cells. bool [H, W]. The rays go in runs of about RAY_CHUNK samples, so
    the samples held at once do not grow with the number of rays (views)."""
    out = np.zeros(grid.shape, bool)
    if len(start) == 0:
        return out
    seg = end - start  # [R, 2]
    n = np.ceil(np.linalg.norm(seg, axis=1) / (RAY_STEP * grid.cell)).astype(np.int64) + 1
    ends = np.cumsum(n)
    a = 0
    while a < len(n):  # rays a..b-1: about RAY_CHUNK samples (one ray at least)
        b = max(a + 1, int(np.searchsorted(ends, ends[a] - n[a] + RAY_CHUNK, "right")))
        _mark_rays(grid, start[a:b], seg[a:b], n[a:b], out)
        a = b
    return out


def _mark_rays(
    grid: Grid, start: np.ndarray, seg: np.ndarray, n: np.ndarray, out: np.ndarray
) -> None:
    """Set in `out` the cells of n [R] samples along each segment (start [R, 2], seg [R, 2])."""
    ray = np.repeat(np.arange(len(start)), n)  # [S] the ray of each sample
    first = np.cumsum(n) - n
    t = (np.arange(int(n.sum())) - first[ray]) / np.maximum(n[ray] - 1, 1)  # [S] in [0, 1]
    xy = start[ray] + t[:, None] * seg[ray]  # [S, 2]
    row, col, inside = grid.cell_of(xy)
    out[row[inside], col[inside]] = True


def observed(
    grid: Grid,
    xy: np.ndarray,
    cams: np.ndarray,
    view: np.ndarray,
    radius: float,
    ray_every: int,
    read: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(near, free, distance): bool [H, W], bool [H, W] and point_distance on `grid`.

    Args:
        grid: the plan grid.
        xy: [N, 2] world plan positions of the projected points.
        cams: [C, 2] world plan positions of the camera centres.
        view: [N] the view of each point (index into cams).
        radius: metres: a cell is near when a point lies this close.
        ray_every: every ray_every-th point gives a free-space ray (0 = none).
        read: bool [N] the points whose view read that far (points._read), or None for all:
            only those give rays. Where the fused surface has a hole (no view read a plain
            cabinet front), the depth runs through it to the wall behind; a ray there is no
            sign that the space was looked through.
    """
    dist = point_distance(grid, xy)
    near = dist <= radius
    if ray_every <= 0 or len(xy) == 0:
        return near, np.zeros(grid.shape, bool), dist
    pick = np.arange(0, len(xy), ray_every)
    if read is not None:  # the same rays less those not read (a new subsample would move
        pick = pick[read[pick]]  # the rays everywhere: the sensor home's plan by 0.3)
    return near, ray_cells(grid, cams[view[pick]], xy[pick]), dist


def room_inside(near: np.ndarray, free: np.ndarray, close_cells: int) -> np.ndarray:
    """The room's extent on the plan: what the views observed or looked through, closed over
    gaps up to 2 * close_cells cells and its holes filled. bool [H, W]."""
    obs = near | free
    if close_cells > 0:
        r = close_cells
        disk = np.hypot(*np.mgrid[-r : r + 1, -r : r + 1]) <= r
        obs = ndimage.binary_closing(np.pad(obs, r + 1), disk)[r + 1 : -r - 1, r + 1 : -r - 1]
    return ndimage.binary_fill_holes(obs)


# the column over an empty cell is tested this share of the cameras' median height above the
# floor: object tops lower than that are seen from the cameras' height (their cells hold
# points); a cell no view saw into yet some view looked past at this height has nothing
# standing on it that reaches it (3-room sensor home, with blueprint.blunf's nearest-point
# test: floor samples on 0 of the 2 596 empty cabinet cells rays crossed, was 1 494, and on
# 2 634 of the 7 262 empty floor cells the plan missed)
PAST_SHARE = 0.5
PAST_MARGIN = 2.5  # cells (0.05 m at 2 cm), plus PAST_SLACK of the distance: a reading this
PAST_SLACK = 0.02  # much farther than the point is a view looking past it (noise stays "at it")
PAST_CHUNK = 1 << 18  # cells projected at once per view


def past_height(cams_z: np.ndarray) -> float:
    """Metres above the floor (z = 0) at which the columns over empty cells are tested:
    PAST_SHARE of the cameras' median height; 0 when the cameras are not above the floor."""
    if len(cams_z) == 0:
        return 0.0
    return max(0.0, PAST_SHARE * float(np.median(cams_z)))


def looked_past(grid: Grid, cells: np.ndarray, views: Iterable, height: float) -> np.ndarray:
    """How many views looked past the point `height` metres above the centre of each cell of
    `cells` (bool [H, W]): the point lies in the view's frame, in front of the camera, and the
    view's depth there reads farther than the point (by PAST_MARGIN cells + PAST_SLACK of its
    distance: in the world's units, as the grid), and so does its own reading when it has one.
    uint16 [H, W], 0 off `cells`.

    Round the cameras' own path the floor lies below every frame, yet views across the room
    look past the space above it; an object's inside is never looked past, whether or not a
    view saw its top. The depth is the fused surface's, which is whole: where no view read
    anything (a plain cabinet front stereo found no match on) the surface has a hole and its
    depth is the wall or floor behind it. The view's own reading (the depth the fusion read,
    at its own resolution) tells a hole from space looked through: it must read past the point
    too, so a pixel it holds no reading at is no evidence (3-room photos home: the front of a
    cabinet seen only from 0.6 m had 2-7 views "looking past" its inside, and took floor).
    One view at a time, at most PAST_CHUNK cells at once: memory bounded by the plan, time
    linear in the views.

    Args:
        grid: the plan grid.
        cells: bool [H, W] the cells to test.
        views: (intrinsics, c2w [4, 4], depth [h, w] metres, 0 = no reading, and the view's
            own reading [h', w'] metres or None) per view.
        height: metres above the floor (z = 0).
    """
    out = np.zeros(grid.shape, np.uint16)
    r, c = np.nonzero(cells)
    if len(r) == 0 or not height > 0:
        return out
    xy = grid.centers()[r, c]  # [K, 2]
    pts = np.concatenate([xy, np.full((len(r), 1), height)], 1)  # [K, 3]
    count = np.zeros(len(r), np.int64)
    margin = PAST_MARGIN * grid.cell
    for intr, c2w, depth, reading in views:
        c2w = np.asarray(c2w, np.float64)
        maps = [(m, intr.scaled(m.shape[1], m.shape[0])) for m in (depth, reading) if m is not None]
        for a in range(0, len(r), PAST_CHUNK):
            p = pts[a : a + PAST_CHUNK]
            ok = np.ones(len(p), bool)
            for m, k in maps:
                d, z = depth_at(p, m, k.K, c2w, k.dist)
                ok &= (d > 0) & (d > z * (1 + PAST_SLACK) + margin)
            count[a : a + PAST_CHUNK] += ok
    out[r, c] = np.minimum(count, np.iinfo(np.uint16).max)
    return out

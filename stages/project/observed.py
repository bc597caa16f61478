"""What the views observed on the plan grid: cells near a projected point, and cells the rays
crossed on their way to the surfaces they met (free space).

A cell is *near* (seen) when a projected point lies within `radius` metres of its centre. A
cell is *free* when the plan projection of some camera ray (camera centre to the point it
met) passes over it: a view looked through the space above it. Neither reads the grid's
extent. The room's extent (*inside*) is what the views observed or looked through, closed
over small gaps, its holes filled; within it the plan is *labelled* up to `fill_radius` of a
point (BluNF fills the gaps between observations) and left unknown farther off: free space
above a floor no view saw (the camera's own footprint) is in the room but not guessed.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.common.blueprint import Grid

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
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(near, free, distance): bool [H, W], bool [H, W] and point_distance on `grid`.

    Args:
        grid: the plan grid.
        xy: [N, 2] world plan positions of the projected points.
        cams: [C, 2] world plan positions of the camera centres.
        view: [N] the view of each point (index into cams).
        radius: metres: a cell is near when a point lies this close.
        ray_every: every ray_every-th point gives a free-space ray (0 = none).
    """
    dist = point_distance(grid, xy)
    near = dist <= radius
    if ray_every <= 0 or len(xy) == 0:
        return near, np.zeros(grid.shape, bool), dist
    pick = np.arange(0, len(xy), ray_every)
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

"""What the views observed on the plan grid: cells near a projected point, and cells the rays
crossed on their way to the surfaces they met (free space).

A cell is *near* when a projected point lies within `radius` metres of its centre. A cell is
*free* when the plan projection of some camera ray (camera centre to the point it met) passes
over it: a view looked through the space above it. Neither reads the grid's extent: a cell no
point came near and no ray crossed was not observed.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.common.blueprint import Grid

RAY_STEP = 0.5  # cells between samples along a ray's plan projection


def near_points(grid: Grid, xy: np.ndarray, radius: float) -> np.ndarray:
    """Cells with a point of xy [N, 2] (world metres) within `radius` metres. bool [H, W]."""
    row, col, inside = grid.cell_of(xy)
    occ = np.zeros(grid.shape, bool)
    occ[row[inside], col[inside]] = True
    if not occ.any():
        return occ
    # distance from a cell's centre to the nearest occupied cell's centre; a point may lie up
    # to half a cell's diagonal off its cell's centre: near cells have a point within radius
    dist = ndimage.distance_transform_edt(~occ) * grid.cell
    return dist <= radius - 0.5 * np.sqrt(2.0) * grid.cell


def ray_cells(grid: Grid, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Cells crossed by the plan segments start [R, 2] -> end [R, 2] (world metres), sampled
    every RAY_STEP cells. bool [H, W]."""
    out = np.zeros(grid.shape, bool)
    if len(start) == 0:
        return out
    seg = end - start  # [R, 2]
    n = np.ceil(np.linalg.norm(seg, axis=1) / (RAY_STEP * grid.cell)).astype(np.int64) + 1
    total = int(n.sum())
    ray = np.repeat(np.arange(len(start)), n)  # [S] the ray of each sample
    first = np.cumsum(n) - n
    t = (np.arange(total) - first[ray]) / np.maximum(n[ray] - 1, 1)  # [S] in [0, 1]
    xy = start[ray] + t[:, None] * seg[ray]  # [S, 2]
    row, col, inside = grid.cell_of(xy)
    out[row[inside], col[inside]] = True
    return out


def observed(
    grid: Grid,
    xy: np.ndarray,
    cams: np.ndarray,
    view: np.ndarray,
    radius: float,
    ray_every: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(near, free) bool [H, W] on `grid`.

    Args:
        grid: the plan grid.
        xy: [N, 2] world plan positions of the projected points.
        cams: [C, 2] world plan positions of the camera centres.
        view: [N] the view of each point (index into cams).
        radius: metres: a cell is near when a point lies this close.
        ray_every: every ray_every-th point gives a free-space ray (0 = none).
    """
    near = near_points(grid, xy, radius)
    if ray_every <= 0 or len(xy) == 0:
        return near, np.zeros(grid.shape, bool)
    pick = np.arange(0, len(xy), ray_every)
    return near, ray_cells(grid, cams[view[pick]], xy[pick])


def room_inside(near: np.ndarray, free: np.ndarray, close_cells: int) -> np.ndarray:
    """The room's extent on the plan: what the views observed or looked through, closed over
    gaps up to 2 * close_cells cells and its holes filled. bool [H, W]."""
    obs = near | free
    if close_cells > 0:
        r = close_cells
        disk = np.hypot(*np.mgrid[-r : r + 1, -r : r + 1]) <= r
        obs = ndimage.binary_closing(np.pad(obs, r + 1), disk)[r + 1 : -r - 1, r + 1 : -r - 1]
    return ndimage.binary_fill_holes(obs)

"""Top-view occlusion: drop the points a camera looking straight down would not see.

A blueprint is a top view, but Π projects every labelled pixel: floor seen between the legs
of a table votes against the table top above it. Per plan cell, the *top* is the z of the
`min_points`-th highest point (so one stray high point does not decide it; cells with fewer
points are left alone). A class is kept in the cell when its highest point there reaches
`band` metres below the top; the other classes' points in that cell are dropped. Keeping every
point of a class that reaches the top (rather than only the points near the top) keeps the
weight of vertical surfaces such as walls, whose points span their whole height.

Cells coarser than the plan's hold enough points to find the top when views are few, but
drop the floor up to a whole cell in front of a wall; taking the union of what several
offset grids keep brings that down to a fraction of a cell. On procedural rooms (3 seeds;
40, 90 and 9 views) 6 cm cells, 2 x 2 offsets, the 2nd highest point and a 10 cm band did
best (fwIoU +1.9 on average over no culling, up to +4.6).
"""

from __future__ import annotations

import numpy as np


def top_view_keep(
    xyz: np.ndarray,
    label: np.ndarray,
    cell: float,
    band: float,
    min_points: int,
    shifts: int = 1,
) -> np.ndarray:
    """Which points a top view sees, on shifts x shifts grids offset by cell / shifts.

    A point is dropped only when every cell holding it, whichever the offset, has another
    class on top (see cell_keep): next to a wall, floor points survive up to cell / shifts of
    it rather than up to a whole cell. Arguments as in cell_keep. Returns bool [N].
    """
    xyz = np.asarray(xyz, np.float64)
    keep = np.zeros(len(xyz), bool)
    for i in range(shifts):
        for j in range(shifts):
            off = np.array([i * cell / shifts, j * cell / shifts, 0.0])
            keep |= cell_keep(xyz + off, label, cell, band, min_points)
    return keep


def cell_keep(
    xyz: np.ndarray, label: np.ndarray, cell: float, band: float, min_points: int
) -> np.ndarray:
    """Which points a top view sees, per square cell of `cell` metres. Returns bool [N].

    Args:
        xyz: [N, 3] world points (z up, metres).
        label: [N] class ids (< 256).
        cell: size of the cells over which the top is taken (cells are aligned on multiples
            of `cell` of the coordinates given: points.py passes them relative to the mean
            camera centre, so the cells move and scale with the world).
        band: a class is seen in a cell when it reaches within `band` metres of the top.
        min_points: the top is the z of the min_points-th highest point of the cell; cells
            with fewer points keep all their points.
    """
    n = len(xyz)
    if n == 0:
        return np.zeros(0, bool)
    z = np.asarray(xyz[:, 2], np.float64)  # [N]
    ij = np.floor(np.asarray(xyz[:, :2], np.float64) / cell).astype(np.int64)  # [N, 2]
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]  # [N] flat cell key
    _, c = np.unique(key, return_inverse=True)  # [N] cell index 0..C-1
    counts = np.bincount(c)  # [C]
    start = np.cumsum(counts) - counts  # [C] first sorted position of each cell
    order = np.lexsort((-z, c))  # by cell, then z from the highest
    top = np.full(len(counts), -np.inf)  # [C]
    dense = counts >= min_points
    top[dense] = z[order[start[dense] + min_points - 1]]
    # highest z of each (cell, class) pair: the first of its group in (pair, -z) order
    pair = c * 256 + np.asarray(label, np.int64)  # [N]
    by_pair = np.lexsort((-z, pair))
    _, first, inv = np.unique(pair[by_pair], return_index=True, return_inverse=True)
    reach = np.empty(n)
    reach[by_pair] = z[by_pair][first][inv]  # [N] highest z of the point's class in its cell
    return reach >= top[c] - band

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
    if shifts <= 1 or len(xyz) == 0:
        return cell_keep(xyz, label, cell, band, min_points)
    # Every offset grid's cells are unions of shifts x shifts cells of cell / shifts: the
    # points are grouped once into those fine cells (per fine cell its min_points highest z
    # and each class's highest z), and each offset grid merges the fine cells' summaries
    # (arrays the size of the plan, not of the points). A point at the fine cell (fi, fj)
    # lies in the offset grid (a, b)'s cell ((fi + a) // shifts, (fj + b) // shifts), as
    # floor((x + a cell / shifts) / cell) puts it. 7.7 M points: 4x fewer passes over them.
    fi = np.floor(xyz[:, 0] * (shifts / cell)).astype(np.int64)  # [N]
    fj = np.floor(xyz[:, 1] * (shifts / cell)).astype(np.int64)
    fi -= shifts * (int(fi.min()) // shifts)  # >= 0, the offset a multiple of shifts
    fj -= shifts * (int(fj.min()) // shifts)
    ni, nj = int(fi.max()) + 1, int(fj.max()) + 1
    f = fi * nj + fj  # [N] fine cell
    m = ni * nj
    z = xyz[:, 2]
    label = np.asarray(label, np.int64)
    seen = np.bincount(label, minlength=256) > 0
    n_lab = int(seen.sum())
    lab = (np.cumsum(seen) - 1)[label]  # [N] classes renumbered 0..L-1
    flat = np.full(m * n_lab, -np.inf)  # highest z per (fine cell, class)
    np.maximum.at(flat, f * n_lab + lab, z)
    reach = flat.reshape(m, n_lab)
    tops = _k_highest(z, f, m, min_points)  # [k, M] per fine cell, -inf where fewer
    keep_pair = np.zeros((m, n_lab), bool)
    ci0, cj0 = np.divmod(np.arange(m), nj)  # [M] fine cell coordinates
    for a in range(shifts):
        for b in range(shifts):
            ci, cj = (ci0 + a) // shifts, (cj0 + b) // shifts
            c = ci * (int(cj.max()) + 1) + cj  # [M] this grid's cell of each fine cell
            mc = int(c.max()) + 1
            cell_reach = np.full((mc, n_lab), -np.inf)
            np.maximum.at(cell_reach, c, reach)
            top = _kth_highest(tops.reshape(-1), np.tile(c, min_points), mc, min_points)
            keep_pair |= cell_reach[c] >= (top[c] - band)[:, None]
    return keep_pair[f, lab]


def _k_highest(z: np.ndarray, c: np.ndarray, m: int, k: int) -> np.ndarray:
    """Per cell 0..m-1 of the points (z [N], cell c [N]): its k highest z, ties counted
    (two points at the highest z fill two rows). Returns [k, m], -inf where fewer points."""
    out = np.full((k, m), -np.inf)
    found = np.zeros(m, np.int64)  # rows filled per cell
    below = np.full(m, np.inf)  # the level of the previous round
    for _ in range(k):
        left = z < below[c]
        level = np.full(m, -np.inf)
        np.maximum.at(level, c[left], z[left])
        count = np.bincount(c[left & (z == level[c])], minlength=m)
        for r in range(k):  # rows found .. found + count - 1 take this level
            put = (found <= r) & (r < found + count)
            out[r, put] = level[put]
        found += count
        below = level
    return out


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
    # Per-cell maxima by scatter (ufunc.at) over a dense cell index, not by sorting: the
    # points of 100 views of 640x480 (7.7 M) sorted twice per offset grid took ~30 s.
    z = np.asarray(xyz[:, 2], np.float64)  # [N]
    i = np.floor(np.asarray(xyz[:, 0], np.float64) / cell).astype(np.int64)  # [N]
    j = np.floor(np.asarray(xyz[:, 1], np.float64) / cell).astype(np.int64)
    i -= i.min()
    j -= j.min()
    c = i * (int(j.max()) + 1) + j  # [N] flat cell index
    m = int(c.max()) + 1
    top = _kth_highest(z, c, m, min_points)  # [M], -inf where fewer points
    # highest z of each (cell, class) pair (classes renumbered 0..L-1)
    label = np.asarray(label, np.int64)
    seen = np.bincount(label, minlength=256) > 0  # a look-up, not np.unique's sort
    lut = np.cumsum(seen) - 1
    pair = c * int(seen.sum()) + lut[label]  # [N]
    reach = np.full(m * int(seen.sum()), -np.inf)
    np.maximum.at(reach, pair, z)
    return reach[pair] >= top[c] - band


def _kth_highest(z: np.ndarray, c: np.ndarray, m: int, k: int) -> np.ndarray:
    """Per cell 0..m-1 of the points (z [N], cell c [N]): the k-th highest z (ties counted:
    two points at the highest z make it the 2nd highest too); -inf in cells with fewer than
    k points. k rounds of a per-cell maximum over the points below the last one."""
    top = np.full(m, -np.inf)
    found = np.zeros(m, np.int64)  # points at or above the current level, per cell
    below = np.full(m, np.inf)  # the level of the previous round
    for _ in range(k):
        left = z < below[c]
        level = np.full(m, -np.inf)
        np.maximum.at(level, c[left], z[left])
        at = left & (z == level[c])
        found += np.bincount(c[at], minlength=m)
        newly = (found >= k) & ~np.isfinite(top) & np.isfinite(level)
        top[newly] = level[newly]
        below = level
    return top

"""Object instances on a plan, shared by every blueprint method.

A method builds its class raster; then each cell of a class whose projected points carry
instances takes the instance of the nearest such point of that class: every cell first takes
the majority instance of the points of the class that fall in it, then the other cells of the
class take the instance of the nearest of those cells (Euclidean distance transform). Cells a
method fills without any point (BluNF's unseen cells) are thus split between the objects
around them, and two objects of one class stay apart however close they stand.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.common.blueprint import Grid


def instance_raster(
    labels: np.ndarray, grid: Grid, xy: np.ndarray, label: np.ndarray, instance: np.ndarray
) -> np.ndarray | None:
    """The instance of every plan cell from the projected points.

    Args:
        labels: uint8 [H, W] the plan's classes on `grid`.
        xy: [N, 2] world (x, y) of the points. label: [N] their classes. instance: [N] their
            object instances (0 = none).

    Returns int32 [H, W] (0 = none: a class without instances, unknown cells), or None when no
    point inside the grid has an instance.
    """
    h, w = grid.shape
    row, col, inside = grid.cell_of(xy)
    has = inside & (np.asarray(instance) > 0)
    if not has.any():
        return None
    cell = (row * w + col)[has]  # [M] flat cell of each point with an instance
    lab = np.asarray(label)[has]  # [M]
    inst = np.asarray(instance)[has].astype(np.int64)  # [M]
    out = np.zeros((h, w), np.int32)
    for c in np.unique(lab).tolist():
        target = labels == c  # [H, W] the cells to name
        if not target.any():
            continue
        cells, win = cell_majority(cell[lab == c], inst[lab == c])
        seeds = np.zeros((h, w), np.int32)  # majority instance of the cells with points of c
        seeds.reshape(-1)[cells] = win
        # indices [2, H, W] of the nearest seeded cell (a seeded cell is its own)
        idx = ndimage.distance_transform_edt(
            seeds == 0, return_distances=False, return_indices=True
        )
        out[target] = seeds[idx[0][target], idx[1][target]]
    return out


def cell_majority(cell: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The most frequent value in each cell (ties to the lowest value).

    Args:
        cell: [M] int cell id of each sample. value: [M] non-negative int values.

    Returns (cells [C] sorted, winning value [C] int64).
    """
    base = int(value.max(initial=0)) + 1
    key = np.asarray(cell, np.int64) * base + np.asarray(value, np.int64)  # [M]
    pair, count = np.unique(key, return_counts=True)  # [P]
    pc, pv = pair // base, pair % base
    order = np.lexsort((pv, -count, pc))  # by cell, then count descending, then value
    pc, pv = pc[order], pv[order]
    first = np.r_[True, pc[1:] != pc[:-1]] if len(pc) else np.zeros(0, bool)
    return pc[first], pv[first]

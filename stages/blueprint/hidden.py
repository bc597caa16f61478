"""The insides of tall objects: cells no view saw into, closed round by one object's points.

A wardrobe or a tall cabinet against a wall shows the views its front and sides; its top, at
or above the cameras, none. Its footprint's inside holds no point, and no ray's plan
projection crosses it (a ray over it would look up past its top), so the field, fitted to
the points, fills it from whatever lies nearest: stripes of floor and wall between the front
and the wall behind. Here such a *pocket* (a 4-connected set of cells within the room that
hold no point and that no ray crossed, observed.npz "free") becomes the object whose points
bound it: the most common object class on its rim (the cells round it that hold points)
when that class holds at least RIM_SHARE of the rim and at least OVER_FLOOR of the rim's
object-or-floor cells. A pocket rimmed by wall alone (the space behind the room's outer
walls), or mostly by floor (floor behind a low object that the rays happened to miss), or
larger than any furniture (MAX_AREA) keeps the field's labels. A thick wall's inside holds
no point and meets no ray either, and where an object hides the wall's face (the gap behind
a cabinet) it joins the object's pocket: the cells the field drew as a wall that holds wall
points somewhere are kept out of every pocket, so the wall stays. (A face-side test, the
wall's inside lying behind the face the rays came from, fails where the object hides the
face behind it: the nearest face seen is then the wall's far side, and the object lies
behind that.)

Ray-crossed cells split a pocket (a ray to the wall above a cabinet that looks up crosses
its footprint), and each piece is judged alone: a piece rimmed by the crossing rays' cells
(free, pointless, so not on the rim) and the wall has no object rim and keeps the field's
labels. Stereo's readings (photos) scatter through the space and their rays cross nearly
every cell: the pockets are few and small there, and this changes little.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from stages.blueprint.mvr import majority_vote
from stages.common.blueprint import Grid, observed_layer
from stages.common.capture import UNKNOWN
from stages.common.classes import FLOOR_NAME, STRUCTURE, WALL_NAME, ids_named

RIM_SHARE = 0.3  # the object's share of the rim's cells that hold points
OVER_FLOOR = 0.6  # the object's cells on the rim against those and the rim's floor cells
MAX_AREA = 4.0  # m^2: a pocket larger than this is no piece of furniture's inside
MIN_CELLS = 4  # a pocket smaller than this is a gap between points, left to the field


def hidden_insides(
    labels: np.ndarray,
    classes: dict[int, str],
    grid: Grid,
    xy: np.ndarray,
    label: np.ndarray,
    observed: Path,
) -> tuple[np.ndarray, int]:
    """fill_pockets of the plan labels [H, W] with the points xy [N, 2] (world metres)
    labelled `label` [N] and observed.npz's free and inside layers (the plan unchanged when
    the file has none)."""
    free = observed_layer(observed, "free", grid.shape)
    inside = observed_layer(observed, "inside", grid.shape)
    if free is None or inside is None:
        return labels, 0
    return fill_pockets(labels, classes, grid, xy, label, free > 0, inside > 0)


def fill_pockets(
    labels: np.ndarray,
    classes: dict[int, str],
    grid: Grid,
    xy: np.ndarray,
    label: np.ndarray,
    free: np.ndarray,
    inside: np.ndarray,
) -> tuple[np.ndarray, int]:
    """(The plan [H, W] with every pocket that one object's points close round made that
    object, how many cells changed).

    xy [N, 2], label [N]: the projected points; free, inside: bool [H, W], the cells rays
    crossed and the room's extent (observed.npz).
    """
    top, _ = majority_vote(np.asarray(xy)[:, :2], label, grid)  # UNKNOWN: no point
    held = top != UNKNOWN
    obj_ids = np.setdiff1d(np.unique(top[held]), ids_named(classes, *STRUCTURE))
    floor_ids = ids_named(classes, FLOOR_NAME)
    if len(obj_ids) == 0:
        return labels, 0
    # the plan's walls that hold wall points somewhere: a thick wall's inside holds no point
    # either, and lies between its two faces' points, not within an object's
    wall = np.isin(labels, ids_named(classes, WALL_NAME))
    parts, _ = ndimage.label(wall)
    seen_wall = np.unique(parts[wall & np.isin(top, ids_named(classes, WALL_NAME))])
    walls = np.isin(parts, seen_wall[seen_wall > 0])
    pocket, _ = ndimage.label(inside & ~free & ~held & ~walls)
    max_cells = MAX_AREA / grid.cell**2
    out, changed = labels.copy(), 0
    ring = np.ones((3, 3), bool)
    for i, box in enumerate(ndimage.find_objects(pocket), 1):
        grown = tuple(slice(max(0, s.start - 1), s.stop + 1) for s in box)
        m = pocket[grown] == i
        size = int(m.sum())
        if size < MIN_CELLS or size > max_cells:
            continue
        rim = top[grown][ndimage.binary_dilation(m, ring) & ~m]
        rim = rim[rim != UNKNOWN]
        obj = rim[np.isin(rim, obj_ids)]
        if len(obj) == 0:
            continue
        cls, votes = np.unique(obj, return_counts=True)
        best, n_best = cls[votes.argmax()], int(votes.max())
        n_floor = int(np.isin(rim, floor_ids).sum())
        if n_best >= RIM_SHARE * len(rim) and n_best >= OVER_FLOOR * (n_best + n_floor):
            changed += int((out[grown][m] != best).sum())
            out[grown][m] = best
    return out, changed

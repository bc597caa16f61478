"""Fused surface that no depth reading supports, removed after fusion (`fusion.min_support`).

A TSDF averages signed distances. Where the views disagree about a surface (one view's
stereo carries a chair's edge a few centimetres out over the floor, the next view reads the
floor there), the zero crossing of the average falls between the readings, on no reading of
any view, and marching cubes draws a surface there: skirts round objects, streaks along the
rays of the views that mismatched. From a plan's point of view these are object where there
is floor, and they hide the floor below them from the top view.

Every vertex is projected into every view; a view supports it when its reading at the
nearest pixel lies within `dist` of the vertex's depth. The surface that fewer than
`min_support` views support is removed. Measured on the photos-only demo room (60 views,
stereo and rendered depth; ground-truth depth decides what is wrong): of the surface
vertices 0.25-1.3 m above the floor, 11 % lie where no true surface is (more views' true
depth sees through them than lies on them); 54 % of those have fewer than two supporting
views within 5 cm, against 3-7 % of the others. Sensor depth needs none of it (the plan
from the room's exact depth: fwIoU 89.8 without, 89.9 with), so it is off unless a config
asks for it (configs/phone.yaml).

Two views often agree on a wrong surface all the same: stereo's errors at an object's edge
repeat from one view to the next along a walk (a skirt from a table's top down to the floor
behind it). The views that look across that place from elsewhere read what lies beyond it:
free space there. `fusion.max_through` removes the surface more than that many views per
supporting view saw through (docs/figures.md#fusion-max-through).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from stages.common.camera import depth_at


def view_votes(
    points: np.ndarray, views: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], dist: float
) -> tuple[np.ndarray, np.ndarray]:
    """(support, through) [N] int32 each, for world points [N, 3]: how many views have a
    reading within `dist` of each point, and how many a reading more than `dist` beyond it
    along their ray (they saw through it: free space there).

    Args:
        views: per view (depth [H, W]: z-depth in metres, 0 = no reading; its [3, 3]
            intrinsics; [4, 4] camera-to-world), read one at a time.
        dist: metres, along the view's optical axis.
    """
    support = np.zeros(len(points), np.int32)
    through = np.zeros(len(points), np.int32)
    for depth, K, c2w in views:
        d, z = depth_at(points, depth, K, c2w)  # d = 0 outside the view or behind it
        seen = d > 0
        support += seen & (np.abs(d - z) <= dist)
        through += seen & (d - z > dist)
    return support, through

"""Far poses recentred on ingest: a capture in georeferenced coordinates moved near the world
origin, its offset kept in `Capture.origin` (exports and the evaluate stage put it back)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.common.capture import Capture

RECENTRE_BEYOND = 1000.0  # metres: poses whose mean centre lies farther, and farther than
#                          RECENTRE_SPREAD times the cameras' spread, are moved near 0 (a
#                          room in kilometre units is a large world, not a far one)
RECENTRE_SPREAD = 100.0
RECENTRE_STEP = 1000.0  # metres: the offset taken off, a whole multiple of this


def recentred(cap: Capture) -> Capture:
    """The capture with its poses moved near the world origin when they lie far from it
    (georeferenced coordinates: float32 geometry at 1e6 m has 6 cm steps), the offset kept in
    `origin`. The offset is a whole number of kilometres, so that the same room anywhere
    gives the same frames (up to float64 rounding) and the same plan."""
    if not cap.has_poses:
        return cap
    centres = cap.poses()[:, :3, 3]
    c = centres.mean(axis=0)  # [3] mean camera centre
    far = np.abs(c).max()
    if not np.all(np.isfinite(c)) or far <= RECENTRE_BEYOND:
        return cap
    if far <= RECENTRE_SPREAD * float(np.abs(centres - c).max()):
        return cap
    o = np.round(c / RECENTRE_STEP) * RECENTRE_STEP  # [3]
    frames = []
    for f in cap.frames:
        pose = np.array(f.pose, np.float64)
        pose[:3, 3] -= o
        frames.append(replace(f, pose=pose))
    origin = np.asarray(cap.origin, np.float64) + o
    return replace(
        cap.with_frames(frames), origin=(float(origin[0]), float(origin[1]), float(origin[2]))
    )

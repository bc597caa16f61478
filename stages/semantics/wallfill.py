"""Walls seen through holes in the fused surface.

Photos-only depth has holes where walls are plain: stereo matches nothing on a white
stretch, so the fused surface keeps only the wall's textured parts (its corners, skirting,
what hangs on it) and the wall plane found from them bounds a stretch that no surface
fills. A ray that passes through every fused surface and crosses the plane of a wall inside
the wall's extent (its inliers' box along the wall, from the floor up to the wall's top)
and inside the room's footprint has seen that wall there: nothing stood in front of it, or
the fusion would have put a surface in the way. The semantics stage labels such pixels wall
at that depth, as floorfill.py does for the floor.

Only rays that hit no surface at all count: a ray that meets a surface beyond the plane has
seen through it (a doorway, a window), which proves there is no wall there. A doorway
whose far side no view reconstructed is filled (a known limit).
"""

from __future__ import annotations

import numpy as np

from stages.semantics.floorfill import Footprint
from stages.semantics.segment import in_extent


def wall_through(
    rays: np.ndarray,
    t_hit: np.ndarray,
    walls: tuple[dict, ...],
    floor_z: float,
    room: Footprint | None,
    margin: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth at which each ray meets the nearest wall plane where the wall is seen through
    the surface; 0 elsewhere.

    Args:
        rays: [..., 6] origin and direction (Open3D's pinhole rays: camera z = 1, so the ray
            parameter is the depth). t_hit: [...] ray parameter of the first surface hit
            (inf: none).
        walls: the wall planes (the segmentation's plane dicts: normal, d, box in (s, z)).
        floor_z: the floor's height: a wall reaches down to it from its box.
        room: where the walls may be (xy: the crossing one cell back along the ray, the wall
            lying on the footprint's edge), or None (anywhere).
        margin: metres by which a crossing may lie outside the wall's box.

    Returns:
        (float32 [...] ray parameter of the crossing or 0, int32 [...] index of the wall or -1)
    """
    # only rays that hit no surface can see a wall through it: the rest are not computed
    # (a photos-only view's unhit rays are a fraction of it, and this runs per wall per view)
    free = ~np.isfinite(t_hit)
    r = rays[free].astype(np.float64)  # [N, 6]
    o, d = r[:, :3], r[:, 3:]
    unit = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    best = np.full(len(o), np.inf)
    which = np.full(len(o), -1, np.int32)
    for i, wall in enumerate(walls):
        normal = np.asarray(wall["normal"], np.float64)
        den = d @ normal
        ok = np.abs(den) > 1e-12
        t = np.where(ok, -(o @ normal + wall["d"]) / np.where(ok, den, 1.0), -1.0)
        x = o + t[..., None] * d  # [..., 3]
        box = {**wall, "box": [wall["box"][0], min(wall["box"][1], floor_z), *wall["box"][2:]]}
        ok &= (t > 0) & in_extent(box, x, margin) & (t < best)
        if room is not None:  # the crossing, one footprint cell back towards the camera
            ok &= room.contains(x[..., :2] - room.cell * unit[..., :2])
        best = np.where(ok, t, best)
        which = np.where(ok, i, which)
    depth = np.zeros(t_hit.shape, np.float32)
    index = np.full(t_hit.shape, -1, np.int32)
    depth[free] = np.where(which >= 0, best, 0.0)
    index[free] = which
    return depth, index

"""Floor seen through holes in the fused surface.

A ray that passes through every fused surface and crosses the floor plane inside the room
has seen floor there: nothing stood between the camera and the floor, or the fusion would
have put a surface in its way. Photos-only depth leaves such holes where the floor meets
objects (stereo windows straddling a chair's edge match the chair; the fusion stage then
drops the surface few views support), and a plan's floor between a chair and a table is
exactly there. The top view still lets an object seen above a filled floor point win.

A ray that crosses a wall's plane inside the wall's extent before it reaches the floor has
left the room through a hole in the wall (a doorway, a window, an unseen patch): the floor
beyond is not this room's. So is a crossing outside the room's footprint: the cells
(`cell` metres) holding floor or wall triangle centres, closed by one cell and with their
enclosed holes filled (scipy.ndimage).

A mesh with no floor plane (photos alone: stereo finds nothing on a plain floor; the
7-Scenes kitchen's fused surface starts at the counters) gives neither a floor height nor a
footprint. There the floor is the align stage's, z = 0 (the sparse SfM points' lowest
surface), and the room is the convex hull of the fused surface and the cameras (the free
space the views look through lies between them; a concave room's hull takes in the corner
outside its walls). Without walls to stop rays there, a `Reach` bounds each ray: it must
point down at least `min_drop_deg` (a grazing ray's crossing moves far for a small error in
the floor's height or the pose) and cross within `max_dist` metres of the camera along the
floor. A ray that passes under a counter through a cabinet front stereo missed paints
floor under it; the project stage's top view lets the counter top seen above it win.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.morphology import convex_hull_image

from stages.semantics.segment import in_extent


@dataclass(frozen=True)
class Footprint:
    """A boolean mask over a world-aligned xy grid: origin [2] (metres), cell, mask [rows, cols]
    with row = floor((y - origin_y) / cell), col = floor((x - origin_x) / cell)."""

    origin: np.ndarray
    cell: float
    mask: np.ndarray

    @classmethod
    def of(cls, xy: np.ndarray, cell: float, max_cells: int = 4_000_000, hull: bool = False
           ) -> Footprint:  # fmt: skip
        """The hole-filled, one-cell-closed occupancy of points xy [N, 2] (N >= 1), on cells
        of `cell` metres, or coarser ones when a stray point far out would need more than
        about `max_cells` (memory stays bounded; the walls still bound the fill). With
        `hull`, the occupancy's convex hull instead."""
        xy = np.asarray(xy, np.float64)
        span = np.ptp(xy, axis=0) + 4 * cell  # [2]
        cell = max(cell, float(np.sqrt(span[0] * span[1] / max_cells)))
        origin = xy.min(axis=0) - 2 * cell  # a free border: closing and filling see the outside
        ij = np.floor((xy - origin) / cell).astype(np.int64)  # [N, 2] (col, row)
        shape = (int(ij[:, 1].max()) + 3, int(ij[:, 0].max()) + 3)
        occ = np.zeros(shape, bool)
        occ[ij[:, 1], ij[:, 0]] = True
        if hull:
            return cls(origin, float(cell), convex_hull_image(occ))
        occ = ndimage.binary_closing(occ, np.ones((3, 3), bool))
        return cls(origin, float(cell), ndimage.binary_fill_holes(occ))

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """bool [...]: whether each point xy [..., 2] lies in the footprint."""
        ij = np.floor((np.asarray(xy, np.float64) - self.origin) / self.cell)
        rows, cols = self.mask.shape
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < cols) & (ij[..., 1] >= 0) & (ij[..., 1] < rows)
        col = np.where(inside, ij[..., 0], 0).astype(np.int64)
        row = np.where(inside, ij[..., 1], 0).astype(np.int64)
        return inside & self.mask[row, col]


@dataclass(frozen=True)
class Reach:
    """How far a ray may reach the floor when no floor plane bounds the fill (see above)."""

    min_drop_deg: float  # the ray points at least this far below the horizontal
    max_dist: float  # metres from the camera to the crossing, along the floor


def _through(wall: dict, o: np.ndarray, d: np.ndarray, t_end: np.ndarray, pad: float
             ) -> np.ndarray:  # fmt: skip
    """bool [...]: whether rays o + t d ([..., 3] each) cross a wall plane of the segmentation
    (semantics.json's plane_list entries) for 0 < t < t_end, inside its box grown by pad."""
    normal = np.asarray(wall["normal"], np.float64)
    den = d @ normal  # [...]
    ok = np.abs(den) > 1e-12
    t = np.where(ok, -(o @ normal + wall["d"]) / np.where(ok, den, 1.0), -1.0)
    x = o + t[..., None] * d  # [..., 3]
    return ok & (t > 0) & (t < t_end) & in_extent(wall, x, pad)


def floor_through(
    rays: np.ndarray,
    t_hit: np.ndarray,
    floor_z: float,
    room: Footprint,
    margin: float,
    walls: tuple[dict, ...] = (),
    reach: Reach | None = None,
) -> np.ndarray:
    """Depth at which each ray meets the floor plane, where the floor is seen through the
    surface; 0 elsewhere.

    Args:
        rays: [..., 6] origin and direction (Open3D's pinhole rays: camera z = 1, so the ray
            parameter is the depth). t_hit: [...] ray parameter of the first surface hit
            (inf: none). floor_z: height of the floor plane. room: where the floor may be.
        margin: metres (along the ray) the surface hit must lie beyond the floor crossing;
            a hit within it is the floor itself, already labelled.
        walls: the room's wall planes (the segmentation's plane dicts), which no ray may pass
            through on its way to the floor.
        reach: when given, rays pointing down less steeply or crossing farther from the
            camera than it allows are not filled either.

    Returns:
        float32 [...]: the crossing's ray parameter for the rays that point down, cross the
        plane in front of the camera inside `room`, through no wall, and hit nothing before
        it; else 0.
    """
    o, d = rays[..., :3].astype(np.float64), rays[..., 3:].astype(np.float64)
    down = d[..., 2] < 0
    t = np.where(down, (floor_z - o[..., 2]) / np.where(down, d[..., 2], -1.0), 0.0)
    length = np.linalg.norm(d, axis=-1)  # metres per unit of t
    beyond = ~np.isfinite(t_hit) | (t_hit > t + margin / np.maximum(length, 1e-12))
    ok = down & (t > 0) & beyond
    xy = o[..., :2] + t[..., None] * d[..., :2]
    ok &= room.contains(xy)
    if reach is not None:
        steep = -d[..., 2] >= np.sin(np.radians(reach.min_drop_deg)) * length
        near = t * np.linalg.norm(d[..., :2], axis=-1) <= reach.max_dist
        ok &= steep & near
    if walls:  # the walls only for the rays still in (the per-view cost is walls x rays)
        at = np.flatnonzero(ok)
        oo, dd, tt = o.reshape(-1, 3)[at], d.reshape(-1, 3)[at], t.reshape(-1)[at]
        past = np.zeros(len(at), bool)
        for wall in walls:
            past |= _through(wall, oo, dd, tt, margin)
        ok.flat[at[past]] = False
    return np.where(ok, t, 0.0).astype(np.float32)


def floor_past(
    rays: np.ndarray,
    t_hit: np.ndarray,
    reading: np.ndarray,
    floor_z: float,
    room: Footprint,
    past: float,
    tol: float,
) -> np.ndarray:
    """Depth at which each ray meets the floor plane, where the view's own reading lies on it
    (within `tol` metres in height), `past` metres or more beyond the surface the ray hits;
    0 elsewhere.

    The fused surface is fatter than what it fused at a silhouette (the TSDF's voxels and
    truncation): the rim of a chair's seat or a table's edge hangs over the floor the views
    saw past it. A reading on the floor plane beyond the hit is that floor: the ray reached
    it, so nothing stood in the way.

    Args:
        rays: [H, W, 6] origin and direction (camera z = 1: the ray parameter is the depth).
        t_hit: [H, W] ray parameter of the first surface hit (inf: none).
        reading: [h, w] the view's depth in metres (0: none), read at the nearest pixel when
            its size differs. floor_z: height of the floor plane. room: where the floor may
            be. past: metres, along the ray, beyond the hit.
    """
    h, w = t_hit.shape
    if reading.shape != (h, w):
        rows = np.minimum((np.arange(h) + 0.5) * reading.shape[0] / h, reading.shape[0] - 1)
        cols = np.minimum((np.arange(w) + 0.5) * reading.shape[1] / w, reading.shape[1] - 1)
        reading = reading[rows.astype(np.int64)[:, None], cols.astype(np.int64)[None, :]]
    o, d = rays[..., :3].astype(np.float64), rays[..., 3:].astype(np.float64)
    down = d[..., 2] < 0
    t = np.where(down, (floor_z - o[..., 2]) / np.where(down, d[..., 2], -1.0), 0.0)
    step = past / np.maximum(np.linalg.norm(d, axis=-1), 1e-12)  # `past` metres in t
    ok = down & (reading > 0) & np.isfinite(t_hit) & (t > t_hit + step)
    ok &= np.abs(o[..., 2] + reading * d[..., 2] - floor_z) <= tol
    ok &= room.contains(o[..., :2] + t[..., None] * d[..., :2])
    return np.where(ok, t, 0.0).astype(np.float32)

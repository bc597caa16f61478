"""Plane hypotheses of a Manhattan room from the points stereo and SfM did read.

The aligned world has z up, the floor at z = 0 and walls roughly along x and y. Points
(checked stereo readings with their normals, SfM track points without) are thinned to one
per voxel; each of the three room axes (up, along the floor's own normal where a floor is
found, and the two wall directions, re-estimated from the points' normals: the align
stage's may be a few degrees off) gets a histogram of the points' offsets along it, whose
smoothed peaks are planes (Furukawa et al., "Manhattan-world stereo", 2009). Each peak is
refitted on its inliers within ±`band` and ±`max_tilt_deg`, and spans the box of its
inliers; with `support_cell` a top also keeps the cells of its plane its inliers fill
(`Cells`): a table top's inliers and a cushion's across the room share a height, and their
box spans the room between them. A table read at its rim alone makes no peak among the
whole room's points (the walls' readings of unknown normal spread over every height): the
floor's tiles find it by their own histograms (`_local_tops`), and a top's cells take in
the holes of up to `top_holes` they enclose, then grow up to `top_grow` over the cells
nothing was read under (`_grown`: a seat read at its front edge). A surface turned a few
degrees about up off a wall axis (a whiteboard on its stand) gets its own plane by a Hough
vote over the turns near each peak (`_turned`). The floor (the lowest horizontal plane
within FLOOR_SEARCH of z = 0, else z = 0 itself) is always a hypothesis. Surfaces off the axes (a
sofa's leaning back) get planes of their own by RANSAC among the points the axes' planes
leave (`free_planes`). Plain walls, which no point shows, come from their feet on the floor
in the photos (`bases`, through `find_planes`'s `feet`); the outermost walls a foot or
stereo's reading shows span the room, upright on the floor.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_dilation, gaussian_filter1d, uniform_filter1d
from scipy.signal import find_peaks
from skimage.morphology import remove_small_holes

from stages.common.camera import pixel_grid, unproject
from stages.common.classes import CEILING_NAME, FLOOR_NAME, WALL_NAME
from stages.common.ransac import plane_ransac
from stages.common.rows import unique_rows
from stages.depth.planes.config import PlanesConfig

log = logging.getLogger(__name__)


ROOM_KINDS = (FLOOR_NAME, CEILING_NAME, WALL_NAME)  # the room's own planes
FURNITURE_KINDS = ("top", "front")  # horizontal 0.2-1.5 m above the floor; other vertical
KINDS = ROOM_KINDS + FURNITURE_KINDS
YAW_PEAK = 1.5  # the wall axes turn to the normals' peak where it holds this many times the
#                mean bin (room_axes; office 2.0, kitchen 1.3: there the align stage's stay)
FLOOR_SEARCH = 0.3  # metres: the floor is sought this far either side of z = 0
FREE_ITERS = 1000  # RANSAC hypotheses per free plane, and for the floor's normal
FLOOR_TILT_DEG = 10.0  # the floor's normal is taken as up within this of the aligned z
Z_HOLDS = 0.95  # ...unless the aligned z holds this share of its floor points (floor_axes)
WALL_TOP = 2.4  # metres above the floor a wall reaches at least (walls_span)
READ_WALL = 1.5  # m²: a vertical plane whose inliers fill this much of it (in support
#                   cells) and reach READ_TOP above the floor is a wall stereo read: a wall's
#                   foot seen beyond or before it is a mark or a piece of furniture
# local tops (_local_tops): the floor is cut in square tiles of cfg.top_tile (and again half
# a tile over), and a horizontal peak in one tile's own histogram, LOCAL_ABOVE or more above
# the floor, holding LOCAL_SUPPORT voxels within band, is a top where the room's histogram
# shows none within band (a table read at its rim on the flank of the walls' hump)
LOCAL_ABOVE = 0.15  # metres
LOCAL_SUPPORT = 40  # voxels (0.016 m² of 2 cm voxels: a 0.9 x 0.6 m table's rim read once)
LOCAL_SHARE = 0.05  # of the tile's voting voxels above LOCAL_ABOVE (office plan 72.7 at 0.1)
LOCAL_TOPS = 8  # at most this many local tops are kept ahead of the stronger planes
READ_TOP = 1.2  # metres (the office's walls are read up to 1.4-2.2 m, behind its sofa too)
# a surface turned off a wall axis (_turned): its points are sought this far (metres) either
# side of a peak, its direction in steps of TURN_STEP degrees, and it must hold TURN_GAIN
# times the points the axis's direction holds within band of one offset (the office's
# whiteboard 1.20; its walls' best turns within max_tilt_deg held 1.05-1.22)
TURN_REACH = 0.12
TURN_STEP = 0.5
TURN_GAIN = 1.15


@dataclass(frozen=True)
class Cells:
    """Where on its plane a plane has inliers: square cells of side `size` in the plane's
    own coordinates (u, v) = (X . axes[0], X . axes[1]), `occupied[i, j]` for the cell at
    origin + (i, j) * size."""

    axes: np.ndarray  # [2, 3] unit, orthogonal to the plane's normal and to each other
    origin: np.ndarray  # [2] (u, v) of cell (0, 0)'s corner
    size: float  # metres
    occupied: np.ndarray  # [nu, nv] bool

    @classmethod
    def of(
        cls,
        normal: np.ndarray,
        points: np.ndarray,
        size: float,
        min_points: int,
        holes: float = 0.0,
    ) -> Cells:
        """The cells of the plane through `points` (its inliers) holding >= min_points, and
        the holes of up to `holes` m² they enclose (a table top read at its rim only)."""
        n = np.asarray(normal, np.float64)
        ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        a = ref - (ref @ n) * n
        a /= np.linalg.norm(a)
        axes = np.stack([a, np.cross(n, a)])
        uv = np.asarray(points, np.float64) @ axes.T
        origin = uv.min(0) if len(uv) else np.zeros(2)
        ij = np.floor((uv - origin) / size).astype(np.int64)
        shape = tuple(ij.max(0) + 1) if len(ij) else (1, 1)
        count = np.zeros(shape, np.int64)
        np.add.at(count, (ij[:, 0], ij[:, 1]), 1)
        occupied = count >= min_points
        if holes > 0:
            # scikit-image's remove_small_holes: 4-connected holes of at most this many cells
            occupied = remove_small_holes(occupied, max_size=int(holes / size**2), connectivity=1)
        return cls(axes, origin, float(size), occupied)

    def near(self, x: np.ndarray, margin: float) -> np.ndarray:
        """[N] whether points x [N, 3] (on or near the plane) lie within `margin` (metres,
        in the plane, to the nearest cell's centre, less half a cell) of an occupied cell."""
        reach = int(np.ceil(margin / self.size))
        r = np.arange(-reach, reach + 1)
        disk = (r[:, None] ** 2 + r[None] ** 2) * self.size**2 <= (margin + 0.5 * self.size) ** 2
        grown = binary_dilation(np.pad(self.occupied, reach), disk) if reach else self.occupied
        ij = np.floor((x @ self.axes.T - self.origin) / self.size).astype(np.int64) + reach
        ok = (ij >= 0).all(1) & (ij[:, 0] < grown.shape[0]) & (ij[:, 1] < grown.shape[1])
        out = np.zeros(len(x), bool)
        out[ok] = grown[ij[ok, 0], ij[ok, 1]]
        return out


# a hypothesis before its kind: (normal, offset, support, lo, hi, cells), as Plane's fields
Found = tuple[np.ndarray, float, int, np.ndarray, np.ndarray, Cells | None]


@dataclass(frozen=True)
class Plane:
    """n . X = d in the world (unit n), with its kind and the box of its inliers."""

    normal: np.ndarray  # [3] unit
    offset: float  # metres
    kind: str  # one of KINDS
    lo: np.ndarray  # [3] inliers' box, world metres
    hi: np.ndarray  # [3]
    support: int  # inlier voxels
    cells: Cells | None = None  # where its inliers lie (None: anywhere in the box)

    def to_json(self) -> dict:
        occupied = None if self.cells is None else int(self.cells.occupied.sum())
        return {
            "kind": self.kind,
            "normal": [round(float(v), 4) for v in self.normal],
            "offset": round(float(self.offset), 4),
            "support": int(self.support),
            "box": [[round(float(v), 3) for v in self.lo], [round(float(v), 3) for v in self.hi]],
            "cells": occupied,  # occupied support cells (None: the box alone)
        }


def view_points(
    depth: np.ndarray,
    K: np.ndarray,
    pose: np.ndarray,
    stride: int = 2,
    rgb: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [N, 3] of a depth map's readings on a strided grid, their unit normals
    [N, 3] from the neighbouring readings (0 where one is missing or jumps) and their
    colours [N, 3] from rgb (the depth map's size; zeros without it)."""
    h, w = depth.shape
    s = max(1, stride)
    d = np.asarray(depth, np.float64)[s // 2 :: s, s // 2 :: s]
    good = np.isfinite(d) & (d > 0)
    uv = pixel_grid(w, h, s)[: d.shape[0], : d.shape[1]].reshape(-1, 2)
    p = unproject(uv, np.where(good, d, 0.0).reshape(-1), K, pose).reshape(*d.shape, 3)
    n = np.zeros_like(p)
    if min(d.shape) >= 3:
        dx = p[1:-1, 2:] - p[1:-1, :-2]  # [H-2, W-2, 3]
        dy = p[2:, 1:-1] - p[:-2, 1:-1]
        nb = good[1:-1, 2:] & good[1:-1, :-2] & good[2:, 1:-1] & good[:-2, 1:-1]
        # a step between neighbours longer than 10 % of the depth per pixel pair: a jump
        step = np.maximum(np.linalg.norm(dx, axis=-1), np.linalg.norm(dy, axis=-1))
        c = np.cross(dx, dy)
        norm = np.linalg.norm(c, axis=-1, keepdims=True)
        ok = nb & (step < 0.1 * s * d[1:-1, 1:-1]) & (norm[..., 0] > 1e-12)
        n[1:-1, 1:-1] = np.where(ok[..., None], c / np.maximum(norm, 1e-12), 0.0)
    c = (
        np.zeros_like(p)
        if rgb is None
        else rgb[s // 2 :: s, s // 2 :: s][: d.shape[0], : d.shape[1]]
    )
    return p[good], n[good], np.asarray(c, np.float64)[good]


def thin(points: np.ndarray, normals: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per voxel (the first), with its normal."""
    if not len(points):
        return points, normals
    keys = np.floor(points / voxel).astype(np.int64)
    _, first, _ = unique_rows(keys)
    return points[first], normals[first]


def room_axes(
    normals: np.ndarray, max_yaw_deg: float = PlanesConfig.axes_yaw_deg
) -> list[np.ndarray]:
    """The room's three axes [up, wall 1, wall 2] from the points' normals: up is the mean
    of the normals within 25° then 10° of z (flipped upward; z where fewer than 50), the wall
    directions the peak of the horizontal normals' angle modulo 90° about it, within
    `max_yaw_deg` of the align stage's x and y (the world's walls; its axes can be a few
    degrees off, not more); 0 keeps the align stage's (`PlanesConfig.axes_yaw_deg`)."""
    unit = normals[np.linalg.norm(normals, axis=1) > 0.5]
    up = np.array([0.0, 0.0, 1.0])
    for cos in (np.cos(np.radians(25)), np.cos(np.radians(10))):
        near = unit[np.abs(unit @ up) >= cos]
        if len(near) < 50:
            break
        m = (near * np.sign(near @ up)[:, None]).mean(0)
        up = m / max(float(np.linalg.norm(m)), 1e-12)
    e1 = np.array([1.0, 0.0, 0.0]) - up[0] * up
    e1 /= max(float(np.linalg.norm(e1)), 1e-12)
    e2 = np.cross(up, e1)
    horiz = unit[np.abs(unit @ up) < 0.3]
    yaw = 0.0
    if len(horiz) >= 50 and max_yaw_deg > 0:
        # the angle modulo the right angle, in [-45°, 45°): 0 is the align stage's walls
        ang = np.mod(np.arctan2(horiz @ e2, horiz @ e1) + np.pi / 4, np.pi / 2) - np.pi / 4
        hist, _ = np.histogram(ang, bins=180, range=(-np.pi / 4, np.pi / 4))
        hist = gaussian_filter1d(hist.astype(np.float64), 2.0, mode="wrap")
        centres = (np.arange(180) + 0.5) * (np.pi / 2) / 180 - np.pi / 4
        near = np.abs(centres) <= np.radians(max_yaw_deg)
        # a peak that does not stand out of the spread is noise: the align stage's axes stay
        if hist[near].max() >= YAW_PEAK * hist.mean():
            yaw = centres[near][np.argmax(hist[near])]
    c, s = np.cos(yaw), np.sin(yaw)
    return [up, c * e1 + s * e2, -s * e1 + c * e2]


def find_planes(
    points: np.ndarray,
    normals: np.ndarray,
    cfg: PlanesConfig,
    feet: Callable[..., list] | None = None,
) -> list[Plane]:
    """Planes along the room's three axes (see the module's docstring).

    Args:
        points: [N, 3] world points (thinned or not: they are thinned to cfg.voxel here).
        normals: [N, 3] unit normals, or zeros where unknown (SfM tracks): those vote on
            every axis.
        feet: walls seen by their foot on the floor (`bases.wall_feet` over the views):
            called with the floor's normal and offset and the two wall axes, it gives
            (normal, offset, views) per wall; each one on whose side of the room no wall
            stereo read stands becomes a wall spanning the room (`_foot_walls`).
    Returns:
        at most cfg.max_planes planes, the floor first, then by decreasing support.
    """
    pts, nrm = thin(np.asarray(points, np.float64), np.asarray(normals, np.float64), cfg.voxel)
    axes = floor_axes(pts, nrm, room_axes(nrm, cfg.axes_yaw_deg), cfg)
    known = np.linalg.norm(nrm, axis=1) > 0.5
    found: list[Found] = []
    tops: list[Found] = []  # the local tops (_local_tops), kept ahead of weaker planes
    for k, a in enumerate(axes):
        votes = ~known | (np.abs(nrm @ a) >= cfg.normal_cos)
        peaks = _axis_planes(pts, votes, a, cfg)
        if k and cfg.turned_deg > cfg.max_tilt_deg:
            peaks = _turned(pts, votes, peaks, a, axes[0], cfg)
        local = _local_tops(pts, votes, a, peaks, cfg) if k == 0 and cfg.top_tile > 0 else []
        for j, (n, d, idx) in enumerate(peaks + local):
            inl = pts[idx]
            box = (np.percentile(inl, 2, 0), np.percentile(inl, 98, 0))
            cells = None
            if cfg.support_cell > 0:
                holes = cfg.top_holes if k == 0 else 0.0
                cells = Cells.of(n, inl, cfg.support_cell, cfg.cell_points, holes)
            found.append((n, d, len(idx), *box, cells))
            if j >= len(peaks):
                tops.append(found[-1])
    # the floor: the lowest horizontal plane within FLOOR_SEARCH of z = 0 (the align stage's
    # floor can sit a few cm off where stereo read little of a plain floor)
    floor = [
        f
        for f in found
        if f[0][2] > 0.97 and abs(f[1]) <= FLOOR_SEARCH and not any(f is t for t in tops)
    ]
    best = min(floor, key=lambda f: f[1]) if floor else None
    rest = [f for f in found if f is not best]
    if best is not None:
        best = _level_floor(best, pts, axes[0], cfg)
    # the floor spans the room (every point's box across), even where no point shows it
    box = (
        (np.percentile(pts, 2, 0), np.percentile(pts, 98, 0))
        if len(pts)
        else (np.zeros(3), np.zeros(3))
    )
    if best is None:  # the align stage put the floor at z = 0
        best = (axes[0], 0.0, 0, box[0], box[1], None)
    else:
        lo, hi = np.minimum(best[3], box[0]), np.maximum(best[4], box[1])
        lo[2], hi[2] = best[3][2], best[4][2]
        best = (best[0], best[1], best[2], lo, hi, None)
    rest.sort(key=lambda f: -f[2])
    # a local top (a table read at its rim) is kept ahead of the planes weaker than it is,
    # up to LOCAL_TOPS of them: its support is small by nature, and the strongest planes
    # that fill the cap are often a vertical slab of the floor's points across the room
    lead = [f for f in rest if any(f is t for t in tops)][:LOCAL_TOPS]
    bounds = _bounding_walls(pts, axes, rest, box, cfg) if cfg.bounding_walls else []
    room = box
    if feet is not None:
        walls, gone = _foot_walls(feet(best[0], best[1], axes[1:]), rest, box, best[1])
        rest = [f for f in rest if not any(f is g for g in gone)]  # a foot took their place
        if walls:  # the room reaches its walls' feet: the floor and the walls span it
            lo, hi = room = _reach(box, walls)
            walls = [(n, d, s_, lo.copy(), hi.copy(), None) for n, d, s_, *_ in walls]
            lo[2], hi[2] = best[3][2], best[4][2]
            best = (
                best[0],
                best[1],
                best[2],
                np.minimum(best[3], lo),
                np.maximum(best[4], hi),
                None,
            )
            bounds += walls
    room_for = max(0, cfg.max_planes - 1 - len(bounds) - len(lead))
    others = [f for f in rest if not any(f is t for t in lead)][:room_for]
    picked = sorted(lead + others, key=lambda f: -f[2])
    chosen = [best, *bounds, *picked]
    planes = _kinds(chosen)
    if cfg.top_grow > 0:
        planes = [
            _grown(p, pts, best[1], cfg) if p.kind == "top" and p.cells is not None else p
            for p in planes
        ]
    if cfg.walls_span:
        # the outermost walls a foot or stereo's reading shows (a weak outermost plane may
        # be furniture: spanning those without the feet, the honest procedural room's plane
        # fills fell from 68.0 to 60.3 % within 5 cm)
        up, base = best[0], best[1]
        shown = {k for k in _outer(chosen) if chosen[k][2] == 0 or _read(chosen[k], base)}
        planes = [_spanning(p, room, up, base) if k in shown else p for k, p in enumerate(planes)]
    return planes + free_planes(pts, nrm, planes, axes, cfg)


def _grown(p: Plane, pts: np.ndarray, floor: float, cfg: PlanesConfig) -> Plane:
    """The top with its support cells grown, up to cfg.top_grow, into the cells of its
    plane over which no point was read on the floor or between the floor and it (band
    clear of each), and its box grown to hold them: a surface whose unread part nothing
    seen under it contradicts (the office's sofa seat, read along its front edge only: the
    floor's plane filled the rest, and the plan drew floor through the sofa).

    A cell over read floor stops the growth, so a top does not spread over the open floor
    around it; cells nothing was read in at all, beyond the walls among them, do not, but
    no view's ray reaches a top's point there before the wall's."""
    c = p.cells
    if c is None:
        return p
    reach = int(np.ceil(cfg.top_grow / c.size))
    occ = np.pad(c.occupied, reach)
    origin = c.origin - reach * c.size
    h = pts @ p.normal - floor  # above the floor, along the top's normal
    under = pts[h < p.offset - floor - cfg.band]  # the floor and what stands below the top
    ij = np.floor((under @ c.axes.T - origin) / c.size).astype(np.int64)
    ok = (ij >= 0).all(1) & (ij[:, 0] < occ.shape[0]) & (ij[:, 1] < occ.shape[1])
    count = np.zeros(occ.shape, np.int64)
    np.add.at(count, (ij[ok, 0], ij[ok, 1]), 1)
    grown = binary_dilation(occ, iterations=reach, mask=(count < cfg.cell_points) | occ)
    # the box takes in the new cells' centres (on the plane)
    i, j = np.nonzero(grown & ~occ)
    lo, hi = p.lo.copy(), p.hi.copy()
    if len(i):
        uv = origin + (np.stack([i, j], 1) + 0.5) * c.size
        x = uv @ c.axes + p.offset * p.normal
        lo[:2] = np.minimum(lo[:2], x[:, :2].min(0))
        hi[:2] = np.maximum(hi[:2], x[:, :2].max(0))
    cells = Cells(c.axes, origin, c.size, grown)
    return Plane(p.normal, p.offset, p.kind, lo, hi, p.support, cells)


def _outer(found: list) -> set[int]:
    """Indices of the vertical hypotheses (Found or Plane fields) no parallel one lies beyond:
    the outermost on each side of each wall axis."""
    vert = [i for i, f in enumerate(found) if abs(f[0][2]) <= 0.9]
    out = set()
    for i in vert:
        ni, di = found[i][0], found[i][1]
        offs = [
            found[j][1] * np.sign(found[j][0] @ ni) for j in vert if abs(found[j][0] @ ni) > 0.99
        ]
        if di >= max(offs) or di <= min(offs):
            out.add(i)
    return out


def _spanning(p: Plane, room: tuple, up: np.ndarray, floor: float) -> Plane:
    """A wall across the room (its box grown to the room's), from the floor to WALL_TOP
    above it at least, standing upright on the floor (turned about the line where it
    crosses its inliers' box's centre height: a wall refitted within max_tilt_deg of an axis
    that leans off the floor's normal drifts 5 cm a metre above or below its inliers)."""
    lo, hi = np.minimum(p.lo, room[0]), np.maximum(p.hi, room[1])
    lo[2] = min(float(p.lo[2]), floor)
    hi[2] = max(float(p.hi[2]), floor + WALL_TOP)
    n = p.normal - (p.normal @ up) * up
    n /= max(float(np.linalg.norm(n)), 1e-12)
    centre = 0.5 * (p.lo + p.hi)
    on = centre - (p.normal @ centre - p.offset) * p.normal  # on the plane, at that height
    return Plane(n, float(n @ on), p.kind, lo, hi, p.support, p.cells)


def free_planes(
    pts: np.ndarray, nrm: np.ndarray, planes: list[Plane], axes: list, cfg: PlanesConfig
) -> list[Plane]:
    """Up to cfg.free_planes fronts of any orientation but near-horizontal, by RANSAC over the
    stereo points (known normals, not horizontal) that lie within `band` of no plane found
    along the room's axes (a turned one, `_turned`, excepted).

    A surface off the room's axes has no histogram peak, and the fill pastes the nearest axis
    plane over it. The Replica office's sofa back leans 11 degrees: it now gets a plane of its
    own, whose fills (10 k pixels) lie within 5 cm of the sensor for 82-90 % of them, and the
    office's photos plan went from 60.7 to 65.7 against its sensor at SfM poses. A plane is
    kept when its inliers number cfg.min_support, most of their own normals agree with it
    (cfg.normal_cos), and it leans more than twice max_tilt_deg off every room axis (nearer,
    the axes' refit already had the chance to take it).
    """
    if cfg.free_planes <= 0 or len(pts) == 0:
        return []
    known = np.linalg.norm(nrm, axis=1) > 0.5
    left = known & (np.abs(nrm @ axes[0]) < 0.9)
    off_axis = np.cos(np.radians(2 * cfg.max_tilt_deg))
    on_axis = np.cos(np.radians(cfg.max_tilt_deg + 0.5))
    for p in planes:  # a turned plane (_turned) leaves them: the office's sofa back, leaning
        #               before its turned whiteboard, crosses its band and lost its plane
        if max(abs(p.normal @ a) for a in axes) >= on_axis:
            left &= np.abs(pts @ p.normal - p.offset) > cfg.band
    idx = np.flatnonzero(left)
    rng = np.random.default_rng(0)
    out: list[Plane] = []
    for _ in range(4 * cfg.free_planes):  # tries: a rejected plane's points are set aside too
        if len(out) == cfg.free_planes or len(idx) < cfg.min_support:
            break
        plane, inl = plane_ransac(pts[idx], cfg.band, FREE_ITERS, rng)
        if len(inl) < cfg.min_support:
            break
        n = plane[:3] / np.linalg.norm(plane[:3])
        q, qn = pts[idx[inl]], nrm[idx[inl]]
        agree = float(np.mean(np.abs(qn @ n) >= cfg.normal_cos))
        if abs(n @ axes[0]) < 0.9 and agree >= 0.5 and max(abs(n @ a) for a in axes) < off_axis:
            if n @ np.median(qn, axis=0) < 0:  # facing where its points' normals face
                n = -n
            lo, hi = np.percentile(q, 2, 0), np.percentile(q, 98, 0)
            out.append(Plane(n, float(np.median(q @ n)), "front", lo, hi, len(inl)))
        idx = np.delete(idx, inl)
    return out


def floor_axes(pts: np.ndarray, nrm: np.ndarray, axes: list, cfg: PlanesConfig) -> list:
    """The room's axes with up along the floor's own normal: the floor by RANSAC among the
    points within FLOOR_SEARCH of z = 0 whose normals point up (or are unknown), its normal
    within FLOOR_TILT_DEG of `axes[0]`, refitted on its inliers. `axes` as they came where no
    such floor holds cfg.min_support.

    The align stage's floor comes from the sparse SfM points and can lie degrees off: on the
    honest procedural room (60 views, 37 registered) the floor the sensor sees lies 4.7
    degrees off the aligned z, and the normals' mean (room_axes) found 2.9 of them. The peaks
    along an axis refit each plane within `band` and `max_tilt_deg` of it, so such a floor
    keeps only the strip of it that crosses the band, at the axis's tilt: its fills lay
    within 5 cm of the sensor for 64 % of their pixels (median error 3.9 cm), against 99.8 %
    (7 mm) with the floor's normal as up, and the table tops turned with it (0.4 and 4 % ->
    95 and 92 %). The wall axes stay: turned with the floor (made perpendicular to it) they
    moved the office's whiteboard front onto another strip of its points, and the fills on
    the board fell from 77 to 32 % within 5 cm.
    """
    up = axes[0]
    known = np.linalg.norm(nrm, axis=1) > 0.5
    near = pts[(np.abs(pts @ up) <= FLOOR_SEARCH) & (~known | (nrm @ up >= cfg.normal_cos))]
    if len(near) < cfg.min_support:
        return axes
    plane, inl = plane_ransac(near, cfg.band, FREE_ITERS, np.random.default_rng(0))
    n = plane[:3] / max(float(np.linalg.norm(plane[:3])), 1e-12)
    if len(inl) < cfg.min_support or abs(n @ up) < np.cos(np.radians(FLOOR_TILT_DEG)):
        return axes
    q = near[inl]
    for _ in range(3):  # least squares on the inliers, then on the points within band of it
        mu = q.mean(0)
        n = np.linalg.svd(q - mu, full_matrices=False)[2][-1]
        n = n * np.sign(n @ up)
        q = near[np.abs((near - mu) @ n) <= cfg.band]
        if len(q) < cfg.min_support:
            return axes
    # the aligned z itself where it holds the floor as well as the refit: fitted to the
    # points near the cameras, the refit leans a few tenths of a degree where the align
    # stage's up can be exact (the honest room's level cameras: 0.38 degrees against 0.03),
    # and a wall's foot, cast onto the floor 3-4 m away at a grazing angle, moves 6 cm for
    # 0.3 degrees (its x walls' fills fell to 0 % within 5 cm). z holds 98.9 % of the
    # refit's floor points there, 99.7 % on the office, 97.8 % on the kitchen, 47.8 % on
    # the honest room aligned 4.7 degrees off (which the refit is for). Honest room's plane
    # fills 91.0 -> 92.4 % within 5 cm (82.3 -> 88.8 % within 3 cm), plan 87.37 -> 87.47;
    # office plan 80.48 -> 80.12 (its refit 0.07 degrees off z); the kitchen's fill is
    # undone either way (docs/figures.md#align-level)
    z = np.array([0.0, 0.0, 1.0])
    if _holds(near, q, z, cfg.band):
        return [z, axes[1], axes[2]]
    return [n, axes[1], axes[2]]


def _holds(pts: np.ndarray, q: np.ndarray, axis: np.ndarray, band: float) -> bool:
    """Whether the plane along `axis` through the median of a refit plane's band points q
    holds Z_HOLDS of as many of pts within band as the refit does."""
    return int((np.abs(pts @ axis - np.median(q @ axis)) <= band).sum()) >= Z_HOLDS * len(q)


def _level_floor(best: Found, pts: np.ndarray, up: np.ndarray, cfg: PlanesConfig) -> Found:
    """The floor peak along `up` itself where up holds its points as well as its refit
    (`_holds`). The peaks refit each plane within max_tilt_deg of their axis, and the floor's
    points lie near the cameras: on the honest procedural room the refit leaned 0.16 degrees
    off a z that lay 0.03 off the sensor's floor, and the walls' feet, cast onto that floor
    at a grazing angle 4-5 m away, moved 3 cm out (the far wall's fills 54 % within 3 cm)."""
    n, d = best[0], best[1]
    q = pts[np.abs(pts @ n - d) <= cfg.band]
    if len(q) == 0 or n @ up >= 1.0 or not _holds(pts, q, up, cfg.band):
        return best
    return (np.asarray(up, np.float64), float(np.median(q @ up)), *best[2:])


def _foot_walls(feet: list, found: list, box: tuple, floor: float) -> tuple[list, list]:
    """The walls of `feet` ((normal, offset, views)) as hypotheses spanning `box`, where no
    wall stereo read stands on the foot's side of the room (a vertical plane whose inliers
    fill READ_WALL of it and reach READ_TOP above the floor `floor`). A read wall within
    0.1 m of the foot is that wall; one beyond it makes the foot a piece of furniture's
    base, one before it a mark on it or an edge in front of it. On the Replica office,
    whose walls stereo reads (2.5-3.9 m² of 10 cm cells, up to 1.4-2.2 m), the feet lay
    0.14-0.49 m beyond its walls, 0.25-0.3 m inside them, or 1.1 m beyond the wall behind
    its sofa (the sofa back's top edge). On the honest procedural room no wall is read
    (the planes the points show there fill 0.2-0.6 m², or 1.5 m² of a bed's side 0.33 m
    high), and the feet's lines fit the sensor's wall points better than the planes the
    points gave near them: 94.6 against 69.1 % within 5 cm on one wall, 74.3 against 74.0
    on another. A foot takes the place of the planes within 0.1 m of it and beyond it (one
    of 152 voxels lay 0.1 m behind a wall: 8.6 % of that wall's sensor points within 5 cm).
    Returns (walls, the planes of `found` a foot replaced).
    """
    out: list[Found] = []
    gone: list[Found] = []
    told = []
    for n, d, views in feet:
        n = np.asarray(n, np.float64)
        # the parallel planes on the foot's side of the room's middle
        mid = float(n @ (0.5 * (box[0] + box[1])))
        par = [(f, float(f[1] * np.sign(f[0] @ n))) for f in found if abs(f[0] @ n) > 0.99]
        side = [(f, o) for f, o in par if o > mid]
        read = [t for t in side if _read(t[0], floor)]
        if read:
            f, o = max(read, key=lambda t: t[1])
            if abs(o - d) < 0.1:
                what = "the wall read there"
            else:
                what = f"a wall read over {_area(f):.1f} m² at {o:+.2f}"
        else:
            gone += [f for f, o in side if o > d - 0.1]
            out.append((n, float(d), 0, box[0].copy(), box[1].copy(), None))
            what = "a wall"
        told.append(f"{np.round(n[:2], 2).tolist()} {d:+.2f} ({views} views): {what}")
    if told:
        log.info("depth/planes: walls' feet: %s", "; ".join(told))
    return out, gone


def _read(f: Found, floor: float) -> bool:
    """Whether a vertical hypothesis is a wall stereo read (READ_WALL, READ_TOP)."""
    return _area(f) >= READ_WALL and f[4][2] - floor >= READ_TOP


def _area(f: Found) -> float:
    """m² of a hypothesis's plane its inliers' cells fill (0 without cells)."""
    cells = f[5]
    return 0.0 if cells is None else float(cells.occupied.sum()) * cells.size**2


def _reach(box: tuple, walls: list) -> tuple[np.ndarray, np.ndarray]:
    """`box` grown along each wall's main axis to the wall."""
    lo, hi = box[0].copy(), box[1].copy()
    for n, d, *_ in walls:
        k = int(np.argmax(np.abs(n[:2])))
        at = d / n[k] if abs(n[k]) > 1e-6 else 0.0
        lo[k], hi[k] = min(lo[k], at), max(hi[k], at)
    return lo, hi


def _bounding_walls(pts: np.ndarray, axes: list, found: list, box: tuple, cfg: PlanesConfig):
    """Walls no peak shows (plain paint: stereo reads nothing there): on each side of each
    wall axis, a plane at the outermost points' offset (their 0.2th / 99.8th percentile),
    spanning the room, unless a found vertical plane lies within 0.1 m of it."""
    out: list[Found] = []
    if len(pts) < cfg.min_support:
        return out
    for a in axes[1:]:
        off = pts @ a
        for q, sign in ((0.2, -1.0), (99.8, 1.0)):
            d = float(np.percentile(off, q))
            if any(abs(f[0] @ a) > 0.99 and abs(f[1] * (f[0] @ a) - d) < 0.1 for f in found):
                continue
            out.append((a * sign, d * sign, 0, box[0].copy(), box[1].copy(), None))
    return out


def _axis_planes(
    pts: np.ndarray, votes: np.ndarray, axis: np.ndarray, cfg: PlanesConfig
) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """(normal, offset, inlier indices) of the histogram peaks along one axis."""
    sel = np.flatnonzero(votes)
    if len(sel) < cfg.min_support:
        return []
    off = pts[sel] @ axis
    lo = np.floor(off.min() / cfg.bin) - 3
    bins = int(np.ceil(off.max() / cfg.bin) - lo) + 4
    hist = np.bincount((np.floor(off / cfg.bin) - lo).astype(np.int64), minlength=bins)
    sm = gaussian_filter1d(hist.astype(np.float64), cfg.smooth)
    # a plane's peak holds about its support spread over the band's bins
    height = cfg.min_support / max(1.0, 2 * cfg.band / cfg.bin)
    peaks, _ = find_peaks(sm, height=height, distance=max(1, int(round(cfg.band / cfg.bin))))
    out: list[tuple[np.ndarray, float, np.ndarray]] = []
    for p in peaks[np.argsort(-sm[peaks])]:
        d0 = (lo + p + 0.5) * cfg.bin
        fit = _refit(pts[sel], axis, d0, cfg)
        if fit is None:
            continue
        n, d, idx = fit
        if any(abs(d - d2) < cfg.band and n @ n2 > 0.999 for n2, d2, _ in out):
            continue  # the same plane from two neighbouring peaks
        out.append((n, d, sel[idx]))
    return out


def _local_tops(
    pts: np.ndarray,
    votes: np.ndarray,
    up: np.ndarray,
    peaks: list,
    cfg: PlanesConfig,
) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Horizontal planes a tile of the floor shows and the room's histogram does not: the
    peaks of each tile's own offset histogram (tiles of cfg.top_tile, two grids half a tile
    apart) LOCAL_ABOVE over the floor, holding LOCAL_SUPPORT voting voxels and LOCAL_SHARE of
    the tile's within band, each refitted (within band and max_tilt_deg of up) on its tile's
    points alone so that its cells stay where it was seen; two at one height whose tiles
    touch are one plane; none within band of a room-wide peak.

    The room's histogram along up sums every voting point, and those whose normal is
    unknown (sparse stereo: a reading without its four neighbours) spread over all heights
    on the walls: a table read only at its rim lies on that hump's flank and makes no peak
    of its own (the office's table at 0.46-0.50 m beside a peak at 0.54 m, its top then
    filled with the floor's plane). In a tile beside a wall the same points give a flat
    histogram whose bumps hold 2-4 % of the tile; the table's peak holds 40 % of its tile."""
    known = [d for _, d, _ in peaks]
    # above the floor: the lowest peak within FLOOR_SEARCH of z = 0, as find_planes takes it
    base = min((d for d in known if abs(d) <= FLOOR_SEARCH), default=0.0)
    sel = np.flatnonzero(votes)
    off = pts[sel] @ up
    high = off >= base + LOCAL_ABOVE
    sel, off = sel[high], off[high]
    if len(sel) < LOCAL_SUPPORT:
        return []
    side = np.array([1.0, 0.0, 0.0]) - up[0] * up
    side /= max(float(np.linalg.norm(side)), 1e-12)
    uv = pts[sel] @ np.stack([side, np.cross(up, side)]).T
    lo = np.floor(off.min() / cfg.bin) - 3  # margins: a peak at either end is a peak
    nb = int(np.ceil(off.max() / cfg.bin) - lo) + 4
    b = (np.floor(off / cfg.bin) - lo).astype(np.int64)
    height = LOCAL_SUPPORT / max(1.0, 2 * cfg.band / cfg.bin)
    found: list[tuple[int, float, np.ndarray]] = []  # (support, offset, indices into sel)
    for shift in (0.0, 0.5):
        tile = np.floor(uv / cfg.top_tile + shift).astype(np.int64)
        _, t_id = np.unique(tile, axis=0, return_inverse=True)
        t_id = t_id.reshape(-1)
        n_t = int(t_id.max()) + 1
        hist = np.bincount(t_id * nb + b, minlength=n_t * nb).reshape(n_t, nb).astype(float)
        sm = gaussian_filter1d(hist, cfg.smooth, axis=1)
        total = hist.sum(1)
        order = np.argsort(t_id, kind="stable")  # the points of tile t: members[t]
        members = np.split(order, np.cumsum(np.bincount(t_id, minlength=n_t))[:-1])
        for t in np.flatnonzero(total >= LOCAL_SUPPORT):
            tops, _ = find_peaks(sm[t], height=height, distance=max(1, int(cfg.band / cfg.bin)))
            in_t = members[t]
            for p in tops:
                d0 = (lo + p + 0.5) * cfg.bin
                if any(abs(d0 - d) < cfg.band for d in known):
                    continue
                mine = in_t[np.abs(off[in_t] - d0) <= cfg.band]
                if len(mine) >= max(LOCAL_SUPPORT, LOCAL_SHARE * total[t]):
                    found.append((len(mine), d0, mine))
    # strongest first; one at the height of a kept one whose points lie within a tile of
    # its points joins it
    kept: list[tuple[float, np.ndarray]] = []
    for _, d0, mine in sorted(found, key=lambda f: -f[0]):
        box = (uv[mine].min(0), uv[mine].max(0))
        for j, (e, idx) in enumerate(kept):
            near = np.all(uv[idx].min(0) <= box[1] + cfg.top_tile) and np.all(
                uv[idx].max(0) >= box[0] - cfg.top_tile
            )
            if abs(d0 - e) < cfg.band and near:
                kept[j] = (e, np.union1d(idx, mine))
                break
        else:
            kept.append((d0, mine))
    out: list[tuple[np.ndarray, float, np.ndarray]] = []
    for d0, idx in kept:
        fit = _refit(pts[sel[idx]], up, d0, cfg, LOCAL_SUPPORT)
        if fit is not None:
            out.append((fit[0], fit[1], sel[idx][fit[2]]))
    if out:
        log.info(
            "depth/planes: %d local tops at %s m",
            len(out),
            ", ".join(f"{d:.2f}" for _, d, _ in sorted(out, key=lambda o: o[1])),
        )
    return out


def _turned(
    pts: np.ndarray,
    votes: np.ndarray,
    peaks: list,
    axis: np.ndarray,
    up: np.ndarray,
    cfg: PlanesConfig,
) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """The peaks along a wall axis, and the surfaces turned about the vertical between
    max_tilt_deg and turned_deg off it that the points show near them; a peak most of whose
    inliers lie on such a surface is a strip of it, and gives way.

    A turned surface spreads over several offset bins, and a peak's refit within `band` and
    max_tilt_deg keeps the strip of it the peak crosses, at the axis's direction (the
    office's whiteboard, turned 3.1 degrees across 2.6 m: fronts 7 cm apart took strips of
    it, and their fills were 10 cm off at the board's far end). Around each peak (strongest
    first), the voting points within TURN_REACH of it vote again along the directions turned
    up to turned_deg about up, in steps of TURN_STEP degrees: the direction with the most
    points within `band` of one offset, when it lies beyond max_tilt_deg, inside the search's
    ends, and holds TURN_GAIN times the axis's most, is refitted (`_refit` about it). A
    Hough vote rather than RANSAC: deterministic, and a plain board's few, noisy readings
    decide by their count alone."""
    if not peaks:
        return peaks
    side = np.cross(up, axis)
    side /= max(float(np.linalg.norm(side)), 1e-12)
    yaw = np.radians(np.arange(-cfg.turned_deg, cfg.turned_deg + 1e-9, TURN_STEP))
    dirs = np.cos(yaw)[:, None] * axis + np.sin(yaw)[:, None] * side
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    at_axis = int(np.argmin(np.abs(yaw)))
    width = 2 * int(round(cfg.band / cfg.bin)) + 1  # bins within band of an offset
    sel = np.flatnonzero(votes)
    q = pts[sel]  # the voting points, and their offsets along the axis
    along = q @ axis
    added: list[tuple[np.ndarray, float, np.ndarray]] = []
    gone: set[int] = set()
    for i, (_, d0, _) in enumerate(peaks):
        if i in gone:
            continue
        near = np.abs(along - d0) <= TURN_REACH
        if near.sum() < cfg.min_support:
            continue
        off = q[near] @ dirs.T  # [M, D]
        lo = np.floor(off.min(0) / cfg.bin)
        b = np.floor(off / cfg.bin) - lo
        nb = int(b.max()) + 1
        flat = (b.astype(np.int64) + nb * np.arange(len(dirs))).reshape(-1)
        hist = np.bincount(flat, minlength=nb * len(dirs)).reshape(len(dirs), nb).astype(float)
        within = uniform_filter1d(hist, width, axis=1, mode="constant")  # within band
        best = within.max(1)
        k = int(np.argmax(best))
        if (
            np.degrees(np.arccos(min(1.0, float(dirs[k] @ axis)))) <= cfg.max_tilt_deg
            or best[k] < TURN_GAIN * best[at_axis]
            or k in (0, len(dirs) - 1)  # the most at the search's end: no turn located
        ):
            continue
        dk = (lo[k] + np.argmax(within[k]) + 0.5) * cfg.bin
        fit = _refit(q, dirs[k], dk, cfg)
        if fit is None:
            continue
        n, d, idx = fit
        if any(n @ m > 0.9995 and abs(d - e) < cfg.band for m, e, _ in added):
            continue  # found already, from another strip of it
        strips = [
            j
            for j, (_, _, ij) in enumerate(peaks)
            if j not in gone and np.mean(np.abs(pts[ij] @ n - d) <= cfg.band) > 0.5
        ]
        log.info(
            "depth/planes: a surface turned %.1f degrees off the axis at %+.2f (%d voxels); "
            "%d peaks were strips of it",
            np.degrees(np.arccos(min(1.0, float(n @ axis)))),
            d,
            len(idx),
            len(strips),
        )
        gone.update(strips)
        added.append((n, d, sel[idx]))
    return [p for j, p in enumerate(peaks) if j not in gone] + added


def _refit(
    pts: np.ndarray, axis: np.ndarray, d0: float, cfg: PlanesConfig, min_support: int = 0
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Least-squares plane on the points within band of n . X = d0, its normal kept within
    max_tilt_deg of the axis (a larger tilt falls back to the axis); None when fewer than
    min_support (cfg.min_support when 0) lie within band."""
    min_support = min_support or cfg.min_support
    n, d = axis, d0
    cos_max = np.cos(np.radians(cfg.max_tilt_deg))
    for _ in range(3):
        idx = np.flatnonzero(np.abs(pts @ n - d) <= cfg.band)
        if len(idx) < min_support:
            return None
        q = pts[idx]
        mu = q.mean(0)
        _, _, vt = np.linalg.svd(q - mu, full_matrices=False)
        m = vt[-1] * np.sign(vt[-1] @ axis or 1.0)
        n = m if m @ axis >= cos_max else axis
        d = float(np.median(q @ n))
    idx = np.flatnonzero(np.abs(pts @ n - d) <= cfg.band)
    if len(idx) < min_support:
        return None
    return n / np.linalg.norm(n), d, idx


def _kinds(found: list) -> list[Plane]:
    """Kinds: floor (the first), ceiling (the highest horizontal plane above 1.9 m), top
    (other horizontal), wall (the outermost vertical plane on each side of an axis, or one
    whose inliers rise above 1.8 m), front (other vertical)."""
    horiz = [i for i, f in enumerate(found) if abs(f[0][2]) > 0.9]
    high = [i for i in horiz[1:] if found[i][1] > 1.9]
    ceiling = max(high, key=lambda i: found[i][1]) if high else -1
    vert = [i for i, f in enumerate(found) if abs(f[0][2]) <= 0.9]
    walls = _outer(found) | {i for i in vert if found[i][4][2] > 1.8}
    planes = []
    for i, (n, d, sup, lo, hi, cells) in enumerate(found):
        if i == 0:
            kind = FLOOR_NAME
        elif i == ceiling:
            kind = CEILING_NAME
        elif i in horiz:
            kind = "top"
        else:
            kind = WALL_NAME if i in walls else "front"
        # the cells bound a top only: a floor, wall or ceiling spans its box (plain paint
        # between its inlier patches is still the wall), and so does a front (a wall with a
        # farther one beyond it is a front: limited to its cells, the office's plainer wall
        # went to a wrong plane, fills within 5 cm 69.8 -> 56.3 %)
        keep = cells if kind == "top" else None
        planes.append(Plane(np.asarray(n, np.float64), float(d), kind, lo, hi, int(sup), keep))
    return planes

"""Walls from the points the views saw: the room's bounding planes, where the mesh has none.

Photos alone leave plain walls in patches: stereo matches their textured strips (a
backsplash, what hangs on them, the corners) and the fused surface, carved to what two
views support, keeps too little of a wall for a RANSAC plane over its triangles to pass
the wall bounds (the 7-Scenes kitchen's wall behind the counters: 0.24 m² of triangles
against 0.5). The points are more: the SfM tracks and every depth reading the fusion read
(stereo, the field where stereo confirmed it), in the aligned world.

A wall bounds the room: the cameras stand on one side of it and the views' readings end on
it (a reading beyond it saw through it). So, along each of the room's four horizontal
directions (the turn at which the readings' offsets pile up most sharply, and its quarter
turns: near x and y once the align stage squared the world), the offsets of the points are
scanned from the outside in, and the plane that holds the most readings (within `dist`,
spanning the wall bounds in length and height, covering `min_area` on cells of
`COVER_CELL`) with few beyond it (at most `max_beyond` of its own, within its length) and
every camera on the inner side is a wall. Its extent: along the wall, the run of
`COVER_CELL` cells from its first reading to its last, grown over the neighbouring cells
where the views saw the room and nothing through it; in height, from the floor up to its
readings' top and at least `top` (a wall reaches over the views' heads; the readings stop
where the views stop looking). The wall is then turned to the least-squares line through
its readings (by at most MAX_TURN: the room's direction is a compromise of every wall,
front and table) and found again.

A cabinet front or a table's side is not taken: readings lie beyond it (the counter top,
the wall behind).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.camera import unproject
from stages.common.capture import Capture
from stages.common.classes import WALL_NAME
from stages.common.io import read_depth
from stages.common.rows import unique_rows

COVER_CELL = 0.1  # metres: cells (along the wall x height) for the coverage and the extent
MAX_TURN = 3.0  # degrees: a wall's direction is the room's turned by at most this
VOXEL = 0.02  # metres: readings are thinned to one per voxel (dense stereo would outvote SfM)


@dataclass(frozen=True)
class PointWallOptions:
    """What makes a plane of points a wall (see the module doc)."""

    dist: float  # metres: a reading this close to the plane is on it
    min_length: float  # metres along the wall (5-95 %) its readings span at least
    min_height: float  # metres in z (5-95 %) its readings span at least
    min_area: float  # m²: the COVER_CELL cells its readings cover
    max_beyond: float  # readings beyond the plane (within its length), per reading on it
    top: float  # metres: the wall reaches at least this high
    # a reading counts as beyond the plane when it lies more than dist + beyond_rel x its
    # range (metres from the camera that took it) past it: depth from photos errs in
    # proportion to the range, and a plain wall's own readings 2-3 m away scatter up to
    # 10 cm either side of it (needs the readings' cameras; 0: dist alone)
    beyond_rel: float = 0.0


def evidence_points(frames: list[Capture], stride: int = 2) -> np.ndarray:
    """World points [N, 3] of every depth reading of the frames (every `stride`-th pixel each
    way), thinned to one per VOXEL. Depth maps at another resolution than the intrinsics
    (stereo's sweep resolution) are read with the intrinsics scaled to them."""
    return evidence_readings(frames, stride)[0]


def evidence_readings(frames: list[Capture], stride: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """As evidence_points, with the centre of the camera each kept reading was taken from:
    (points [N, 3], cameras [N, 3])."""
    out, eye = [np.zeros((0, 3))], [np.zeros((0, 3))]
    for cap in frames:
        for f in cap.frames:
            if f.depth is None or f.pose is None:
                continue
            d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)  # [H, W]
            k = f.intrinsics.scaled(d.shape[1], d.shape[0]).K
            sparse = (d > 0).mean() < 0.05  # SfM tracks: every reading counts
            step = 1 if sparse else stride
            v, u = np.nonzero(d[::step, ::step] > 0)
            v, u = v * step, u * step
            uv = np.stack([u, v], axis=1).astype(np.float64)
            pose = np.asarray(f.pose, np.float64)
            out.append(unproject(uv, d[v, u], k, pose))
            eye.append(np.broadcast_to(pose[:3, 3], (len(v), 3)))
    p, c = np.concatenate(out), np.concatenate(eye)
    if len(p) == 0:
        return p, c
    keys = np.floor(p / VOXEL).astype(np.int64)
    _, first, _ = unique_rows(keys)
    first = np.sort(first)
    return p[first], c[first]


def room_directions(points: np.ndarray, bin_m: float) -> np.ndarray:
    """The four horizontal unit directions [4, 3] of the room's walls: the turn about z, in
    [0, 90) degrees, at which the readings' offsets along the two axes pile up most sharply
    (the largest sum of squared counts over bins of `bin_m`: walls, fronts and shelves of a
    square room all lie across the same two directions), and its quarter turns. A search
    rather than the mesh's normals: a plain wall's noisy patches tilt their normals, and a
    direction 5 degrees off spreads a 2.4 m wall's readings over 20 cm."""
    xy = points[:, :2]

    def sharpness(deg: float) -> float:
        a = np.radians(deg)
        total = 0.0
        for ang in (a, a + np.pi / 2):
            s = xy @ np.array([np.cos(ang), np.sin(ang)])
            h = np.bincount(np.floor((s - s.min()) / bin_m).astype(np.int64))
            total += float((h.astype(np.float64) ** 2).sum())
        return total

    if len(points) < 2:
        best = 0.0
    else:
        coarse = np.arange(0.0, 90.0, 1.0)
        best = float(coarse[np.argmax([sharpness(d) for d in coarse])])
        fine = best + np.arange(-1.0, 1.01, 0.1)
        best = float(fine[np.argmax([sharpness(d) for d in fine])])
    a = np.radians(best) + np.arange(4) * np.pi / 2
    return np.stack([np.cos(a), np.sin(a), np.zeros(4)], axis=1)


def point_walls(
    points: np.ndarray,
    cams: np.ndarray,
    directions: np.ndarray,
    floor_z: float,
    opt: PointWallOptions,
    eyes: np.ndarray | None = None,
) -> list[dict]:
    """The room's bounding walls among the points (see the module doc), at most one per
    direction, as the segmentation's plane dicts (kind "wall", normal facing the room, d,
    area_m2, triangles 0, box [s0, z0, s1, z1], span, source "points"). eyes [N, 3]: the
    camera each reading was taken from (evidence_readings), for opt.beyond_rel."""
    # metres past the plane beyond which a reading saw through it, per reading
    past = np.full(len(points), opt.dist)
    if eyes is not None and opt.beyond_rel > 0:
        past = past + opt.beyond_rel * np.linalg.norm(points - eyes, axis=1)
    walls = []
    for n in directions:
        got = _outermost(points, cams, n, floor_z, opt, past)
        if got is None:
            continue
        # the wall's own direction: the least-squares line through its readings (in the plan)
        # within MAX_TURN of the room's, which put it within reach of them
        s, u = points @ n, points @ np.array([-n[1], n[0], 0.0])
        on = np.abs(s - (got[1]["d"])) < opt.dist
        slope = np.polyfit(u[on], s[on], 1)[0] if on.sum() >= 3 else 0.0
        a = np.clip(np.arctan(slope), -np.radians(MAX_TURN), np.radians(MAX_TURN))
        m = np.array([n[0] * np.cos(a) - n[1] * np.sin(a), n[0] * np.sin(a) + n[1] * np.cos(a), 0])
        turned = _outermost(points, cams, m, floor_z, opt, past)
        walls.append((turned or got)[1])
    return walls


def _outermost(
    p: np.ndarray,
    cams: np.ndarray,
    n: np.ndarray,
    floor_z: float,
    opt: PointWallOptions,
    past: np.ndarray | None = None,
) -> tuple[int, dict] | None:
    """The wall along n (see the module doc) with the count of its readings, or None;
    past [N]: metres past the plane beyond which each reading saw through it (opt.dist)."""
    past = np.full(len(p), opt.dist) if past is None else past
    s = p @ n  # [N] offset outwards along n
    along = np.array([-n[1], n[0], 0.0])  # the segmentation's axis along a vertical plane
    u = p @ along
    inner = float((cams @ n).max()) if len(cams) else -np.inf
    step = opt.dist / 2.0
    hi = np.percentile(s, 99.9) if len(s) else -np.inf
    best, best_n = None, 0
    for s0 in np.arange(hi, inner + opt.dist, -step):
        on = np.abs(s - s0) < opt.dist
        k = int(on.sum())
        if k < max(10, best_n):
            continue
        lo_u, hi_u = np.percentile(u[on], [5, 95])
        lo_z, hi_z = np.percentile(p[on, 2], [5, 95])
        uz = np.floor(np.stack([u[on], p[on, 2]], 1) / COVER_CELL).astype(np.int64)
        cells = unique_rows(uz)[0]
        beyond = (s > s0 + past) & (u >= lo_u) & (u <= hi_u)
        if (
            hi_u - lo_u >= opt.min_length
            and hi_z - lo_z >= opt.min_height
            and len(cells) * COVER_CELL**2 >= opt.min_area
            and beyond.sum() <= opt.max_beyond * k
        ):
            best, best_n = (float(s0), (hi_u - lo_u, hi_z - lo_z), len(cells)), k
    if best is None:
        return None
    s0, (length, height), n_cells = best
    s0 = float(np.median(s[np.abs(s - s0) < opt.dist]))  # refined
    on = np.abs(s - s0) < opt.dist
    lo, hi_ext = _extent(u, s, on, s0, past)
    top = max(float(p[on, 2].max()), opt.top)
    normal = -n  # facing the room (the cameras)
    return int(on.sum()), {
        "kind": WALL_NAME,
        "normal": [round(float(x), 4) for x in normal],
        "d": round(s0, 4),  # normal @ x + d = 0 on the plane: -s + s0
        "area_m2": round(n_cells * COVER_CELL**2, 3),
        "triangles": 0,
        # the box in (s along the plane's axis, z): the axis of -n is -along
        "box": [round(-hi_ext, 4), round(floor_z, 4), round(-lo, 4), round(top, 4)],
        "span": [round(float(length), 3), round(float(height), 3)],
        "source": "points",
        "dist": opt.dist,
    }


def _extent(u: np.ndarray, s: np.ndarray, on: np.ndarray, s0: float, past: np.ndarray
            ) -> tuple[float, float]:  # fmt: skip
    """Along the wall: the run of cells from its first reading to its last, grown over the
    neighbouring cells where the views saw the room (some reading lies there) and no more
    readings lie beyond the plane than on it."""
    edges = np.arange(u.min(), u.max() + COVER_CELL, COVER_CELL)
    if len(edges) < 2 or not on.any():
        return float(u[on].min()), float(u[on].max())
    n_on = np.histogram(u[on], edges)[0]
    n_beyond = np.histogram(u[s > s0 + past], edges)[0]
    n_any = np.histogram(u, edges)[0]
    i0, i1 = np.searchsorted(edges, [u[on].min(), u[on].max()], side="right") - 1
    i0, i1 = max(int(i0), 0), min(int(i1), len(n_on) - 1)
    free = (n_beyond <= n_on) & (n_any > 0)
    lo, hi = float(u[on].min()), float(u[on].max())
    while i0 > 0 and free[i0 - 1]:
        i0 -= 1
        lo = float(edges[i0])
    while i1 < len(free) - 1 and free[i1 + 1]:
        i1 += 1
        hi = float(edges[i1 + 1])
    return lo, hi

"""Floor, walls, ceiling and object instances of a triangle mesh in the aligned world.

Every triangle gets a class (semantics.config CLASSES, or UNKNOWN) and an object instance
id (0 = none), from its centre, unit normal and area:

1. Floor: RANSAC planes (stages.common.ransac: seeded, the same planes every run) over the
   horizontal triangles facing up whose centre is within `planes.floor_max_z` of z = 0;
   ceiling: the same over horizontal triangles facing down above `planes.ceiling_min_z`. A
   plane counts when its inliers (within `planes.plane_dist`, normal within
   `planes.max_tilt_deg`) cover `planes.min_area`.
2. Walls: RANSAC planes over the remaining vertical triangles; a plane is a wall when its
   inliers span `walls.min_height` in z, `walls.min_length` along the floor and cover
   `walls.min_area` (a cabinet front is too low, a chair back too small), it stands within
   `walls.max_lean_deg` of upright on the floor, and no other such plane, nor a wall from
   the views' points, stands behind it within `walls.behind` (blinds before a window wall,
   cubicle panels, tall cabinets against a wall, a whiteboard before a plain wall: the wall
   is the outermost surface). Planes that fail stay in the object pool, except one before a
   wall that hangs clear of the floor (blinds, a curtain, a whiteboard: unknown), and with it
   what lies from `walls.hanger_slab` before it to the wall behind it, along the stretches it
   covers (its frame, legs and stand); one that hangs within `walls.hanger_slab` of that wall
   (blinds, a curtain over a window) closes it: wall, with what lies by it.
3. Unlabelled triangles within `planes.plane_dist` of an accepted plane, inside its extent, join it
   whatever their normal: the rounded seams of the TSDF surface where a wall meets the
   floor would otherwise form thin "objects" along every wall. A wall takes none that faces
   up: that is the top of what stands against it (a sofa's back, a counter).
4. Objects: the rest, clustered by DBSCAN (Open3D `cluster_dbscan`) on voxels of
   cluster_eps / 2. A cluster is an object instance when it covers `objects.min_area` and its
   lowest point is within `objects.max_gap` of the floor; smaller clusters, DBSCAN noise and
   clusters hanging higher (wall cabinets, lamps, fused noise) are labelled UNKNOWN: a plan
   holds what stands on the floor, and no class is invented for them; except a table top
   whose legs no view fused (a cluster mostly facing up, at table height), or what rests on
   a standing object (a plant on its stand): objects.py.
   Each cluster is split into pieces where its top height steps by more than `objects.piece_step`
   (pieces.py): a counter run, the island beside it, a wardrobe, a chair's seat by a table
   are instances of their own.

Mesh normals of the TSDF surface point to free space (checked on the fused rooms: every
floor triangle faces up), which tells a floor from the underside of a table top.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from stages.common.capture import UNKNOWN
from stages.common.classes import (
    CEILING,
    CEILING_NAME,
    FLOOR,
    FLOOR_NAME,
    WALL,
    WALL_NAME,
)
from stages.common.ransac import plane_ransac
from stages.semantics.config import SemanticsConfig
from stages.semantics.objects import objects
from stages.semantics.segmentation import Segmentation

log = logging.getLogger(__name__)

SPAN_PCT = (5.0, 95.0)  # robust extent of a plane's inliers (percentiles)
PARALLEL_COS = float(np.cos(np.radians(15.0)))  # two walls this near parallel face one way
HANGS = 0.1  # metres: a surface before a wall whose lowest inliers (5 %) lie higher hangs


def triangles(verts: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres [T, 3], unit normals [T, 3] (zero when degenerate) and areas [T] (m²)."""
    p = np.asarray(verts, np.float64)[np.asarray(tris, np.int64)]  # [T, 3, 3]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # [T, 3]
    norm = np.linalg.norm(cross, axis=1)  # [T]
    normal = cross / np.where(norm > 0, norm, 1.0)[:, None]
    return p.mean(axis=1), normal, norm / 2.0


# more walls from elsewhere than the mesh's triangles (pointwalls.py): given the triangles'
# centres, normals and areas and the floor's height, plane dicts as _describe's, each with
# the "dist" within which triangles join it
MoreWalls = Callable[[np.ndarray, np.ndarray, np.ndarray, float], list[dict]]


def segment(
    verts: np.ndarray, tris: np.ndarray, cfg: SemanticsConfig, more_walls: MoreWalls | None = None
) -> Segmentation:
    """Classify every triangle of a mesh (world metres, z up, floor at z = 0).

    Args:
        verts: [V, 3] vertex positions. tris: [T, 3] vertex indices.
        more_walls: walls found elsewhere (the views' points); one that lies on a wall the
            mesh gave (facing the same way, within its dist) is dropped.
    """
    rng = np.random.default_rng(cfg.seed)
    c, n, area = triangles(verts, tris)
    t = len(c)
    seg = Segmentation(np.full(t, UNKNOWN, np.uint8), np.zeros(t, np.int32), area)
    cos_t, sin_t = (
        np.cos(np.radians(cfg.planes.max_tilt_deg)),
        np.sin(np.radians(cfg.planes.max_tilt_deg)),
    )
    ok = area > 0
    horiz = ok & (np.abs(n[:, 2]) > cos_t)
    vert = ok & (np.abs(n[:, 2]) < sin_t)

    pool = horiz & (n[:, 2] > 0) & (np.abs(c[:, 2]) < cfg.planes.floor_max_z)
    for plane, inl in _planes(c, n, area, pool, cfg, rng, horizontal=True):
        if area[inl].sum() >= cfg.planes.min_area:
            _accept(seg, plane, inl, FLOOR_NAME, FLOOR, c, area)
    floor = seg.cls == FLOOR
    if floor.any():
        seg.floor_z = float(np.median(c[floor, 2]))
    pool = horiz & (n[:, 2] < 0) & (c[:, 2] > cfg.planes.ceiling_min_z)
    for plane, inl in _planes(c, n, area, pool, cfg, rng, horizontal=True):
        if area[inl].sum() >= cfg.planes.min_area:
            _accept(seg, plane, inl, CEILING_NAME, CEILING, c, area)
    pool = vert & (seg.cls == UNKNOWN)
    found = []
    floors = [p["normal"] for p in seg.planes if p["kind"] == FLOOR_NAME]
    up = np.asarray(floors[0], np.float64) if floors else np.array([0.0, 0.0, 1.0])
    for plane, inl in _planes(c, n, area, pool, cfg, rng, horizontal=False):
        if _is_wall(plane, c[inl], area[inl], cfg, up):
            found.append((plane, inl))
        else:
            seg.rejected.append(_describe(plane, inl, "vertical", c, area))
            log.debug("semantics: not a wall %s", seg.rejected[-1])
    # the walls the views' points give (found before the fronts are told from the walls: a
    # board standing before a plain wall the mesh holds too little of is a front of it)
    extra = more_walls(c, n, area, seg.floor_z) if more_walls is not None else []
    behind = _behind(found, c, n, cfg.walls.behind, extra)
    hung = np.zeros(t, bool)  # surfaces hanging before a wall: in no object
    hangers: list[tuple[np.ndarray, np.ndarray, float]] = []  # see _by_hangers
    for (plane, inl), (gap, facing) in zip(found, behind, strict=True):
        if gap == 0:
            _accept(seg, plane, inl, WALL_NAME, WALL, c, area)
            continue
        # in front of a wall: furniture standing on the floor is left to the object
        # clusters; what hangs clear of it (blinds, a curtain, a board) stays unknown and
        # the plan shows the floor the views saw under it
        seg.rejected.append({**_describe(plane, inl, "vertical", c, area), "front": True})
        log.debug("semantics: in front of a wall %s", seg.rejected[-1])
        if np.percentile(c[inl, 2], SPAN_PCT[0]) - seg.floor_z > HANGS:
            hung[inl] = True
            along = c[inl] @ _axes(facing)
            hangers.append((facing, _stretches(along, area[inl], cfg.walls.hanger_slab), gap))
    for w in extra:
        if not any(_same_wall(w, p) for p in seg.planes if p["kind"] == WALL_NAME):
            seg.planes.append(w)
            log.debug("semantics: wall from points %s", w)
    _absorb(seg, c, n, cfg)
    by = _by_hangers(c, hangers, cfg.walls.hanger_slab) & (seg.cls == UNKNOWN) & ~hung
    seg.hanger_triangles = int(by.sum())
    # one hanging within hanger_slab of the wall behind it (blinds, a curtain over a window)
    # closes that wall: nothing stands in the gap, and the plan draws the wall to its face
    close = [h for h in hangers if h[2] <= cfg.walls.hanger_slab]
    seg.cls[(hung | by) & _by_hangers(c, close, cfg.walls.hanger_slab)] = WALL
    objects(seg, c, n, area, ok & ~hung & ~by, cfg)
    return seg


def _planes(
    c: np.ndarray,
    n: np.ndarray,
    area: np.ndarray,
    pool: np.ndarray,
    cfg: SemanticsConfig,
    rng: np.random.Generator,
    horizontal: bool,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (plane [4] = unit normal and d, inlier indices) while the pool holds a plane.

    Each plane is fitted by RANSAC on a sample of the pool, refined by least squares on its
    inliers (distance < plane_dist and normal within max_tilt_deg of the plane's); its
    inliers leave the pool. Planes whose orientation is not the one asked are skipped.
    """
    pool = pool.copy()
    cos_t = np.cos(np.radians(cfg.planes.max_tilt_deg))
    min_area = cfg.planes.min_area if horizontal else cfg.walls.min_area
    for _ in range(cfg.planes.max_planes):
        idx = np.flatnonzero(pool)
        if len(idx) < 3 or area[idx].sum() < min_area:
            return
        sample = (
            idx
            if len(idx) <= cfg.planes.ransac_points
            else rng.choice(idx, cfg.planes.ransac_points, False)
        )
        sample = np.sort(sample)
        plane, raw = plane_ransac(c[sample], cfg.planes.plane_dist, cfg.planes.ransac_iters, rng)
        if not raw.size:  # the sample spans no plane (all on a line)
            pool[sample] = False
            continue
        inl = _inliers(plane, c, n, idx, cfg.planes.plane_dist, cos_t)
        if len(inl) >= 3:
            plane = _refit(c[inl])
            inl = _inliers(plane, c, n, idx, cfg.planes.plane_dist, cos_t)
        up = abs(plane[2])
        kind_ok = (up > cos_t) if horizontal else (up < np.sin(np.radians(cfg.planes.max_tilt_deg)))
        if len(inl) < 3 or not kind_ok:
            # RANSAC's plane cuts across surfaces of other orientations (clutter): drop its
            # points from the pool so the next fit looks elsewhere
            pool[sample[np.asarray(raw, np.int64)]] = False
            continue
        pool[inl] = False
        yield plane, inl


def _inliers(
    plane: np.ndarray, c: np.ndarray, n: np.ndarray, idx: np.ndarray, dist: float, cos_t: float
) -> np.ndarray:
    """Indices of idx within `dist` of the plane whose normal is within the tilt of its."""
    near = np.abs(c[idx] @ plane[:3] + plane[3]) < dist
    along = np.abs(n[idx] @ plane[:3]) > cos_t
    return idx[near & along]


def _refit(p: np.ndarray) -> np.ndarray:
    """Least-squares plane [4] (unit normal, d) through points [N, 3]."""
    mid = p.mean(axis=0)
    normal = np.linalg.svd(p - mid, full_matrices=False)[2][-1]
    return np.append(normal, -normal @ mid)


def _axes(plane: np.ndarray) -> np.ndarray:
    """Unit horizontal direction [3] along a vertical plane."""
    u = np.cross([0.0, 0.0, 1.0], plane[:3])
    return u / max(np.linalg.norm(u), 1e-12)


def _is_wall(
    plane: np.ndarray, c: np.ndarray, area: np.ndarray, cfg: SemanticsConfig, up: np.ndarray
) -> bool:
    s = c @ _axes(plane)  # [N] position along the plane
    lo, hi = np.percentile(np.stack([s, c[:, 2]], axis=1), SPAN_PCT, axis=0)  # [2] each
    length, height = hi - lo
    lean = np.degrees(np.arcsin(min(1.0, abs(float(plane[:3] @ up)))))
    return bool(
        height >= cfg.walls.min_height
        and length >= cfg.walls.min_length
        and area.sum() >= cfg.walls.min_area
        and lean <= cfg.walls.max_lean_deg
    )


def _behind(
    found: list[tuple[np.ndarray, np.ndarray]],
    c: np.ndarray,
    n: np.ndarray,
    behind: float,
    walls: Sequence[dict] = (),
) -> list[tuple[float, np.ndarray]]:
    """For each wall plane (plane [4], inlier indices): how far behind it (metres, away from
    the room, the side its triangles do not face) the nearest other wall plane facing the
    same way lies, between 2 cm and `behind`, along at least half its length (5-95 % of its
    inliers): 0 when none does (the plane is the outermost surface there, a wall), and the
    plane facing the room [4]. Blinds before a window wall, cubicle panels or a row of tall
    cabinets before the wall they stand against are no wall. behind 0: all are.

    walls: walls from the views' points (pointwalls.py, innerwalls.py: normal facing the
    room, box along it) count as planes behind too, from beyond their own `dist` (nearer,
    the plane is that wall's own surface): photos leave a plain wall too few triangles for
    a plane of its own, and a board on a stand 0.25 m before it was taken for the wall."""
    facing = []  # [unit normal facing the room, d]
    for plane, inl in found:
        sign = 1.0 if (n[inl] @ plane[:3]).sum() >= 0 else -1.0
        facing.append(sign * plane)
    if behind <= 0 or len(found) + len(walls) < 2:
        return [(0.0, f) for f in facing]
    out = []
    for i, (_, inl) in enumerate(found):
        u = _axes(facing[i])
        lo, hi = np.percentile(c[inl] @ u, SPAN_PCT)
        gaps = []  # metres to each plane behind it
        for w in walls:
            nw = np.asarray(w["normal"], np.float64)
            if facing[i][:3] @ nw < PARALLEL_COS:
                continue
            off = float(np.median(c[inl] @ nw + w["d"]))  # > 0: the plane before the wall
            a, b = np.percentile(c[inl] @ _axes(nw), SPAN_PCT)  # the plane along the wall's axis
            if max(w.get("dist", 0.0), 0.02) < off <= behind and (
                min(b, w["box"][2]) - max(a, w["box"][0]) >= 0.5 * (b - a)
            ):
                gaps.append(off)
        for j, (_, other) in enumerate(found):
            if j == i or facing[i][:3] @ facing[j][:3] < PARALLEL_COS:
                continue
            off = float(np.median(c[other] @ facing[i][:3] + facing[i][3]))  # < 0: behind
            a, b = np.percentile(c[other] @ u, SPAN_PCT)
            if -behind <= off <= -0.02 and min(hi, b) - max(lo, a) >= 0.5 * (hi - lo):
                gaps.append(-off)
        out.append((min(gaps, default=0.0), facing[i]))
    return out


def _accept(
    seg: Segmentation,
    plane: np.ndarray,
    inl: np.ndarray,
    kind: str,
    cls: int,
    c: np.ndarray,
    area: np.ndarray,
) -> None:
    seg.cls[inl] = cls
    seg.planes.append(_describe(plane, inl, kind, c, area))
    log.debug("semantics: %s plane %s", kind, seg.planes[-1])


def _describe(plane: np.ndarray, inl: np.ndarray, kind: str, c: np.ndarray, area: np.ndarray
              ) -> dict:  # fmt: skip
    """A plane for semantics.json and for the seams: normal, d, area and its box, which is
    [lo0, lo1, hi0, hi1] in xy for a horizontal plane, in (s along it, z) for a vertical one."""
    p = c[inl]
    q = p[:, :2] if kind in (FLOOR_NAME, CEILING_NAME) else np.stack([p @ _axes(plane), p[:, 2]], 1)
    return {
        "kind": kind,
        "normal": [round(float(x), 4) for x in plane[:3]],
        "d": round(float(plane[3]), 4),
        "area_m2": round(float(area[inl].sum()), 3),
        "triangles": len(inl),
        "box": [*q.min(axis=0).round(4).tolist(), *q.max(axis=0).round(4).tolist()],
        "span": np.ptp(np.percentile(q, SPAN_PCT, axis=0), axis=0).round(3).tolist(),
    }


def _same_wall(a: dict, b: dict) -> bool:
    """Whether two wall planes are parallel (within 15 degrees), lie within the first's
    dist of each other (a fitted plane's normal may face either way) and overlap along it
    (the stretches of one plane either side of a doorway are two walls)."""
    na, nb = np.asarray(a["normal"]), np.asarray(b["normal"])
    sign = 1.0 if na @ nb >= 0 else -1.0
    if sign * (na @ nb) < PARALLEL_COS:
        return False
    lo, hi = sorted([sign * b["box"][0], sign * b["box"][2]])  # b's box on a's axis
    overlap = min(a["box"][2], hi) - max(a["box"][0], lo)
    return abs(a["d"] - sign * b["d"]) < a.get("dist", 0.0) and overlap > 0


def _absorb(seg: Segmentation, c: np.ndarray, n: np.ndarray, cfg: SemanticsConfig) -> None:
    """Unlabelled triangles near an accepted plane (its "dist", else plane_dist), inside its
    box, join it (any normal), except triangles facing up near a wall: a wall has no face
    that looks up, and its seam with the floor lies within the floor's reach (the floor
    comes first); they are the top of what stands against it (a sofa's back, a counter),
    which painted a strip of wall over the furniture on the plan."""
    ids = {FLOOR_NAME: FLOOR, WALL_NAME: WALL, CEILING_NAME: CEILING}
    up = n[:, 2] > np.cos(np.radians(cfg.planes.max_tilt_deg))  # [T]
    for pl in seg.planes:
        free = np.flatnonzero((seg.cls == UNKNOWN) & ~(up & (pl["kind"] == WALL_NAME)))
        p = c[free]
        dist = pl.get("dist", cfg.planes.plane_dist)
        near = np.abs(p @ np.asarray(pl["normal"]) + pl["d"]) < dist
        seg.cls[free[near & in_extent(pl, p, cfg.planes.plane_dist)]] = ids[pl["kind"]]


def in_extent(plane: dict, p: np.ndarray, pad: float) -> np.ndarray:
    """bool [...]: whether points p [..., 3] lie inside an accepted plane's box (`_describe`)
    grown by `pad` metres: in xy for a floor or ceiling, in (s along it, z) for a wall."""
    if plane["kind"] in (FLOOR_NAME, CEILING_NAME):
        q = p[..., :2]
    else:
        along = _axes(np.append(np.asarray(plane["normal"], np.float64), plane["d"]))
        q = np.stack([p @ along, p[..., 2]], axis=-1)
    lo, hi = np.asarray(plane["box"][:2]), np.asarray(plane["box"][2:])
    return np.asarray(((q >= lo - pad) & (q <= hi + pad)).all(axis=-1))


def _stretches(along: np.ndarray, area: np.ndarray, slab: float) -> np.ndarray:
    """[K, 2] the stretches (lo, hi metres) along a hanging surface that it covers: bins
    `slab` metres wide holding at least slab² m² of its inliers (positions along [N], areas
    [N]), consecutive bins joined. Inliers of the plane that lie apart from the surface (a
    leaf of a plant beside it, a screen's edge in the same plane 0.5 m away) add no stretch:
    the surface's extent is where it is, not the span of everything co-planar."""
    if slab <= 0 or len(along) == 0:
        return np.zeros((0, 2))
    k = np.floor(along / slab).astype(np.int64)
    k0 = int(k.min())
    full = np.bincount(k - k0, weights=area) >= slab**2  # [B]
    edges = np.diff(np.concatenate([[0], full.astype(np.int8), [0]]))
    lo, hi = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return np.stack([lo + k0, hi + k0], axis=1) * slab


def _by_hangers(
    c: np.ndarray, hangers: list[tuple[np.ndarray, np.ndarray, float]], slab: float
) -> np.ndarray:
    """bool [T]: triangle centres c [T, 3] by a surface hanging before a wall (its plane
    facing the room [4], its stretches along it [K, 2], the gap to the wall behind it in
    metres), inside one of its stretches grown by `slab`, at any height, from `slab` metres
    before it to the wall behind it: its frame, legs and stand (a whiteboard's, a screen's)
    and what it hides from the room, which hang with it (unknown) and would otherwise paint
    its whole depth object on the plan. slab 0: none."""
    out = np.zeros(len(c), bool)
    if slab <= 0:
        return out
    for plane, runs, gap in hangers:
        s = c @ _axes(plane)
        dist = c @ plane[:3] + plane[3]  # > 0: before it, in the room
        near = (dist <= slab) & (dist >= -gap - slab)
        for lo, hi in runs:
            out |= near & (s >= lo - slab) & (s <= hi + slab)
    return out

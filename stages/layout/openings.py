"""Openings read off the mesh along each wall: rays from just inside the room out through the
wall's face at a few heights (Open3D's ray casting). Where no ray meets the wall along a
stretch at least `min_opening` wide, it is a door (up to `door_max` wide) or a passage when a
ray cast down in the wall's middle meets the floor there (the floor runs through), and a
window where the lowest ray meets the wall and the others do not, with the wall met on both
sides of it at their heights."""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numpy as np
import open3d as o3d

from stages.layout.config import LayoutConfig

HEIGHTS = (0.3, 1.0, 1.5)  # metres: the horizontal rays (below a window sill, at and above)
INSET = 0.05  # metres: rays start this far inside the room
BIN = 0.02  # metres: ray spacing along a wall
BEYOND = (0.04, 0.08, 0.12)  # metres beyond the face: where the floor is looked for
JAMB_HEIGHTS = (0.2, 0.5, 0.8, 1.1, 1.4, 1.7)  # metres: where a door's edges are read
STEP = 0.005  # metres: ray spacing there
FACE = 0.01  # metres: a surface this close to the face's depth is the face
MAX_BEVEL = 0.12  # metres: how far a door's edge moves from where the gap closes
AROUND = 16  # horizontal rays cast round a point to tell whether the walls enclose it
ENCLOSED = 0.75  # share of them that must meet a surface from its front
AROUND_BATCH = 4096  # points whose AROUND rays are cast at once (memory, not results)
SPECK = 2  # bins: a stretch this short met at one height only, open on both sides, is a speck


def _tensor(a: np.ndarray) -> o3d.core.Tensor:
    return o3d.core.Tensor.from_numpy(np.ascontiguousarray(a))


def scene_of(verts: np.ndarray, tris: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        _tensor(verts.astype(np.float32, copy=False)), _tensor(tris.astype(np.uint32, copy=False))
    )
    return scene


def _runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index pairs (end exclusive) of the True runs of a 1-D mask."""
    d = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0], strict=True))


def mesh_openings(
    walls: list[dict],
    verts: np.ndarray | None,
    tris: np.ndarray | None,
    cfg: LayoutConfig,
    scene: o3d.t.geometry.RaycastingScene | None = None,
) -> list[dict]:
    """plan.json openings of `walls` (world metres) found in the mesh: `scene`, the caller's
    scene of it (one scene for the stage: each holds its own copy of the mesh and its BVH),
    else one made of `verts` and `tris`."""
    if scene is None:
        assert verts is not None and tris is not None  # callers give a scene or the mesh
        scene = scene_of(verts, tris)
    out = []
    for wi, w in enumerate(walls):
        a, b, t = np.asarray(w["start"]), np.asarray(w["end"]), float(w["thickness"])
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        n = np.array([d[1], -d[0]])  # outwards
        s = np.arange(BIN / 2, length, BIN)
        wall = met(scene, w, s)  # [H, S]
        # the floor beyond the face: rays cast down at a few depths into the wall line (a
        # fused threshold has holes: measured half of it on a 30-view room); a wall that the
        # views did not see, behind furniture, has none
        down = np.concatenate(
            [
                np.concatenate(
                    [a + s[:, None] * d + n * off, np.full((len(s), 1), 0.5)]
                    + [np.tile([0, 0, -1.0], (len(s), 1))],
                    1,
                )
                for off in BEYOND
            ]
        ).astype(np.float32)
        floor_t = scene.cast_rays(_tensor(down))["t_hit"].numpy().reshape(len(BEYOND), -1)
        floor = (np.abs(floor_t - 0.5) < 0.08).any(0)
        for kind_of, open_ in (
            ("door", ~_specks_out(wall)),
            ("window", wall[0] & ~wall[1:].any(0)),
        ):
            for i, j in _runs(np.asarray(open_)):
                width = (j - i) * BIN
                if width < cfg.min_opening:
                    continue
                kind, s0, s1 = kind_of, i * BIN, j * BIN
                if kind == "window" and not all(w[:i].any() and w[j:].any() for w in wall[1:]):
                    continue  # no wall seen beside it at a height it is open at: a wall the
                    # views saw only low down (far off, at a slant), not a hole in one
                if kind == "door":
                    if floor[i:j].mean() < 0.4:
                        continue
                    s0, s1 = _jambs(scene, (a, d, n), (s0, s1), t)
                    width = s1 - s0
                    kind = "door" if width <= cfg.door_max else "passage"
                p, q = a + s0 * d, a + s1 * d
                out.append(
                    {
                        "kind": kind,
                        "wall": wi,
                        "start": np.round(p, 4).tolist(),
                        "end": np.round(q, 4).tolist(),
                        "width": round(width, 4),
                    }
                )
    return out


def met(scene: o3d.t.geometry.RaycastingScene, wall: dict, s: np.ndarray) -> np.ndarray:
    """Whether the rays cast out through the face of `wall` (a plan.json wall) at each of `s`
    (metres along it) and HEIGHTS meet a surface before its back, 5 cm of slack [H, S]."""
    a, b = np.asarray(wall["start"], np.float64), np.asarray(wall["end"], np.float64)
    d = (b - a) / max(float(np.linalg.norm(b - a)), 1e-12)
    n = np.array([d[1], -d[0]])  # outwards
    return _depth(scene, (a, d, n), s, HEIGHTS) <= float(wall["thickness"]) + 0.05


def held(scene: o3d.t.geometry.RaycastingScene, walls: list[dict]) -> np.ndarray:
    """The share of each wall's inner 80 % where a ray met it at some height [W] (`met`, every
    BIN; 0 for a wall under 4 BIN long). A wall the plan holds from the views' readings alone
    (a partition that stereo fused neither face of) the mesh does not: no ray meets it."""
    out = np.zeros(len(walls))
    for wi, w in enumerate(walls):
        length = float(np.linalg.norm(np.subtract(w["end"], w["start"])))
        if length >= 4 * BIN:
            out[wi] = float(met(scene, w, np.arange(0.1 * length, 0.9 * length, BIN)).any(0).mean())
    return out


def _specks_out(wall: np.ndarray) -> np.ndarray:
    """Where a ray met the wall at some height [S] from the hits per height [H, S], less the
    specks: a stretch of at most SPECK bins met at one height only, between two stretches
    that no ray met. A wall, a jamb, furniture in a doorway stand over heights; a fleck of
    stereo's noise floating in a doorway meets one ray (the 3-room home from photos: one
    bin at 1.0 m cut a 1.7 m passage to 1.43 m)."""
    hit = cast(np.ndarray, wall.any(0))  # [S]: along an axis, an array (numpy types a bool too)
    for i, j in _runs(hit):
        if 0 < i and j < len(hit) and j - i <= SPECK and wall[:, i:j].sum(0).max() <= 1:
            hit[i:j] = False
    return hit


def _depth(
    scene: o3d.t.geometry.RaycastingScene, face: tuple, s: np.ndarray, heights: tuple
) -> np.ndarray:
    """Depth behind the face (a, d, n: start, direction, outward normal) of the first surface
    met by rays cast out from INSET inside the room at each of `s` (metres along the face) and
    `heights` [H, S] (inf: nothing met)."""
    a, d, n = face
    xy = a + s[:, None] * d - n * INSET  # [S, 2]
    rays = np.concatenate(
        [
            np.concatenate([xy, np.full((len(s), 1), h), np.tile([*n, 0.0], (len(s), 1))], 1)
            for h in heights
        ]
    ).astype(np.float32)
    return scene.cast_rays(_tensor(rays))["t_hit"].numpy().reshape(len(heights), -1) - INSET


def _jambs(
    scene: o3d.t.geometry.RaycastingScene, face: tuple, span: tuple, t: float
) -> tuple[float, float]:
    """A door's two edges (metres along the face) read at STEP where the face itself starts,
    not where some surface closes the wall line: a fused jamb leans into the gap (the TSDF
    rounds a convex corner seen at a slant outwards: measured up to 7 cm along the wall and
    4-7 cm deep behind the face on the procedural rooms). From just inside the gap outwards,
    at each of JAMB_HEIGHTS, the edge is the first ray that meets a surface within FACE of
    the face's own depth (its median 15-30 cm along past the edge); the median over the
    heights. An edge moves by at most MAX_BEVEL."""
    out = []
    for edge, sign in ((span[0], -1.0), (span[1], 1.0)):
        s = edge + sign * np.arange(-BIN, MAX_BEVEL + STEP / 2, STEP)
        depth = _depth(scene, face, s, JAMB_HEIGHTS)  # [H, S]
        ref = _depth(scene, face, edge + sign * np.arange(0.15, 0.3, BIN), JAMB_HEIGHTS)
        found = []
        for row, r in zip(depth, ref, strict=True):
            r = r[r <= t + 0.05]
            if len(r) < 3:
                continue
            at = np.nonzero(row <= np.median(r) + FACE)[0]
            if len(at) and at[0] > 0:
                found.append(s[at[0]] - sign * STEP / 2)
        out.append(float(np.median(found)) if found else edge)
    return out[0], out[1]


def _around(
    scene: o3d.t.geometry.RaycastingScene, xy: np.ndarray, z: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """AROUND horizontal rays at height z cast round each point [N, 2]: the depth of the
    first surface met [N, AROUND] (inf: none), whether it was met from its front [N,
    AROUND], and the rays' directions [AROUND, 3]."""
    a = np.arange(AROUND) * 2 * np.pi / AROUND
    dirs = np.stack([np.cos(a), np.sin(a), np.zeros(AROUND)], 1)
    t = np.empty((len(xy), AROUND), np.float32)
    facing = np.empty((len(xy), AROUND), bool)
    # a batch of points at a time: a home's unseen floor is 10^5 points, 16 rays each, and a
    # cast's rays and hits (normals, ids, uvs) are ~100 bytes a ray
    for i in range(0, len(xy), AROUND_BATCH):
        p = xy[i : i + AROUND_BATCH]
        o = np.concatenate([p, np.full((len(p), 1), z)], 1)
        rays = np.concatenate([np.repeat(o, AROUND, 0), np.tile(dirs, (len(p), 1))], 1)
        hit = scene.cast_rays(_tensor(rays.astype(np.float32)))
        t[i : i + len(p)] = hit["t_hit"].numpy().reshape(-1, AROUND)
        normals = hit["primitive_normals"].numpy().reshape(-1, AROUND, 3)
        facing[i : i + len(p)] = (normals * dirs).sum(-1) < 0
        del hit, rays, normals
    return t, facing, dirs


def enclosed(scene: o3d.t.geometry.RaycastingScene, xy: np.ndarray, z: float = 1.0) -> np.ndarray:
    """Whether the mesh's walls enclose each floor point [N, 2] -> [N] bool: at least ENCLOSED
    of AROUND horizontal rays at height z meet a surface from its front (a fused surface faces
    the views that saw it, the room's inside). From outside the walls the rays meet their
    backs or nothing; through a doorway a few of them leave the room."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    t, facing, _ = _around(scene, xy, z)
    return _enclosing(t, facing)


def _enclosing(t: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """`enclosed` from the rays cast round each point (`_around`'s depths and facings)."""
    return (np.isfinite(t) & facing).mean(1) >= ENCLOSED


def outside_walls(
    scene: o3d.t.geometry.RaycastingScene,
    xy: np.ndarray,
    is_wall: Callable[[np.ndarray], np.ndarray],
    z: float = 1.0,
) -> np.ndarray:
    """Whether each point [N, 2] lies outside the walls -> [N] bool: not `enclosed`, and at
    least one of the same AROUND rays meets a surface from its back where the plan has a
    wall (`is_wall`: world xy [M, 2] -> [M] bool). A point outside the walls sees their
    backs; one behind furniture that stands against an unseen stretch of wall sees the
    furniture's back and nothing, not a wall. One cast of the rays serves both readings."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    t, facing, dirs = _around(scene, xy, z)
    back = np.isfinite(t) & ~facing
    at = xy[:, None, :] + np.where(back, t, 0.0)[..., None] * dirs[None, :, :2]  # [N, A, 2]
    wall = is_wall(at.reshape(-1, 2)).reshape(back.shape)
    return ~_enclosing(t, facing) & (back & wall).any(1)


CEILING_SHARE = 0.25  # least share of the floor points under a ceiling the mesh holds (sensor
#                      depth of the 3-room home fused it over 46-49 % of its floor cells)
CEILING_LEVEL = 0.5  # least share of the hits within CEILING_BAND of their median
CEILING_BAND = 0.1  # metres


def ceiling(scene: o3d.t.geometry.RaycastingScene, floor_xy: np.ndarray) -> float | None:
    """Height of the ceiling's underside: the median hit of rays cast up from floor points
    [N, 2], None when there is no ceiling. A ceiling is a level surface over part of the
    floor: at least CEILING_SHARE of the rays meet something, CEILING_LEVEL of those within
    CEILING_BAND of their median. The views fuse a ceiling in patches (the cameras look
    level): with half of the rays required, the 3-room home's sensor mesh, whose ceiling
    covers 46-49 % of the floor, had one or none by the draw of the 50 floor points sampled
    (23 of 51 rays met it with the plan of wall_face, 28 without), and without one its
    1.6 m cabinet against the living room's wall stayed a notch of four corners
    (furniture.py). No ceiling: the rays meet nothing but the underside of some furniture,
    at its heights (the 7-Scenes kitchen: 2-8 % of the floor points)."""
    if len(floor_xy) == 0:
        return None
    rays = np.concatenate(
        [floor_xy, np.full((len(floor_xy), 1), 0.05), np.tile([0, 0, 1.0], (len(floor_xy), 1))], 1
    )
    t = scene.cast_rays(_tensor(rays.astype(np.float32)))["t_hit"].numpy()
    hit = t[np.isfinite(t)]
    if len(hit) < max(3, CEILING_SHARE * len(t)):
        return None
    mid = float(np.median(hit))
    if (np.abs(hit - mid) <= CEILING_BAND).mean() < CEILING_LEVEL:
        return None
    return 0.05 + mid


def heights(
    scene: o3d.t.geometry.RaycastingScene, xys: list[np.ndarray], ceil: float | None
) -> list[float | None]:
    """Top of the surface over each set of floor points [N, 2]: the 98th percentile of the
    first hits of rays cast down from just under the ceiling (from 5 m without one)."""
    z0 = ceil - 0.02 if ceil is not None else 5.0
    out: list[float | None] = []
    for xy in xys:
        rays = np.concatenate(
            [xy, np.full((len(xy), 1), z0), np.tile([0, 0, -1.0], (len(xy), 1))], 1
        )
        t = scene.cast_rays(_tensor(rays.astype(np.float32)))["t_hit"].numpy()
        t = t[np.isfinite(t)]
        out.append(round(float(np.percentile(z0 - t, 98)), 4) if len(t) else None)
    return out


FACE_HEIGHTS = (0.3, 0.6, 1.0, 1.3, 1.6)  # metres: where a wall's face is read in the mesh
FACE_REACH = 0.12  # metres: a face read this far either side of the traced one moves it
FACE_SUPPORT = 0.3  # share of the rays that must meet the face within FACE_REACH


def face_offsets(scene: o3d.t.geometry.RaycastingScene, walls: list[dict]) -> np.ndarray:
    """How far each wall's face lies in the mesh beyond the traced one [W] (metres, along
    its outward normal; 0 where too few rays meet a surface within FACE_REACH): the median
    depth of the first surfaces met from inside by rays out through its inner 80 % at
    FACE_HEIGHTS, every BIN. The traced outline follows the plan's 2 cm cells and the
    field's boundary; the mesh's face is measured."""
    out = np.zeros(len(walls))
    for wi, w in enumerate(walls):
        a, b = np.asarray(w["start"], np.float64), np.asarray(w["end"], np.float64)
        length = float(np.linalg.norm(b - a))
        if length < 4 * BIN:
            continue
        d = (b - a) / length
        n = np.array([d[1], -d[0]])
        s = np.arange(0.1 * length, 0.9 * length, BIN)
        back = FACE_REACH + INSET  # rays start FACE_REACH inside the face
        xy = a + s[:, None] * d - n * back
        rays = np.concatenate(
            [
                np.concatenate([xy, np.full((len(s), 1), h), np.tile([*n, 0.0], (len(s), 1))], 1)
                for h in FACE_HEIGHTS
            ]
        ).astype(np.float32)
        hit = scene.cast_rays(_tensor(rays))
        t = hit["t_hit"].numpy() - back
        facing = (hit["primitive_normals"].numpy()[:, :2] * n).sum(1) < 0
        ok = np.isfinite(t) & (np.abs(t) <= FACE_REACH) & facing
        if ok.mean() >= FACE_SUPPORT:
            out[wi] = float(np.median(t[ok]))
    return out

"""Layout stage, `walls`: the architectural plan read off the blueprint (plan.py), written as
plan.json, plan.svg and plan.dxf (draw.py)."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy import ndimage as ndi
from shapely.errors import GEOSException
from shapely.geometry import Polygon

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import FLOOR_NAME, WALL_NAME, ids_named
from stages.common.heap import heap_returned
from stages.common.io import write_json
from stages.layout.config import LayoutConfig, LayoutInputs, LayoutOutputs
from stages.layout.draw import write_dxf, write_svg
from stages.layout.extract import Line, intersect
from stages.layout.furniture import filled_notches
from stages.layout.meshfile import read_mesh
from stages.layout.openings import (
    FACE_HEIGHTS,
    FACE_SUPPORT,
    ceiling,
    face_offsets,
    heights,
    held,
    mesh_openings,
    outside_walls,
    scene_of,
)
from stages.layout.plan import architecture, in_rooms, objects
from stages.layout.plangaps import HELD, face_line, plan_openings
from stages.layout.rooms import join_rooms, split_seen

log = logging.getLogger(__name__)

FLOOR_BAND = 0.15  # metres: floor cells need a surface of the mesh within this of z = 0
WALL_NEAR = 3  # cells: a surface met this close to the plan's wall cells is a wall's


def build_plan(bp: Blueprint, cfg: LayoutConfig, mesh: Path | None = None) -> dict:
    """plan.json's content: rooms, walls, openings and objects of the blueprint. With a mesh:
    object heights, and the openings read off the mesh (openings.py) rather than the plan,
    but for the walls the mesh does not hold (plangaps.py)."""
    scene = None if mesh is None else _scene(mesh)
    if scene is not None:
        plan = architecture(seen_floor(bp, scene), cfg)
        plan = moved_to_faces(plan, face_offsets(scene, plan["walls"]), cfg, bp.grid.cell)
        apart = kept_apart(plan["walls"], bp, cfg)
        if apart.any():
            plan = moved_to_faces(plan, apart, cfg, bp.grid.cell)
        fid = ids_named(bp.classes, FLOOR_NAME)
        floor = bp.grid.centers()[np.isin(bp.labels, fid)]
        ceil = ceiling(scene, floor[:: max(1, len(floor) // 50)])
        plan = filled_notches(plan, scene, ceil)
        # the mesh's openings in the walls it holds; the plan's in those it does not
        share = held(scene, plan["walls"])
        found = mesh_openings(plan["walls"], None, None, cfg, scene)
        found = [o for o in found if share[o["wall"]] >= HELD]
        found += plan_openings(plan["walls"], share, bp, cfg)
        plan["openings"] = _in_walls(_distinct(found), plan["walls"])
        plan["walls"] = seen_thickness(scene, plan["walls"], cfg)
        plan["objects"] = objects(
            bp, cfg, lambda xys: object_heights(scene, xys, ceil), lambda xy: solid(scene, xy, ceil)
        )
        plan["ceiling_m"] = None if ceil is None else round(ceil, 4)
    else:
        plan = architecture(bp, cfg)
        plan["openings"] = _distinct(plan["openings"])
        plan["objects"] = objects(bp, cfg)
    # the drawing is of the rooms: what lies outside them stays in the BluNF plan only
    plan["objects"], plan["objects_outside"] = in_rooms(
        plan["objects"], plan["rooms"], 2 * bp.grid.cell
    )
    return join_rooms(split_seen(plan))


def _scene(mesh: Path) -> o3d.t.geometry.RaycastingScene | None:
    """One ray-casting scene of the mesh for the whole stage (None: a mesh without faces).
    The mesh is read as float32 vertices and uint32 triangles only, after the heap's free
    pages went back to the system: the scene is not built from them (meshfile.py)."""
    heap_returned()
    verts, tris = read_mesh(mesh)
    return scene_of(verts, tris) if len(tris) else None


def object_heights(
    scene: o3d.t.geometry.RaycastingScene, xys: list[np.ndarray], ceil: float | None
) -> list[tuple[float | None, float | None]]:
    """(height, top) over each object's floor points [N, 2]: its highest point (the 98th
    percentile of the first surfaces met by rays cast down from under the ceiling:
    openings.heights) and its top, the median of them (the surface things are set on: a
    counter's top under the kettle, a chair's seat inside its back), metres above the floor."""
    z0 = ceil - 0.02 if ceil is not None else 5.0
    out: list[tuple[float | None, float | None]] = []
    for xy, high in zip(xys, heights(scene, xys, ceil), strict=True):
        rays = np.concatenate(
            [xy, np.full((len(xy), 1), z0), np.tile([0, 0, -1.0], (len(xy), 1))], 1
        ).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
        t = t[np.isfinite(t)]
        out.append((high, round(float(np.median(z0 - t)), 4) if len(t) else None))
    return out


SOLID_Z = 0.08  # metres: a surface higher than this over the floor is something standing


def solid(scene: o3d.t.geometry.RaycastingScene, xy: np.ndarray, ceil: float | None
          ) -> np.ndarray:  # fmt: skip
    """bool [N]: whether the first surface met by a ray cast down at each point [N, 2] from
    under the ceiling (from 5 m without one) lies higher than SOLID_Z (not the floor, not a
    hole in the surface)."""
    z0 = ceil - 0.02 if ceil is not None else 5.0
    rays = np.concatenate([xy, np.full((len(xy), 1), z0), np.tile([0, 0, -1.0], (len(xy), 1))], 1)
    t = scene.cast_rays(o3d.core.Tensor.from_numpy(rays.astype(np.float32)))["t_hit"].numpy()
    return np.isfinite(t) & (z0 - t > SOLID_Z)


def seen_floor(bp: Blueprint, scene: o3d.t.geometry.RaycastingScene) -> Blueprint:
    """The blueprint with its floor cells that have no surface of the mesh at floor level
    (a ray cast down from FLOOR_BAND meets nothing within 2 x FLOOR_BAND) made unknown when
    they lie outside the mesh's walls: not enclosed by them (openings.enclosed) and with a
    wall's back in view (openings.outside_walls: a ray meets a surface from behind within
    WALL_NEAR cells of the plan's wall cells). The plan's field fills ground no view saw
    outside an L's walls and behind a doorway, which is no room. Unseen floor the walls
    enclose stays floor: the shadow of a bed or a chair against a wall (measured up to
    1.5 x 1 m in a rectangular room, which bent its outline round the shadow: corner F1 0.35
    against 1.0). So does unseen floor that sees no wall's back: behind and beside a tall
    cabinet before a stretch of wall stereo did not fuse, whose rays meet the cabinet's back
    or nothing (photos alone, rectangle seed 5: the outline stepped 0.56 m inside the north
    wall round it, corner F1 0.6 against 1.0)."""
    fid = ids_named(bp.classes, FLOOR_NAME)
    floor = np.isin(bp.labels, fid)
    if not floor.any():
        return bp
    xy = bp.grid.centers()[floor]  # [N, 2]
    rays = np.concatenate(
        [xy, np.full((len(xy), 1), FLOOR_BAND), np.tile([0.0, 0.0, -1.0], (len(xy), 1))], 1
    )
    t = scene.cast_rays(o3d.core.Tensor.from_numpy(rays.astype(np.float32)))["t_hit"].numpy()
    labels = bp.labels.copy()
    rows, cols = np.nonzero(floor)
    gone = np.nonzero(~(t <= 2 * FLOOR_BAND))[0]
    wid = ids_named(bp.classes, WALL_NAME)
    near = ndi.binary_dilation(np.isin(bp.labels, wid), iterations=WALL_NEAR)

    def is_wall(pts: np.ndarray) -> np.ndarray:
        row, col, inside = bp.grid.cell_of(pts)
        return near[row, col] & inside

    gone = gone[outside_walls(scene, xy[gone], is_wall)]
    labels[rows[gone], cols[gone]] = UNKNOWN
    return replace(bp, labels=labels)


def moved_to_faces(plan: dict, offsets: np.ndarray, cfg: LayoutConfig, cell: float) -> dict:
    """The plan with each wall's face moved out by its offset [W] (metres along its outward
    normal; openings.face_offsets) and its thickness less by as much (`default_thickness`
    where less than a plan `cell` of the wall's band is left behind it); each room's corners
    where its moved faces meet (kept where two neighbouring faces are near parallel), its
    walls' ends and lengths and its area with them. A room whose moved outline would cross
    itself keeps its traced one."""
    walls = [dict(w) for w in plan["walls"]]
    rooms = []
    for ri, room in enumerate(plan["rooms"]):
        idx = [i for i, w in enumerate(walls) if w["room"] == ri]
        poly = np.asarray(room["polygon"], np.float64)
        if len(idx) != len(poly):
            rooms.append(room)
            continue
        k = len(poly)
        d = np.roll(poly, -1, 0) - poly
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        n = np.stack([d[:, 1], -d[:, 0]], 1)  # outward of a counter-clockwise outline
        p = poly + offsets[idx][:, None] * n  # a point on each moved face
        faces = [Line(p[i], d[i], 0.0) for i in range(k)]
        new = poly.copy()
        for i in range(k):  # corner i joins face i-1 and face i
            c = intersect(faces[i - 1], faces[i], tol=0.05)
            if c is not None:
                new[i] = c
        moved = Polygon(new)
        if not moved.is_valid or not moved.exterior.is_ccw:
            rooms.append(room)
            continue
        for e, wi in enumerate(idx):
            a, b = new[e], new[(e + 1) % k]
            thick = float(walls[wi]["thickness"]) - float(offsets[wi])
            walls[wi].update(
                start=np.round(a, 4).tolist(),
                end=np.round(b, 4).tolist(),
                length=round(float(np.linalg.norm(b - a)), 4),
                thickness=round(thick if thick >= cell else cfg.default_thickness, 4),
            )
        rooms.append({**room, "polygon": np.round(new, 4).tolist(), "area": round(moved.area, 4)})
    return {**plan, "rooms": rooms, "walls": walls}


BACK_BIN = 0.05  # metres: ray spacing along a wall where its back face is looked for
APART = 0.5  # share of default_thickness under which two rooms' back-to-back faces are one
ALONG = 0.5  # share of the shorter face two back-to-back faces must run side by side


def kept_apart(walls: list[dict], bp: Blueprint, cfg: LayoutConfig) -> np.ndarray:
    """Offsets [W] (metres along each wall's outward normal, moved_to_faces) that give a
    partition its thickness back where two rooms' faces of it met on one line.

    From photos a partition may show in the plan as one band of wall cells whose faces
    neither room's mesh holds (stereo fused neither face), and a room's traced outline may
    take the band in: both rooms' faces then lie on one line, the band's far side, and the
    wall between them is drawn with no thickness, though no wall is that thin. Of two faces
    of different rooms that run back to back (opposite normals, side by side along ALONG of
    the shorter) less than APART x `default_thickness` apart, the one whose room holds the
    band (the larger share of wall cells within `default_thickness` in front of it) goes
    back to `default_thickness` in front of the other. The 3-room home from photos: room 3's
    face at the partition 13 cm past the ground truth's, then 3 cm."""
    out = np.zeros(len(walls))
    faces = [face_line(w) for w in walls]
    wid = ids_named(bp.classes, WALL_NAME)

    def band(i: int) -> float:
        """Share of wall cells within default_thickness in front of face i (its room's side)."""
        a, d, n, length = faces[i]
        t = np.arange(0.1, 0.9, 0.02) * length
        s = (np.arange(5) + 0.5) * cfg.default_thickness / 5
        pts = a + t[:, None, None] * d - s[None, :, None] * n
        lab = bp.sample(pts.reshape(-1, 2))
        return float(np.isin(lab, wid).mean())

    for i in range(len(walls)):
        for j in range(i + 1, len(walls)):
            if walls[j]["room"] == walls[i]["room"]:
                continue
            (a, d, n, la), (b, e, m, lb) = faces[i], faces[j]
            if n @ m > -0.999 or min(la, lb) <= 0:
                continue
            gap = float((b - a) @ n)  # j's face beyond i's, along i's outward normal
            t0, t1 = sorted([float((b - a) @ d), float((b + e * lb - a) @ d)])
            side = min(t1, la) - max(t0, 0.0)
            if abs(gap) >= APART * cfg.default_thickness or side < ALONG * min(la, lb):
                continue
            # the thickness is the same from either face's side
            out[i if band(i) >= band(j) else j] = gap - cfg.default_thickness
    return out


def seen_thickness(
    scene: o3d.t.geometry.RaycastingScene, walls: list[dict], cfg: LayoutConfig
) -> list[dict]:
    """The walls with their thickness read off the mesh: the median distance from the face to
    the wall's back face (a surface facing away from the room, seen from beyond it: the next
    room's side of a partition) where at least FACE_SUPPORT of the rays cast back towards the
    face from `max_thickness` behind it, at FACE_HEIGHTS over its inner 80 %, meet one;
    `default_thickness` elsewhere. A one-sided wall shows no thickness: the plan's band behind
    its face is what the views did not see (the grid's padding, cabinets merged into it:
    the 7-Scenes kitchen's north wall drew 0.40 m), not the wall."""
    out = []
    for w in walls:
        a, b = np.asarray(w["start"], np.float64), np.asarray(w["end"], np.float64)
        length = float(np.linalg.norm(b - a))
        thick = cfg.default_thickness
        if length >= 4 * BACK_BIN:
            d = (b - a) / length
            n = np.array([d[1], -d[0]])  # outwards
            s = np.arange(0.1 * length, 0.9 * length, BACK_BIN)
            back = cfg.max_thickness + 0.02
            xy = a + s[:, None] * d + n * back
            rays = np.concatenate(
                [
                    np.concatenate(
                        [xy, np.full((len(s), 1), h), np.tile([*-n, 0.0], (len(s), 1))], 1
                    )
                    for h in FACE_HEIGHTS
                ]
            ).astype(np.float32)
            hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
            t = back - hit["t_hit"].numpy()  # depth of the hit behind the face
            away = (hit["primitive_normals"].numpy()[:, :2] @ n) > 0.7
            ok = np.isfinite(t) & away & (t > 0.02) & (t <= cfg.max_thickness)
            if ok.mean() >= FACE_SUPPORT:
                thick = float(np.median(t[ok]))
        out.append({**w, "thickness": round(thick, 4)})
    return out


def _distinct(openings: list[dict], tol: float = 0.3) -> list[dict]:
    """One opening where the two faces of a wall between rooms each found it."""
    out: list[dict] = []
    for o in openings:
        c = (np.asarray(o["start"]) + o["end"]) / 2
        if all(np.linalg.norm(c - (np.asarray(k["start"]) + k["end"]) / 2) > tol for k in out):
            out.append(o)
    return out


WHOLE = 0.9  # share of an inferred wall's length an opening spanning it all covers


def _in_walls(openings: list[dict], walls: list[dict]) -> list[dict]:
    """The openings less those that span an inferred wall (`seen` false) along WHOLE of its
    length or more: an open side closed over space no view saw as a surface is all gap, not
    a door or a passage in a wall (the room `continues` beyond it already says so)."""
    out = []
    for o in openings:
        w = walls[o["wall"]] if 0 <= o.get("wall", -1) < len(walls) else None
        if w is not None and not w["seen"] and o["width"] >= WHOLE * float(w["length"]):
            continue
        out.append(o)
    return out


def write_plan(plan: dict, outs: LayoutOutputs, title: str = "") -> None:
    """The plan's three files (export may call this again after an edit)."""
    write_json(outs.plan_json, plan)
    write_svg(plan, outs.plan_svg, title)
    write_dxf(plan, outs.plan_dxf)


def run(cfg: LayoutConfig, inputs: LayoutInputs, out: Path) -> LayoutOutputs:
    """Rooms, walls, openings and object footprints of the blueprint, as vectors in metres."""
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bp = Blueprint.load(inputs.blueprint)
    outs = LayoutOutputs.at(out)
    try:
        plan = build_plan(bp, cfg, inputs.mesh)
        write_plan(plan, outs)
    except GEOSException as e:
        # the architectural drawing is a layer over the plan, not the plan: a geometry the
        # overlay cannot handle leaves it empty, says why, and the run keeps its blueprint
        log.warning("layout: no drawing: %s", e)
        plan = {"rooms": [], "walls": [], "openings": [], "objects": [], "error": str(e)}
        write_plan(plan, outs)
    write_json(out / "layout.json", {"error": plan.get("error"), **_counts(plan)})
    log.info("layout: %s in %.2f s", _counts(plan), time.perf_counter() - t0)
    return outs


def _counts(plan: dict) -> dict:
    return {k: len(plan[k]) for k in ("rooms", "walls", "openings", "objects")}

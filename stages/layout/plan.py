"""The plan as vectors: rooms, walls, openings (extract.py) and object footprints, in metres.

plan.json: {"units": "m", "angle_deg": the room's direction, "rooms": [{name, polygon
(counter-clockwise interior outline), area, continues (an inferred wall closes it: the room
goes on beyond)}], "walls": [{start, end (interior face, room on the left), length,
thickness, room, seen (false: inferred, the outline closes over space no view saw as a wall
surface)}], "openings": [{kind door|passage, wall, start, end, width, rooms ([i, j]: the two
rooms it joins; [i]: room i to the outside)}], "objects": [{instance,
class, name, polygon, center, width, depth, angle_deg, height (its highest point) and top (its
upper surface: a counter's top, a chair's seat), metres above the floor, None without a mesh,
shape rect|polygon}], "objects_outside": how many object footprints lay outside every room
(left out of the drawing; the BluNF plan keeps them)}.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage as ndi
from shapely.geometry import MultiPoint, Polygon
from shapely.geometry.polygon import orient
from skimage.measure import find_contours

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import FLOOR_NAME, STRUCTURE, WALL_NAME
from stages.layout.config import LayoutConfig
from stages.layout.extract import (
    Frame,
    class_id,
    close_lines,
    close_passages,
    dominant_angle,
    frame_of,
    outline,
)
from stages.layout.rooms import cut_openings, disjoint, seen_pieces, split
from stages.layout.unseen import filled_between, notched, recessed

SEEN_NEAR = 0.1  # metres: a face is seen where a seen wall cell lies this close to its band
SEEN_SHARE = 0.5  # a wall is seen (not inferred) when this share of its face is


def _r(x: np.ndarray | float) -> list | float:
    return np.round(np.asarray(x, np.float64), 4).tolist()


def _seen_walls(bp: Blueprint, wid: int) -> Blueprint:
    """A plan of 1 where a wall cell was seen, 0 elsewhere (to be turned into the frame)."""
    assert bp.seen is not None
    return Blueprint(((bp.labels == wid) & (bp.seen > 0)).astype(np.uint8), bp.grid)


def _seen_along(
    fr: Frame, seen_wall: np.ndarray, a: np.ndarray, b: np.ndarray, thickness: float
) -> np.ndarray:
    """bool [T]: at each cell along the face a->b (frame xy), whether a seen wall cell
    (`seen_wall`: or an opening seen through) lies behind it, within its thickness plus
    SEEN_NEAR metres along its outward normal (or SEEN_NEAR in front of it)."""
    cell = fr.grid.cell
    length = float(np.linalg.norm(b - a))
    d = (b - a) / max(length, 1e-9)
    n = np.array([d[1], -d[0]])  # outside a counter-clockwise outline
    ts = np.arange(0.5 * cell, length, cell)
    if len(ts) == 0:
        return np.zeros(0, bool)
    steps = np.arange(-SEEN_NEAR, thickness + SEEN_NEAR + cell / 2, cell / 2)
    pts = a + ts[:, None, None] * d + steps[None, :, None] * n  # [T, S, 2]
    row, col, inside = fr.grid.cell_of(pts.reshape(-1, 2))
    hit = (seen_wall[row, col] & inside).reshape(len(ts), len(steps))
    return hit.any(axis=1)


def _thickness(
    fr: Frame, closed: np.ndarray, a: np.ndarray, b: np.ndarray, cfg: LayoutConfig
) -> float:
    """Median run of closed wall cells behind the face a->b (frame xy), along its outward
    normal; `default_thickness` where none is seen."""
    cell = fr.grid.cell
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([d[1], -d[0]])  # right of the walk: outside a counter-clockwise outline
    length = float(np.linalg.norm(b - a))
    ts = np.arange(0.1 * length, 0.9 * length, cell)
    steps = np.arange(0.5, cfg.max_thickness / cell + 1, 1.0) * cell
    pts = a + ts[:, None, None] * d + steps[None, :, None] * n  # [T, S, 2]
    row, col, inside = fr.grid.cell_of(pts.reshape(-1, 2))
    hit = (closed[row, col] & inside).reshape(len(ts), len(steps))
    runs = np.argmin(hit, axis=1)  # 0 where the band runs past max_thickness: unknown
    runs = runs[runs > 0]
    return float(np.median(runs) * cell) if len(runs) else cfg.default_thickness


def architecture(bp: Blueprint, cfg: LayoutConfig) -> dict:
    """Rooms, walls and openings of the blueprint (world metres)."""
    wid, fid = class_id(bp, WALL_NAME), class_id(bp, FLOOR_NAME)
    out: dict = {"units": "m", "angle_deg": 0.0, "rooms": [], "walls": [], "openings": []}
    if wid is None:
        return out
    angle = dominant_angle(bp.labels == wid)
    fr = frame_of(bp, angle)
    out["angle_deg"] = round(math.degrees(angle), 3)
    cell = fr.grid.cell
    wall = fr.labels == wid
    # the wall cells some view saw (all of them when the plan does not say what was seen)
    seen_wall = wall if bp.seen is None else frame_of(_seen_walls(bp, wid), angle).labels == 1
    run = max(1, int(round(cfg.min_run / cell)))
    across = int(round(cfg.max_thickness / cell))
    closed = close_lines(wall, int(round(cfg.max_opening / cell)), run, across)
    if fid is not None and cfg.max_passage > cfg.max_opening:
        floor_ = fr.labels == fid
        closed |= close_passages(wall, floor_, int(round(cfg.max_passage / cell)), run, across)
    region, cuts = split(
        (fr.labels != UNKNOWN) & ~closed,
        cell,
        cfg.room_split_h,
        cfg.door_max,
        cfg.min_room_area,
        closed,
        cfg.min_run,
    )
    n = int(region.max())
    # a face is seen where a seen wall lies behind it, or an opening (a gap in the wall line,
    # a cut between rooms) some view saw through
    gap = closed & ~wall
    for _, _, rc in cuts:
        gap[rc[:, 0], rc[:, 1]] = True
    if bp.seen is not None:
        gap &= frame_of(Blueprint(bp.seen.astype(np.uint8), bp.grid), angle).labels == 1
    seen_face = seen_wall | gap
    area = ndi.sum_labels(np.ones_like(region), region, np.arange(1, n + 1)) * cell**2
    # a room has floor: a closed space of objects (stereo's noise behind a photos-only plan's
    # walls, labelled object there) with specks of floor is none
    floor = (
        np.full(n, np.inf)
        if fid is None
        else ndi.sum_labels(fr.labels == fid, region, np.arange(1, n + 1)) * cell**2
    )
    faces: list[tuple[int, np.ndarray, np.ndarray]] = []
    room_of: dict[int, int] = {}  # region label -> room index
    traced: list[tuple[int, np.ndarray]] = []  # (region label, outline in the frame)
    rooms_at = 1 + np.nonzero((area >= cfg.min_room_area) & (floor >= cfg.min_room_area))[0]
    for k in np.argsort(-area, kind="stable"):  # largest first, ties in label order
        if area[k] < cfg.min_room_area:
            break
        if floor[k] < cfg.min_room_area:
            continue
        # the closing also fills the notches of a ragged wall face: one cell back, up to the
        # wall cells themselves (measured: 1 cm inward on each side of a room 23 deg off axis)
        mask = ndi.binary_fill_holes(region == k + 1)
        # pieces too small for a room inside the room's box are its own (floor cut off by
        # wall-labelled clutter), with what closed them off
        sl = ndi.find_objects(mask.astype(np.int32))[0]
        small = np.isin(region[sl], 1 + np.nonzero(area < cfg.min_room_area)[0])
        box = np.zeros_like(mask)
        box[sl] = small | (closed[sl] & ~wall[sl])
        lab, _ = ndi.label(box | mask)
        mask = ndi.binary_fill_holes(lab == lab[np.nonzero(mask)][0]) & (mask | box)
        others = np.isin(region, rooms_at[rooms_at != k + 1])  # other rooms' cells stay theirs
        mask |= ndi.binary_dilation(mask) & ~wall & (fr.labels != UNKNOWN) & ~others
        r = max(1, int(round(cfg.notch / cell / 2)))
        disk = np.hypot(*np.mgrid[-r : r + 1, -r : r + 1]) <= r
        mask = ndi.binary_closing(np.pad(mask, r + 1), disk)[r + 1 : -r - 1, r + 1 : -r - 1]
        mask &= ~others
        if not ndi.binary_erosion(mask, iterations=max(1, int(0.4 / cell))).any():
            continue  # no room is narrower than 0.8 m: a strip of floor outside the walls
        poly = outline(mask, fr, cfg)
        if poly is None:
            continue
        poly = filled_between(poly, fr, others, wall)
        if bp.seen is not None:  # corners closed over space no view saw follow what they saw

            def seen_edge(a: np.ndarray, b: np.ndarray) -> bool:
                along = _seen_along(fr, seen_face, a, b, _thickness(fr, closed, a, b, cfg))
                return len(along) > 0 and along.mean() >= SEEN_SHARE

            poly = notched(poly, mask, fr, seen_edge, others)
            poly = recessed(poly, mask, fr, seen_edge, others)
        if cfg.face_offset > 0:
            grown = Polygon(poly).buffer(cfg.face_offset * cell, join_style="mitre", mitre_limit=10)
            # kept as traced where the offset would change the outline's corners
            if grown.geom_type == "Polygon" and len(grown.exterior.coords) - 1 == len(poly):
                poly = np.asarray(orient(grown, 1.0).exterior.coords)[:-1]
        traced.append((int(k) + 1, poly))
    polys = disjoint([p for _, p in traced], [k for k, _ in traced], region, fr)
    for (k, _), poly in zip(traced, polys, strict=True):
        if poly is None:
            continue
        ri = len(out["rooms"])
        room_of[k] = ri
        world = fr.to_world(poly)
        out["rooms"].append(
            {"name": f"room {ri + 1}", "polygon": _r(world), "area": round(Polygon(world).area, 4)}
        )
        for i in range(len(poly)):
            a, b = poly[i], poly[(i + 1) % len(poly)]
            t = _thickness(fr, closed, a, b, cfg)
            faces.append((ri, a, b))
            w = fr.to_world(np.array([a, b]))
            along = _seen_along(fr, seen_face, a, b, t)
            seen = len(along) > 0 and along.mean() >= SEEN_SHARE
            out["walls"].append(
                {
                    "start": _r(w[0]),
                    "end": _r(w[1]),
                    "length": round(float(np.linalg.norm(b - a)), 4),
                    "thickness": round(t, 4),
                    "room": ri,
                    "seen": bool(seen),
                }
            )
            pieces = seen_pieces(along, cell)
            if len(pieces) > 1:  # split later (rooms.split_seen), once the faces have moved
                out["walls"][-1]["pieces"] = pieces
        # an outline closed over space no view saw as a surface: the room goes on beyond it
        out["rooms"][-1]["continues"] = not all(w["seen"] for w in out["walls"] if w["room"] == ri)
    if fid is not None and faces:
        out["openings"] = _openings(
            fr, closed & ~wall & (fr.labels == fid), faces, out["walls"], cfg
        )
    if faces:
        out["openings"] += cut_openings(fr, cuts, room_of, faces, out["walls"], cfg.door_max)
    return out


def _openings(
    fr: Frame, gap: np.ndarray, faces: list, walls: list[dict], cfg: LayoutConfig
) -> list[dict]:
    """Floor in the closed wall line: each piece on the wall face it lies behind."""
    cell = fr.grid.cell
    lab, n = ndi.label(gap)
    out = []
    for k in range(1, n + 1):
        rows, cols = np.nonzero(lab == k)
        if len(rows) * cell**2 < 0.01:
            continue
        xy = fr.xy(np.stack([rows, cols], 1))
        best = None
        for wi, (_, a, b) in enumerate(faces):
            d = (b - a) / np.linalg.norm(b - a)
            nrm = np.array([d[1], -d[0]])
            t, s = (xy - a) @ d, (xy - a) @ nrm  # along the face, behind it
            depth = walls[wi]["thickness"] + 2 * cell
            on = (t > -cell) & (t < np.linalg.norm(b - a) + cell) & (s > -cell) & (s < depth)
            # the width is read in the wall's middle (the faces may be ragged off the axes)
            mid = on & (np.abs(s - walls[wi]["thickness"] / 2) <= walls[wi]["thickness"] / 4)
            if on.mean() > 0.5 and mid.any() and (best is None or on.mean() > best[0]):
                best = (on.mean(), wi, a, d, t[mid])
        if best is None:
            continue
        _, wi, a, d, t = best
        t0, t1 = float(t.min() - cell / 2), float(t.max() + cell / 2)
        p, q = fr.to_world(np.array([a + t0 * d, a + t1 * d]))
        width = t1 - t0
        kind = "door" if width <= cfg.door_max else "passage"
        out.append(
            {"kind": kind, "wall": wi, "start": _r(p), "end": _r(q), "width": round(width, 4)}
        )
    return out


def objects(
    bp: Blueprint, cfg: LayoutConfig, top: Callable | None = None, solid: Callable | None = None
) -> list[dict]:
    """Each object's footprint: oriented rectangle (or outline polygon when not box-like),
    width x depth; `top` gives (height, top) over floor points (walls.object_heights; None: no
    mesh, both None). The objects are the plan's instances: the semantics stage splits a
    cluster into pieces where its top steps (a counter run, the island, a chair's seat).
    `solid` ([N, 2] xy -> [N] bool: a surface stands above the floor there; walls.solid) keeps
    an object's footprint to the cells it stands on: the plan's field paints unseen floor
    beside furniture with the nearest object (the 7-Scenes kitchen's island drew 3.5 x 2.0 m
    where its surfaces span 2.9 x 1.25: now 2.8 x 1.4)."""
    names = {k: v for k, v in bp.classes.items() if v not in STRUCTURE}
    obj = np.isin(bp.labels, list(names))
    if bp.instances is not None:
        ids = np.where(obj, bp.instances, 0)
    else:
        ids = np.zeros(bp.labels.shape, np.int64)
        for c in names:
            lab, n = ndi.label(bp.labels == c)
            ids[lab > 0] = lab[lab > 0] + ids.max()
    cell, out = bp.grid.cell, []
    centres = bp.grid.centers()
    counts: dict[str, int] = {}
    for inst in np.unique(ids[ids > 0]):
        m = ids == inst
        if solid is not None and m.any():
            m[m] = solid(centres[m])
        if m.sum() * cell**2 < cfg.min_object_area:
            continue
        cls = int(np.bincount(bp.labels[m]).argmax())
        xy = centres[m]
        h = cell / 2
        corners = (xy[:, None, :] + np.array([[-h, -h], [h, -h], [h, h], [-h, h]])).reshape(-1, 2)
        hull = MultiPoint(corners).convex_hull
        rect = hull.minimum_rotated_rectangle
        rc = np.asarray(rect.exterior.coords)[:4]
        e0, e1 = rc[1] - rc[0], rc[2] - rc[1]
        major = e0 if np.linalg.norm(e0) >= np.linalg.norm(e1) else e1
        width, depth = (
            float(np.linalg.norm(major)),
            float(min(np.linalg.norm(e0), np.linalg.norm(e1))),
        )
        ang = math.degrees(math.atan2(major[1], major[0]))
        ang = (ang + 90) % 180 - 90
        box_like = m.sum() * cell**2 >= (1 - cfg.box_slack) * rect.area
        shape = rect if box_like else _outline(m, bp, hull)
        inner = ndi.binary_erosion(m)
        height, up = (
            top([centres[inner if inner.sum() >= 4 else m]])[0] if top is not None else (None, None)
        )
        name = bp.classes.get(cls, str(cls))
        counts[name] = counts.get(name, 0) + 1
        out.append(
            {
                "instance": int(inst),
                "class": name,
                "name": f"{name}_{counts[name]}",
                "shape": "rect" if box_like else "polygon",
                "polygon": _r(np.asarray(shape.exterior.coords)[:-1]),
                "center": _r(np.asarray(rect.centroid.coords)[0]),
                "width": round(width, 4),
                "depth": round(depth, 4),
                "angle_deg": round(ang, 3),
                "height": height,
                "top": up,
            }
        )
    return out


def in_rooms(objs: list[dict], rooms: list[dict], pad: float) -> tuple[list[dict], int]:
    """The objects whose footprint lies at least half inside a room (its outline grown by
    `pad` metres: a footprint against a wall's face may reach past the traced outline), and
    how many were left out: furniture of the next room seen through a doorway, stereo's
    noise behind a wall. Without rooms every object is kept."""
    if not rooms:
        return objs, 0
    area = Polygon(rooms[0]["polygon"]).buffer(pad)
    for r in rooms[1:]:
        area = area.union(Polygon(r["polygon"]).buffer(pad))
    kept = []
    for o in objs:
        fp = Polygon(o["polygon"])
        fp = fp if fp.is_valid else fp.buffer(0)  # a traced outline may touch itself
        if fp.area > 0 and fp.intersection(area).area >= 0.5 * fp.area:
            kept.append(o)
    return kept, len(objs) - len(kept)


def _outline(m: np.ndarray, bp: Blueprint, hull: Polygon) -> Polygon:
    """The outline of an object's cells (its largest piece, on the cell edges, simplified
    within a cell): an L of kitchen counters is an L, not the hull that spans the room; the
    convex hull where the trace is degenerate."""
    sl = ndi.find_objects(m.astype(np.int32))[0]
    cs = find_contours(np.pad(m[sl], 1).astype(np.float64), 0.5)
    if not cs:
        return hull
    rc = max(cs, key=len) - 1.0 + np.array([sl[0].start, sl[1].start])  # (row, col)
    (ox, oy), cell, h = bp.grid.origin, bp.grid.cell, bp.grid.shape[0]
    xy = np.stack([ox + (rc[:, 1] + 0.5) * cell, oy + (h - rc[:, 0] - 0.5) * cell], 1)
    poly = Polygon(xy).buffer(0).simplify(cell)
    if poly.geom_type != "Polygon" or poly.is_empty or poly.area < 0.5 * m.sum() * cell**2:
        return hull
    return orient(poly, 1.0)

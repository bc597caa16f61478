"""The meshes and the exact layout of a procedural home (stages/synth/home_plan.py).

Walls are what lies inside the outer wall band and outside every room and gap, cut into
axis-aligned boxes; a passage with a lintel gets the wall above it back from its `top`.
Each room has its own floor (and the floor through the gaps it opens), the ceiling covers
the whole home, an outside door looks onto a wall BEYOND metres past it (as the L room's
doors do). Furniture is placed in each room as in a single room (room.furnish), with the
floor in front of each gap kept free and tall pieces kept LOOP_CLEAR off the camera's walk.
"""

from __future__ import annotations

import logging
from typing import cast

import numpy as np
import trimesh
from shapely import affinity
from shapely.geometry import LineString, Polygon, box

from stages.common.classes import CEILING, CEILING_NAME, FLOOR, WALL
from stages.common.classes import SYNTH_COLORS as PALETTE
from stages.synth.doors import CLEAR, bounds_mesh
from stages.synth.home_plan import Gap, HomePlan
from stages.synth.room import CLASSES, LOOP_CLEAR, Part, Room, _jitter, _Layout, furnish
from stages.synth.shape import BEYOND, faces_of

log = logging.getLogger(__name__)


def _concat(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    out = trimesh.util.concatenate(meshes)
    assert isinstance(out, trimesh.Trimesh)
    return out


def wall_boxes(plan: HomePlan) -> list[tuple[float, float, float, float]]:
    """(x0, x1, y0, y1) boxes tiling the walls in plan: the outer band round the home, minus
    the rooms and the gaps; rows of a fine grid merged along x, then equal runs along y."""
    t = plan.wall
    lx, ly = plan.size
    free = [b for k in range(plan.n_rooms) for b in plan.boxes_of(k)] + [g.rect for g in plan.gaps]
    xs = sorted({-t, lx + t, *(v for b in free for v in b[:2])})
    ys = sorted({-t, ly + t, *(v for b in free for v in b[2:])})
    cx = (np.array(xs[:-1]) + np.array(xs[1:])) / 2
    cy = (np.array(ys[:-1]) + np.array(ys[1:])) / 2
    solid = np.ones((len(cy), len(cx)), bool)
    for x0, x1, y0, y1 in free:
        solid[np.ix_((cy > y0) & (cy < y1), (cx > x0) & (cx < x1))] = False
    runs: dict[tuple[int, int], list[int]] = {}  # (x from, x to) -> rows
    for j in range(len(cy)):
        i = 0
        while i < len(cx):
            if solid[j, i]:
                k = i
                while k + 1 < len(cx) and solid[j, k + 1]:
                    k += 1
                runs.setdefault((i, k + 1), []).append(j)
                i = k + 1
            else:
                i += 1
    out = []
    for (i0, i1), rows in sorted(runs.items()):
        start = rows[0]
        for a, b in zip(rows, rows[1:] + [None], strict=True):
            if b != a + 1:
                out.append((xs[i0], xs[i1], ys[start], ys[a + 1]))
                start = cast(int, b)  # None past the last row only, where the loop ends
    return sorted(out)


def _beyond(g: Gap, plan: HomePlan) -> tuple[float, float, float, float, float, float]:
    """The wall an outside door looks onto: BEYOND past the outer band, 0.5 m wider a side."""
    s0, s1 = g.start - 0.5, g.end + 0.5
    out = g.band[1] + BEYOND if g.normal[0] + g.normal[1] > 0 else g.band[0] - BEYOND
    a, b = (out, out + 0.1) if g.normal[0] + g.normal[1] > 0 else (out - 0.1, out)
    if g.along_x:
        return (s0, s1, a, b, 0.0, plan.height)
    return (a, b, s0, s1, 0.0, plan.height)


def clear_in_front(g: Gap, side: int) -> Polygon:
    """The floor kept free in front of a gap on its side `side` (-1: rooms[0]'s, +1: the
    other's): a door-wide square, a passage's strip up to CLEAR deep."""
    depth = g.width if g.kind == "door" else min(g.width, CLEAR)
    x0, x1, y0, y1 = g.rect
    if g.along_x:
        y = y0 if side * g.normal[1] < 0 else y1
        far = y + side * g.normal[1] * depth
        return box(x0, min(y, far), x1, max(y, far))
    x = x0 if side * g.normal[0] < 0 else x1
    far = x + side * g.normal[0] * depth
    return box(min(x, far), y0, max(x, far), y1)


def home_parts(
    plan: HomePlan, seed: int, walk: np.ndarray, ceiling: bool = True
) -> tuple[Part, ...]:
    """The home's parts: floors (room by room), walls, lintels, the outside door's wall
    beyond, the ceiling, then the furniture (instances 1.. room by room). walk: the camera's
    path [K, 2] (x, y), kept clear of tall furniture."""
    rng = np.random.default_rng([seed, 12, plan.n_rooms])
    h, parts = plan.height, []
    for k in range(plan.n_rooms):
        slabs = [(*b, -0.05, 0.0) for b in plan.boxes_of(k)]
        slabs += [(*g.rect, -0.05, 0.0) for g in plan.gaps if g.rooms[0] == k]
        mesh = _concat([bounds_mesh(b) for b in slabs])
        parts.append(Part(mesh, FLOOR, 0, f"floor_{k + 1}", _jitter(rng, PALETTE[FLOOR])))
    boxes = [(*b, 0.0, h) for b in wall_boxes(plan)]
    boxes += [(*g.rect, g.top, h) for g in plan.gaps if g.top is not None]
    parts.append(
        Part(
            _concat([bounds_mesh(b) for b in boxes]), WALL, 0, "walls", _jitter(rng, PALETTE[WALL])
        )
    )
    for i, g in enumerate(g for g in plan.gaps if len(g.rooms) == 1):
        parts.append(
            Part(
                bounds_mesh(_beyond(g, plan)),
                WALL,
                0,
                f"beyond_{i + 1}",
                _jitter(rng, PALETTE[WALL]),
            )
        )
    color = _jitter(rng, PALETTE[CEILING])
    if ceiling:
        t, (lx, ly) = plan.wall, plan.size
        top = bounds_mesh((-t, lx + t, -t, ly + t, h, h + 0.05))
        parts.append(Part(top, CEILING, 0, CEILING_NAME, color))
    ring = LineString(walk).buffer(LOOP_CLEAR)
    counts: dict[int, int] = {}
    placed = [cm for k in range(plan.n_rooms) for cm in _furnish_room(plan, k, seed, ring)]
    for i, (cls, mesh) in enumerate(placed, start=1):
        counts[cls] = counts.get(cls, 0) + 1
        name = f"{CLASSES[cls]}_{counts[cls]}"
        parts.append(Part(mesh, cls, i, name, _jitter(rng, PALETTE[cls])))
    return tuple(parts)


def _furnish_room(
    plan: HomePlan, k: int, seed: int, ring: Polygon
) -> list[tuple[int, trimesh.Trimesh]]:
    """Room k's furniture (class, mesh in the home's frame), placed in the room's own frame
    (its bounding box's corner at the origin) as room.furnish places a room's."""
    poly = Polygon(plan.polygon(k))
    ox, oy, x1, y1 = poly.bounds
    keep = [clear_in_front(g, -1 if g.rooms[0] == k else 1) for g in plan.gaps if k in g.rooms]
    move = lambda s: affinity.translate(s, -ox, -oy)  # noqa: E731
    lay = _Layout((x1 - ox, y1 - oy), move(ring), [move(s) for s in keep], inside=move(poly))
    rng = np.random.default_rng([seed, 11, k])
    try:
        furnish(rng, lay, (x1 - ox, y1 - oy))
    except RuntimeError:  # no room for a table group: only what stands against the walls
        lay.placed = []
    out = []
    for p in lay.placed:
        mesh = p.mesh.copy()
        mesh.apply_translation([ox, oy, 0.0])
        out.append((p.cls, mesh))
    return out


def home_room(plan: HomePlan, parts: tuple[Part, ...]) -> Room:
    """The home as a Room (for the plan's top-down rays and gt/mesh.ply): its bounding box."""
    lx, ly = plan.size
    return Room((lx, ly), plan.height, plan.wall, parts, (lx / 2, ly / 2, 0.0, 0.0))


def _area(poly: list[list[float]]) -> float:
    x, y = [p[0] for p in poly], [p[1] for p in poly]
    return 0.5 * sum(x[i - 1] * y[i] - x[i] * y[i - 1] for i in range(len(poly)))


def home_layout(plan: HomePlan) -> dict:
    """gt/layout.json of the home: rooms (name, counter-clockwise interior polygon, area),
    walls (each room's own, interior face, room on the left, with `room`), openings (each
    with `rooms`: the two it joins, or one for a door to the outside; `wall`: the index of
    the wall of rooms[0] it cuts; its ends on that wall's face)."""
    rooms: list[dict] = []
    walls: list[dict] = []
    for k in range(plan.n_rooms):
        poly = [[float(x), float(y)] for x, y in plan.polygon(k)]
        rooms.append({"name": f"room {k + 1}", "polygon": poly, "area": round(_area(poly), 6)})
        for f in faces_of(plan.polygon(k), plan.wall, plan.height):
            walls.append(
                {
                    "name": f.name,
                    "start": list(f.a),
                    "end": list(f.b),
                    "thickness": plan.wall,
                    "length": round(f.length, 6),
                    "room": k,
                }
            )
    openings = []
    for g in plan.gaps:
        step = g.normal[1] if g.along_x else g.normal[0]
        face = g.band[0] if step > 0 else g.band[1]  # rooms[0]'s side of the band
        ax = 1 if g.along_x else 0
        wi = next(
            i
            for i, w in enumerate(walls)
            if w["room"] == g.rooms[0]
            and w["start"][ax] == face == w["end"][ax]
            and min(w["start"][1 - ax], w["end"][1 - ax]) <= g.start
            and g.end <= max(w["start"][1 - ax], w["end"][1 - ax])
        )
        p, q = ([g.start, face], [g.end, face]) if g.along_x else ([face, g.start], [face, g.end])
        o = {
            "kind": g.kind,
            "rooms": list(g.rooms),
            "wall": wi,
            "start": p,
            "end": q,
            "width": round(g.width, 6),
        }
        if g.kind == "passage":
            o["top"] = plan.height if g.top is None else g.top
        openings.append(o)
    return {"units": "m", "rooms": rooms, "walls": walls, "openings": openings}

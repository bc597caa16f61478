"""Doors and passages of the procedural room: gaps in the walls with the floor running through.

A door is a full-height gap (no leaf) WIDTH wide; a passage is wider (PASSAGE), full height or
up to a lintel (the wall above it from LINTEL high). Doors are drawn from their own random
stream (seed, 2), passages from (seed, 4) in the walls left without a door, so adding either
leaves the rest of a seed's room (size, colours, the other kind's gaps) as it was; the
furniture is placed round them. The floor in front of a gap (a door-wide square, a passage
wide and up to CLEAR deep) is kept free of furniture.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, TypeVar

import numpy as np
import trimesh
from shapely.geometry import Polygon, box

from stages.common.classes import FLOOR_NAME

WALLS = ("wall_north", "wall_south", "wall_east", "wall_west")
WIDTH = (0.8, 1.0)  # door width range (metres)
CORNER = 0.3  # a door keeps this far from the room's corners (metres)
PASSAGE = (1.5, 2.0)  # passage width range (metres): wider than the layout's door_max, 1.2
LINTEL = (2.0, 2.3)  # a passage's lintel height range (metres), when it has one
CLEAR = 1.0  # metres: the furniture-free floor in front of a passage reaches this far in

P = TypeVar("P")  # a room part: a dataclass with `mesh` and `name`
Bounds = tuple[float, float, float, float, float, float]  # x0, x1, y0, y1, z0, z1


@dataclass(frozen=True)
class Door:
    """A gap in one wall, the floor continuing through it (a door or a passage)."""

    wall: str  # one of WALLS
    start: float  # along the wall's interior face: x for north/south, y for east/west (m)
    end: float  # start < end (metres)
    kind: str = "door"  # "door" or "passage"
    top: float | None = None  # metres: the lintel's underside (None: full height)

    @property
    def width(self) -> float:
        return self.end - self.start


def draw_doors(seed: int, n: int, lx: float, ly: float) -> list[Door]:
    """`n` (0..4) doors in distinct walls of the room [0, lx] x [0, ly]."""
    if not 0 <= n <= len(WALLS):
        raise ValueError(f"doors must be in 0..4, got {n}")
    rng = np.random.default_rng([seed, 2])
    out = []
    for k in rng.permutation(len(WALLS))[:n]:
        name = WALLS[int(k)]
        span = lx if name in ("wall_north", "wall_south") else ly
        w = round(float(rng.uniform(*WIDTH)), 3)
        a = round(float(rng.uniform(CORNER, span - CORNER - w)), 3)
        out.append(Door(name, a, round(a + w, 3)))
    return out


def draw_passages(seed: int, n: int, spans: list[tuple[str, float, float]]) -> list[Door]:
    """`n` passages in distinct walls of `spans` (name, start, length along the face: the
    walls without a door) long enough for one."""
    rng = np.random.default_rng([seed, 4])
    room_for = [sp for sp in spans if sp[2] >= 2 * CORNER + PASSAGE[1] + 0.2]
    if not 0 <= n <= len(room_for):
        raise ValueError(f"passages must be in 0..{len(room_for)} for this room, got {n}")
    out = []
    for k in rng.permutation(len(room_for))[:n]:
        name, lo, length = room_for[int(k)]
        w = round(float(rng.uniform(*PASSAGE)), 3)
        a = round(float(lo + rng.uniform(CORNER, length - CORNER - w)), 3)
        top = round(float(rng.uniform(*LINTEL)), 3) if rng.random() < 0.5 else None
        out.append(Door(name, a, round(a + w, 3), "passage", top))
    return out


def depth_clear(d: Door) -> float:
    """How far into the room the floor in front of a gap is kept free (metres)."""
    return d.width if d.kind == "door" else min(d.width, CLEAR)


def clearance(d: Door, lx: float, ly: float) -> Polygon:
    """The floor in front of the gap inside the room: a door-wide square, a passage's strip."""
    w = depth_clear(d)
    if d.wall == "wall_north":
        return box(d.start, ly - w, d.end, ly)
    if d.wall == "wall_south":
        return box(d.start, 0.0, d.end, w)
    if d.wall == "wall_east":
        return box(lx - w, d.start, lx, d.end)
    return box(0.0, d.start, w, d.end)


def wall_bounds(name: str, lx: float, ly: float, t: float, h: float) -> Bounds:
    """The box of a whole wall (as the room builder makes it)."""
    return {
        "wall_north": (-t, lx + t, ly, ly + t, 0.0, h),
        "wall_south": (-t, lx + t, -t, 0.0, 0.0, h),
        "wall_east": (lx, lx + t, 0.0, ly, 0.0, h),
        "wall_west": (-t, 0.0, 0.0, ly, 0.0, h),
    }[name]


def wall_pieces(
    name: str, doors: list[Door], bounds: Bounds, along_x: bool | None = None
) -> list[Bounds]:
    """The wall's box cut by its gaps into the pieces between them, and the lintels over
    those that have one (along x or y; by default from the name of a rectangular room's
    wall)."""
    x0, x1, y0, y1, z0, z1 = bounds
    along_x = name in ("wall_north", "wall_south") if along_x is None else along_x
    lo, hi = (x0, x1) if along_x else (y0, y1)
    cuts = sorted((d.start, d.end) for d in doors if d.wall == name)
    spans = [
        (a, b, z0, z1)
        for a, b in zip([lo] + [c[1] for c in cuts], [c[0] for c in cuts] + [hi], strict=True)
    ]
    spans += [(d.start, d.end, d.top, z1) for d in doors if d.wall == name and d.top is not None]
    out = []
    for a, b, za, zb in spans:
        if b - a > 1e-9 and zb - za > 1e-9:
            out.append((a, b, y0, y1, za, zb) if along_x else (x0, x1, a, b, za, zb))
    return out


def threshold(d: Door, lx: float, ly: float, t: float) -> Bounds:
    """The floor slab under the door's gap (the floor's thickness, 5 cm)."""
    x0, x1, y0, y1, _, _ = wall_bounds(d.wall, lx, ly, t, 0.0)
    if d.wall in ("wall_north", "wall_south"):
        return (d.start, d.end, y0, y1, -0.05, 0.0)
    return (x0, x1, d.start, d.end, -0.05, 0.0)


def bounds_mesh(b: Bounds) -> trimesh.Trimesh:
    x0, x1, y0, y1, z0, z1 = b
    t = np.eye(4)
    t[:3, 3] = [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]
    return trimesh.creation.box(extents=[x1 - x0, y1 - y0, z1 - z0], transform=t)


def cut_doors(
    parts: list[P], doors: list[Door], dims: tuple[float, float, float, float]
) -> list[P]:
    """The room's parts with the walls cut by the doors and the floor run through them (same
    names and colours). dims: (lx, ly, wall thickness, wall height)."""
    lx, ly, t, h = dims
    out = []
    for p in parts:
        q: Any = p
        if q.name in WALLS and any(d.wall == q.name for d in doors):
            pieces = wall_pieces(q.name, doors, wall_bounds(q.name, lx, ly, t, h))
            q = replace(q, mesh=trimesh.util.concatenate([bounds_mesh(b) for b in pieces]))
        elif q.name == FLOOR_NAME:
            slabs = [bounds_mesh(threshold(d, lx, ly, t)) for d in doors]
            q = replace(q, mesh=trimesh.util.concatenate([q.mesh, *slabs]))
        out.append(q)
    return out

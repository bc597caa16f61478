"""A procedural room: walls with real thickness, floor, optional ceiling, furniture from boxes.

World frame (DESIGN.md): metres, z up, floor top at z = 0. The room interior spans
[0, Lx] x [0, Ly]; the four walls stand outside it, `wall` metres thick, from z = 0 to
`height`. Furniture footprints are disjoint (no object under another, so the top-down plan
hides nothing) and stay inside the interior; objects taller than `LOW_MAX` keep
`LOOP_CLEAR` metres off the camera loop, and cameras fly at CAM_Z[0] or higher, so a camera
is never inside furniture and passes at least 0.35 m above whatever stands under the loop.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from shapely import affinity
from shapely.geometry import Point, Polygon, box

from stages.synth.doors import Door, clearance, cut_doors, draw_doors

log = logging.getLogger(__name__)

FLOOR, WALL, CEILING, TABLE, CHAIR, SOFA, CABINET, BED, PLANT = range(9)
CLASSES = {
    FLOOR: "floor",
    WALL: "wall",
    CEILING: "ceiling",
    TABLE: "table",
    CHAIR: "chair",
    SOFA: "sofa",
    CABINET: "cabinet",
    BED: "bed",
    PLANT: "plant",
}
IGNORE = (CEILING,)  # never projected to the plan

# Base colours (linear RGB in [0, 1]); each instance gets a jittered copy.
PALETTE = {
    FLOOR: (0.62, 0.48, 0.34),
    WALL: (0.78, 0.76, 0.70),
    CEILING: (0.85, 0.85, 0.85),
    TABLE: (0.55, 0.33, 0.18),
    CHAIR: (0.30, 0.42, 0.62),
    SOFA: (0.62, 0.22, 0.24),
    CABINET: (0.80, 0.70, 0.45),
    BED: (0.35, 0.60, 0.50),
    PLANT: (0.25, 0.55, 0.20),
}

CAM_Z = (1.25, 1.65)  # camera heights along the loop (metres)
LOW_MAX = 0.9  # objects up to this height may stand under the camera loop
LOOP_WALL = 1.3  # the loop keeps this far from the walls when the room allows it
LOOP_CLEAR = 0.45  # tall objects keep this far from the loop (metres)
GAP = 0.08  # minimum gap between two objects' footprints (metres)


@dataclass(frozen=True)
class Part:
    """One mesh of the scene: a room surface (instance 0) or a piece of furniture (1..)."""

    mesh: trimesh.Trimesh
    cls: int  # class id (CLASSES)
    instance: int  # 0 = floor / wall / ceiling, 1.. = furniture
    name: str  # e.g. "chair_2", "wall_north"
    color: tuple[float, float, float]  # base RGB in [0, 1]


@dataclass(frozen=True)
class Room:
    """The scene and the ellipse the cameras move along."""

    size: tuple[float, float]  # interior (Lx, Ly) metres
    height: float  # wall height (metres); the ceiling underside when there is one
    wall: float  # wall thickness (metres)
    parts: tuple[Part, ...]
    loop: tuple[float, float, float, float]  # camera ellipse (cx, cy, semi-axis x, semi-axis y)
    doors: tuple[Door, ...] = ()  # openings in the walls (floor through them, no lintel)

    @property
    def furniture(self) -> tuple[Part, ...]:
        return tuple(p for p in self.parts if p.instance > 0)


# ---- primitives ------------------------------------------------------------------------
def _box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> trimesh.Trimesh:
    """Axis-aligned box between the given bounds (local frame)."""
    t = np.eye(4)
    t[:3, 3] = [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]
    return trimesh.creation.box(extents=[x1 - x0, y1 - y0, z1 - z0], transform=t)


def _cylinder(x: float, y: float, r: float, z0: float, z1: float) -> trimesh.Trimesh:
    t = np.eye(4)
    t[:3, 3] = [x, y, (z0 + z1) / 2]
    return trimesh.creation.cylinder(radius=r, height=z1 - z0, sections=32, transform=t)


def _legs(hx: float, hy: float, inset: float, side: float, z1: float) -> list[trimesh.Trimesh]:
    """Four square legs under a rectangle of half extents (hx, hy)."""
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (hx - inset - side / 2), sy * (hy - inset - side / 2)
            out.append(_box(cx - side / 2, cx + side / 2, cy - side / 2, cy + side / 2, 0, z1))
    return out


# ---- furniture, in a local frame: footprint centred at the origin, back towards +y ------
# Each builder returns (parts, footprint half extents (hx, hy) or radius as (r, -1), height).
Built = tuple[list[trimesh.Trimesh], tuple[float, float], float]


def _measure(parts: list[trimesh.Trimesh], round_foot: bool = False) -> Built:
    """Parts with their footprint (symmetric about the origin) and height, from the vertices."""
    v = np.concatenate([m.vertices for m in parts])  # [V, 3]
    if round_foot:
        ext = (float(np.linalg.norm(v[:, :2], axis=1).max()), -1.0)
    else:
        ext = (float(np.abs(v[:, 0]).max()), float(np.abs(v[:, 1]).max()))
    return parts, ext, float(v[:, 2].max())


def _table(rng: np.random.Generator) -> Built:
    w, d, h = rng.uniform(1.0, 1.6), rng.uniform(0.7, 0.9), rng.uniform(0.72, 0.78)
    parts = [_box(-w / 2, w / 2, -d / 2, d / 2, h - 0.04, h)]
    parts += _legs(w / 2, d / 2, 0.05, 0.05, h - 0.04)
    return _measure(parts)


def _chair(rng: np.random.Generator) -> Built:
    s, sh, top = rng.uniform(0.42, 0.48), rng.uniform(0.43, 0.47), rng.uniform(0.78, 0.88)
    parts = [
        _box(-s / 2, s / 2, -s / 2, s / 2, sh - 0.04, sh),
        _box(-s / 2, s / 2, s / 2 - 0.04, s / 2, sh, top),
    ]
    parts += _legs(s / 2, s / 2, 0.01, 0.035, sh - 0.04)
    return _measure(parts)


def _sofa(rng: np.random.Generator) -> Built:
    w, d = rng.uniform(1.6, 2.2), rng.uniform(0.8, 0.95)
    seat, back, arm, at = rng.uniform(0.40, 0.45), rng.uniform(0.78, 0.86), 0.6, 0.18
    parts = [
        _box(-w / 2, w / 2, -d / 2, d / 2, 0.0, seat),
        _box(-w / 2, w / 2, d / 2 - 0.22, d / 2, 0.0, back),
        _box(-w / 2, -w / 2 + at, -d / 2, d / 2, 0.0, arm),
        _box(w / 2 - at, w / 2, -d / 2, d / 2, 0.0, arm),
    ]
    # two seat cushions, slightly proud of the base
    mid = 0.01
    parts += [
        _box(-w / 2 + at + 0.02, -mid, -d / 2 + 0.03, d / 2 - 0.24, seat, seat + 0.06),
        _box(mid, w / 2 - at - 0.02, -d / 2 + 0.03, d / 2 - 0.24, seat, seat + 0.06),
    ]
    return _measure(parts)


def _cabinet(rng: np.random.Generator) -> Built:
    w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.4, 0.55), rng.uniform(1.0, 1.9)
    door = 0.015
    y0 = -d / 2 + door  # body front; the doors stand proud of it
    parts = [
        _box(-w / 2, w / 2, y0, d / 2, 0.08, h),
        _box(-w / 2 + 0.03, w / 2 - 0.03, y0 + 0.03, d / 2, 0.0, 0.08),
    ]
    for x0, x1 in ((-w / 2 + 0.02, -0.005), (0.005, w / 2 - 0.02)):
        parts.append(_box(x0, x1, -d / 2, y0, 0.12, h - 0.04))
        hx = x1 - 0.05 if x0 < 0 else x0 + 0.05
        parts.append(_box(hx - 0.012, hx + 0.012, -d / 2 - 0.02, -d / 2, h / 2 - 0.1, h / 2 + 0.1))
    return _measure(parts)


def _bed(rng: np.random.Generator) -> Built:
    w, length, h = rng.uniform(1.4, 1.8), rng.uniform(1.9, 2.1), rng.uniform(0.45, 0.55)
    hb = 0.06  # headboard thickness, at the +y end
    y1 = length / 2 - hb
    parts = [
        _box(-w / 2, w / 2, -length / 2, y1, 0.0, h - 0.2),
        _box(-w / 2 + 0.03, w / 2 - 0.03, -length / 2 + 0.03, y1, h - 0.2, h),
        _box(-w / 2, w / 2, y1, length / 2, 0.0, 0.88),
    ]
    for x0, x1 in ((-w / 2 + 0.1, -0.05), (0.05, w / 2 - 0.1)):
        parts.append(_box(x0, x1, y1 - 0.45, y1 - 0.08, h, h + 0.12))
    return _measure(parts)


def _plant(rng: np.random.Generator) -> Built:
    rp, hp, rf = rng.uniform(0.14, 0.22), rng.uniform(0.3, 0.45), rng.uniform(0.28, 0.42)
    foliage = trimesh.creation.icosphere(subdivisions=3, radius=rf)
    foliage.apply_translation([0, 0, hp + 0.85 * rf])
    parts = [_cylinder(0, 0, rp, 0.0, hp), _cylinder(0, 0, rp + 0.02, hp - 0.04, hp), foliage]
    return _measure(parts, round_foot=True)


BUILDERS: dict[int, Callable[[np.random.Generator], Built]] = {
    TABLE: _table,
    CHAIR: _chair,
    SOFA: _sofa,
    CABINET: _cabinet,
    BED: _bed,
    PLANT: _plant,
}


# ---- placement -------------------------------------------------------------------------
@dataclass
class _Placed:
    cls: int
    mesh: trimesh.Trimesh
    foot: Polygon  # world footprint
    height: float


def _footprint(ext: tuple[float, float], x: float, y: float, yaw: float) -> Polygon:
    if ext[1] < 0:  # round
        return Point(x, y).buffer(ext[0], quad_segs=16)
    rect = box(-ext[0], -ext[1], ext[0], ext[1])
    return affinity.translate(affinity.rotate(rect, yaw, origin=(0, 0), use_radians=True), x, y)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:2, 3] = [x, y]
    return t


def _instantiate(cls: int, built: Built, x: float, y: float, yaw: float) -> _Placed:
    parts, ext, h = built
    mesh = _join(parts)
    mesh.apply_transform(_pose(x, y, yaw))
    return _Placed(cls, mesh, _footprint(ext, x, y, yaw), h)


def _yaw_facing(nx: float, ny: float) -> float:
    """Yaw that turns the local +y (the back) towards the world direction (nx, ny)."""
    return math.atan2(ny, nx) - math.pi / 2


class _Layout:
    """Footprints placed so far, checked against the room, each other and the camera loop."""

    def __init__(self, size: tuple[float, float], ring: Polygon, keep_out: list[Polygon]) -> None:
        self.inside = box(0.02, 0.02, size[0] - 0.02, size[1] - 0.02)
        self.ring = ring
        self.placed: list[_Placed] = []
        self.keep_out = keep_out  # furniture-free floor, e.g. in front of a door

    def fits(self, group: list[_Placed]) -> bool:
        taken = [p.foot.buffer(GAP) for p in self.placed] + self.keep_out
        for i, p in enumerate(group):
            if not self.inside.contains(p.foot):
                return False
            if p.height > LOW_MAX and p.foot.intersects(self.ring):
                return False
            if any(p.foot.intersects(t) for t in taken):
                return False
            if any(p.foot.intersects(q.foot.buffer(GAP)) for q in group[:i]):
                return False
        return True


def _table_group(
    rng: np.random.Generator, lay: _Layout, size: tuple[float, float]
) -> list[_Placed]:
    """A table with chairs around it: always one chair per long side, more when room allows."""
    for _ in range(200):
        table = _table(rng)
        hx, hy = table[1]
        yaw = float(rng.choice([0.0, math.pi / 2]) + rng.uniform(-0.35, 0.35))
        x, y = rng.uniform(0.5, size[0] - 0.5), rng.uniform(0.5, size[1] - 0.5)
        group = [_instantiate(TABLE, table, x, y, yaw)]
        c, s = math.cos(yaw), math.sin(yaw)
        # sides as (outward normal in the table frame, half extent along it, lateral offsets)
        per_long = 2 if 2 * hx >= 1.3 and rng.random() < 0.6 else 1
        offs = [0.0] if per_long == 1 else [-hx / 2, hx / 2]
        sides = [((0, 1), hy, offs), ((0, -1), hy, offs)]
        sides += [((n, 0), hx, [0.0]) for n in (1, -1) if rng.random() < 0.4]
        for (nx, ny), half, lateral in sides:
            for off in lateral:
                chair = _chair(rng)
                dist = half + rng.uniform(0.1, 0.2) + chair[1][1]
                lx, ly = nx * dist + (-ny) * off, ny * dist + nx * off  # table frame
                wx, wy = x + c * lx - s * ly, y + s * lx + c * ly
                wn = (c * nx - s * ny, s * nx + c * ny)
                jitter = rng.uniform(-0.12, 0.12)
                group.append(_instantiate(CHAIR, chair, wx, wy, _yaw_facing(*wn) + jitter))
        if lay.fits(group):
            return group
    raise RuntimeError("no room for the table group")  # unreachable for rooms >= 3.5 m


def _against_wall(
    rng: np.random.Generator, lay: _Layout, size: tuple[float, float], cls: int
) -> _Placed | None:
    """An object with its back to a random wall, at a random place along it."""
    lx, ly = size
    for _ in range(60):
        built = BUILDERS[cls](rng)
        ext = built[1]
        depth = ext[0] if ext[1] < 0 else ext[1]
        along = ext[0]
        wall = int(rng.integers(4))  # north, south, east, west
        gap = rng.uniform(0.03, 0.08)
        if wall < 2:
            x = rng.uniform(along, lx - along)
            y = ly - gap - depth if wall == 0 else gap + depth
            yaw = _yaw_facing(0.0, 1.0 if wall == 0 else -1.0)
        else:
            y = rng.uniform(along, ly - along)
            x = lx - gap - depth if wall == 2 else gap + depth
            yaw = _yaw_facing(1.0 if wall == 2 else -1.0, 0.0)
        placed = _instantiate(cls, built, x, y, yaw)
        if lay.fits([placed]):
            return placed
    return None


def _ellipse(cx: float, cy: float, a: float, b: float, n: int = 128) -> Polygon:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return Polygon(np.stack([cx + a * np.cos(t), cy + b * np.sin(t)], axis=1))


def build_room(seed: int, ceiling: bool = True, doors: int = 0) -> Room:
    """The room of a seed: size, walls, furniture, `doors` doors (stages/synth/doors.py)."""
    rng = np.random.default_rng([seed, 1])
    lx, ly = round(float(rng.uniform(4.0, 7.0)), 3), round(float(rng.uniform(3.5, 6.0)), 3)
    height, wall = round(float(rng.uniform(2.5, 2.8)), 3), round(float(rng.uniform(0.1, 0.15)), 3)
    a, b = max(0.6, lx / 2 - LOOP_WALL), max(0.5, ly / 2 - LOOP_WALL)
    loop = (lx / 2, ly / 2, a, b)
    ring = _ellipse(*loop).exterior.buffer(LOOP_CLEAR)
    gaps = draw_doors(seed, doors, lx, ly)
    lay = _Layout((lx, ly), ring, [clearance(d, lx, ly) for d in gaps])
    lay.placed += _table_group(rng, lay, (lx, ly))
    wish = [SOFA, CABINET, BED, PLANT, PLANT, CABINET]
    keep = [
        c for c, p in zip(wish, (0.8, 0.9, 0.5, 0.9, 0.5, 0.4), strict=True) if rng.random() < p
    ]
    for cls in keep:
        placed = _against_wall(rng, lay, (lx, ly), cls)
        if placed is not None:
            lay.placed.append(placed)

    parts = _room_parts(rng, lx, ly, height, wall, ceiling)
    parts = cut_doors(parts, gaps, (lx, ly, wall, height)) if gaps else parts
    counts: dict[int, int] = {}
    for i, p in enumerate(lay.placed, start=1):
        counts[p.cls] = counts.get(p.cls, 0) + 1
        parts.append(
            Part(
                p.mesh, p.cls, i, f"{CLASSES[p.cls]}_{counts[p.cls]}", _jitter(rng, PALETTE[p.cls])
            )
        )
    log.info("room %.2f x %.2f x %.2f m, %d pieces of furniture", lx, ly, height, len(lay.placed))
    return Room((lx, ly), height, wall, tuple(parts), loop, tuple(gaps))


def _jitter(rng: np.random.Generator, c: tuple[float, float, float]) -> tuple[float, float, float]:
    j = np.clip(np.asarray(c) * rng.uniform(0.8, 1.2) + rng.uniform(-0.06, 0.06, 3), 0.05, 0.95)
    return (float(j[0]), float(j[1]), float(j[2]))


def _room_parts(
    rng: np.random.Generator, lx: float, ly: float, h: float, t: float, ceiling: bool
) -> list[Part]:
    """Floor slab under the interior, four walls outside it, the ceiling slab on top."""
    parts = [Part(_box(0, lx, 0, ly, -0.05, 0.0), FLOOR, 0, "floor", _jitter(rng, PALETTE[FLOOR]))]
    walls = {
        "wall_north": _box(-t, lx + t, ly, ly + t, 0, h),
        "wall_south": _box(-t, lx + t, -t, 0, 0, h),
        "wall_east": _box(lx, lx + t, 0, ly, 0, h),
        "wall_west": _box(-t, 0, 0, ly, 0, h),
    }
    for name, mesh in walls.items():
        parts.append(Part(mesh, WALL, 0, name, _jitter(rng, PALETTE[WALL])))
    color = _jitter(rng, PALETTE[CEILING])  # drawn either way: the room must not depend on it
    if ceiling:
        parts.append(Part(_box(0, lx, 0, ly, h, h + 0.05), CEILING, 0, "ceiling", color))
    return parts


def _join(meshes: list[trimesh.Trimesh], colors: np.ndarray | None = None) -> trimesh.Trimesh:
    """One mesh from several, optionally with one RGBA uint8 colour [M, 4] per input mesh."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=False)])
    vc = None if colors is None else np.repeat(colors, np.diff(offsets), axis=0)
    verts = np.concatenate([m.vertices for m in meshes])
    return trimesh.Trimesh(verts, faces, vertex_colors=vc, process=False)


def scene_mesh(room: Room) -> trimesh.Trimesh:
    """The whole scene as one mesh with per-part vertex colours (for gt/mesh.ply)."""
    rgba = np.array([[*(round(255 * c) for c in p.color), 255] for p in room.parts], np.uint8)
    return _join([p.mesh for p in room.parts], rgba)

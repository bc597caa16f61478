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
from dataclasses import dataclass

import numpy as np
import trimesh
from shapely import affinity
from shapely.geometry import Point, Polygon, box

from stages.common.classes import (  # noqa: F401  (re-exported: room.FLOOR etc.)
    BED,
    CABINET,
    CEILING,
    CEILING_NAME,
    CHAIR,
    FLOOR,
    FLOOR_NAME,
    PLANT,
    SOFA,
    TABLE,
    WALL,
)
from stages.common.classes import SYNTH as CLASSES
from stages.common.classes import SYNTH_COLORS as PALETTE
from stages.common.classes import SYNTH_IGNORE as IGNORE  # noqa: F401  (re-exported)
from stages.synth.doors import WALLS, Door, clearance, cut_doors, draw_doors, draw_passages
from stages.synth.furniture import BUILDERS, Built, box_mesh, build_chair, build_table, join_meshes

log = logging.getLogger(__name__)

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
    doors: tuple[Door, ...] = ()  # gaps in the walls, the floor through them: doors, passages
    outline: tuple[tuple[float, float], ...] = ()  # interior corners, counter-clockwise, when
    #                                              not the rectangle [0, Lx] x [0, Ly]
    loops: tuple[tuple[float, float, float, float], ...] = ()  # camera ellipses when several

    @property
    def polygon(self) -> tuple[tuple[float, float], ...]:
        """The interior's corners, counter-clockwise."""
        lx, ly = self.size
        return self.outline or ((0.0, 0.0), (lx, 0.0), (lx, ly), (0.0, ly))

    @property
    def furniture(self) -> tuple[Part, ...]:
        return tuple(p for p in self.parts if p.instance > 0)


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
    mesh = join_meshes(parts)
    mesh.apply_transform(_pose(x, y, yaw))
    return _Placed(cls, mesh, _footprint(ext, x, y, yaw), h)


def _yaw_facing(nx: float, ny: float) -> float:
    """Yaw that turns the local +y (the back) towards the world direction (nx, ny)."""
    return math.atan2(ny, nx) - math.pi / 2


class _Layout:
    """Footprints placed so far, checked against the room, each other and the camera loop."""

    def __init__(
        self,
        size: tuple[float, float],
        ring: Polygon,
        keep_out: list[Polygon],
        inside: Polygon | None = None,  # the interior when not the rectangle
    ) -> None:
        self.inside = (
            box(0.02, 0.02, size[0] - 0.02, size[1] - 0.02)
            if inside is None
            else inside.buffer(-0.02, join_style="mitre")
        )
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
        table = build_table(rng)
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
                chair = build_chair(rng)
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


def build_room(seed: int, ceiling: bool = True, doors: int = 0, passages: int = 0) -> Room:
    """The rectangular room of a seed: size, walls, furniture, `doors` doors and `passages`
    passages (stages/synth/doors.py); stages/synth/shape.py builds the L-shaped rooms on it."""
    rng = np.random.default_rng([seed, 1])
    lx, ly = round(float(rng.uniform(4.0, 7.0)), 3), round(float(rng.uniform(3.5, 6.0)), 3)
    height, wall = round(float(rng.uniform(2.5, 2.8)), 3), round(float(rng.uniform(0.1, 0.15)), 3)
    a, b = max(0.6, lx / 2 - LOOP_WALL), max(0.5, ly / 2 - LOOP_WALL)
    loop = (lx / 2, ly / 2, a, b)
    ring = _ellipse(*loop).exterior.buffer(LOOP_CLEAR)
    gaps = draw_doors(seed, doors, lx, ly)
    if passages:
        free = [w for w in WALLS if all(d.wall != w for d in gaps)]
        spans = [(w, 0.0, lx if w in ("wall_north", "wall_south") else ly) for w in free]
        gaps += draw_passages(seed, passages, spans)
    lay = _Layout((lx, ly), ring, [clearance(d, lx, ly) for d in gaps])
    furnish(rng, lay, (lx, ly))
    parts = _room_parts(rng, lx, ly, height, wall, ceiling)
    parts = cut_doors(parts, gaps, (lx, ly, wall, height)) if gaps else parts
    parts += furniture_parts(rng, lay)
    log.info("room %.2f x %.2f x %.2f m, %d pieces of furniture", lx, ly, height, len(lay.placed))
    return Room((lx, ly), height, wall, tuple(parts), loop, tuple(gaps))


def furnish(rng: np.random.Generator, lay: _Layout, size: tuple[float, float]) -> None:
    """A table group, then a sofa, cabinets, a bed and plants against the walls when they fit."""
    lay.placed += _table_group(rng, lay, size)
    wish = [SOFA, CABINET, BED, PLANT, PLANT, CABINET]
    keep = [
        c for c, p in zip(wish, (0.8, 0.9, 0.5, 0.9, 0.5, 0.4), strict=True) if rng.random() < p
    ]
    for cls in keep:
        placed = _against_wall(rng, lay, size, cls)
        if placed is not None:
            lay.placed.append(placed)


def furniture_parts(rng: np.random.Generator, lay: _Layout) -> list[Part]:
    """The placed furniture as parts, instances 1.. in placing order, jittered colours."""
    counts: dict[int, int] = {}
    out = []
    for i, p in enumerate(lay.placed, start=1):
        counts[p.cls] = counts.get(p.cls, 0) + 1
        name = f"{CLASSES[p.cls]}_{counts[p.cls]}"
        out.append(Part(p.mesh, p.cls, i, name, _jitter(rng, PALETTE[p.cls])))
    return out


def _jitter(rng: np.random.Generator, c: tuple[float, float, float]) -> tuple[float, float, float]:
    j = np.clip(np.asarray(c) * rng.uniform(0.8, 1.2) + rng.uniform(-0.06, 0.06, 3), 0.05, 0.95)
    return (float(j[0]), float(j[1]), float(j[2]))


def _room_parts(
    rng: np.random.Generator, lx: float, ly: float, h: float, t: float, ceiling: bool
) -> list[Part]:
    """Floor slab under the interior, four walls outside it, the ceiling slab on top."""
    parts = [
        Part(box_mesh(0, lx, 0, ly, -0.05, 0.0), FLOOR, 0, FLOOR_NAME, _jitter(rng, PALETTE[FLOOR]))
    ]
    walls = {
        "wall_north": box_mesh(-t, lx + t, ly, ly + t, 0, h),
        "wall_south": box_mesh(-t, lx + t, -t, 0, 0, h),
        "wall_east": box_mesh(lx, lx + t, 0, ly, 0, h),
        "wall_west": box_mesh(-t, 0, 0, ly, 0, h),
    }
    for name, mesh in walls.items():
        parts.append(Part(mesh, WALL, 0, name, _jitter(rng, PALETTE[WALL])))
    color = _jitter(rng, PALETTE[CEILING])  # drawn either way: the room must not depend on it
    if ceiling:
        parts.append(Part(box_mesh(0, lx, 0, ly, h, h + 0.05), CEILING, 0, CEILING_NAME, color))
    return parts


def scene_mesh(room: Room) -> trimesh.Trimesh:
    """The whole scene as one mesh with per-part vertex colours (for gt/mesh.ply)."""
    rgba = np.array([[*(round(255 * c) for c in p.color), 255] for p in room.parts], np.uint8)
    return join_meshes([p.mesh for p in room.parts], rgba)

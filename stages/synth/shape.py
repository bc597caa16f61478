"""An L-shaped procedural room: the seed's rectangle grown by `GROW` with a notch cut from one
corner, six walls round it (`blunf synth --shape L`).

The room is drawn from the seed's own streams: the rectangle's size, height and wall from
(seed, 1) as for the rectangular room, the notch from (seed, 3), doors from (seed, 2); the
furniture is placed as in a rectangular room, inside the L. Walls stand outside the
interior, each an axis-aligned box on its face: a wall along x runs on over the corner
square at each convex corner, a wall along y stops short of the other wall at a concave one,
so that the boxes tile the wall band without overlapping.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import trimesh
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from stages.common.classes import CEILING, CEILING_NAME, FLOOR, FLOOR_NAME, WALL
from stages.common.classes import SYNTH_COLORS as PALETTE
from stages.synth.doors import (
    CORNER,
    WIDTH,
    Bounds,
    Door,
    bounds_mesh,
    depth_clear,
    draw_passages,
    wall_pieces,
)
from stages.synth.room import (
    LOOP_CLEAR,
    Part,
    Room,
    _ellipse,
    _jitter,
    _Layout,
    build_room,
    furnish,
    furniture_parts,
)

log = logging.getLogger(__name__)

GROW = 1.25  # an L room's bounding box is the seed's rectangle grown by this factor
NOTCH = (0.35, 0.5)  # the notch's sides as shares of the bounding box's sides
LOOP_WALL = 1.3  # metres: each arm's camera loop keeps this far from the arm's sides
BEYOND = 1.0  # metres: the wall a door looks onto stands this far past the door's wall
_NORMALS = {(0, -1): "south", (1, 0): "east", (0, 1): "north", (-1, 0): "west"}


@dataclass(frozen=True)
class Face:
    """One wall: its interior face a -> b (room on the left) and the wall's box."""

    name: str
    a: tuple[float, float]
    b: tuple[float, float]
    bounds: Bounds

    @property
    def along_x(self) -> bool:
        return self.a[1] == self.b[1]

    @property
    def normal(self) -> np.ndarray:
        """Outward unit normal (right of the walk)."""
        d = np.subtract(self.b, self.a) / self.length
        return np.array([d[1], -d[0]])

    @property
    def length(self) -> float:
        return float(abs(self.b[0] - self.a[0]) + abs(self.b[1] - self.a[1]))


def faces_of(poly: tuple[tuple[float, float], ...], t: float, h: float) -> list[Face]:
    """The walls, `t` thick and `h` high, of a counter-clockwise axis-aligned outline."""
    p = np.asarray(poly, np.float64)
    n = len(p)
    edge = [p[(i + 1) % n] - p[i] for i in range(n)]

    def convex(i: int) -> bool:  # the corner at vertex i (between edge i-1 and edge i)
        u, v = edge[i - 1], edge[i]
        return bool(u[0] * v[1] - u[1] * v[0] > 0)

    out: list[Face] = []
    seen: dict[str, int] = {}
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        d = np.sign(b - a).astype(int)
        nrm = (int(d[1]), int(-d[0]))
        side = _NORMALS[nrm]
        seen[side] = seen.get(side, 0) + 1
        name = f"wall_{side}" + ("" if seen[side] == 1 else f"_{seen[side]}")
        ends = [(a, convex(i), -1), (b, convex((i + 1) % n), 1)]  # (point, convex, sign along d)
        if d[1] == 0:  # along x: over the corner squares at convex ends
            xs = [float(q[0]) + (s * d[0] * t if c else 0.0) for q, c, s in ends]
            ys = [float(a[1]), float(a[1]) + nrm[1] * t]
        else:  # along y: short of the other wall at concave ends
            ys = [float(q[1]) + (0.0 if c else -s * d[1] * t) for q, c, s in ends]
            xs = [float(a[0]), float(a[0]) + nrm[0] * t]
        bounds = (min(xs), max(xs), min(ys), max(ys), 0.0, h)
        out.append(Face(name, (float(a[0]), float(a[1])), (float(b[0]), float(b[1])), bounds))
    return out


def ell(lx: float, ly: float, notch: tuple[float, float], corner: int) -> tuple:
    """The L's outline (counter-clockwise, from its lowest then leftmost corner), two boxes
    that tile it and the box where its arms meet (x0, x1, y0, y1): [0, lx] x [0, ly] without a
    notch (nx, ny) at corner 0 SW, 1 SE, 2 NE, 3 NW."""
    nx, ny = notch
    x0, x1 = (0.0, nx) if corner in (0, 3) else (lx - nx, lx)
    y0, y1 = (0.0, ny) if corner in (0, 1) else (ly - ny, ly)
    shape = box(0.0, 0.0, lx, ly).difference(box(x0, y0, x1, y1))
    pts = [(round(float(x), 6), round(float(y), 6)) for x, y in shape.exterior.coords[:-1]]
    pts = _ccw_from_low_left(pts)
    strip = (0.0, lx, y1, ly) if y0 == 0.0 else (0.0, lx, 0.0, y0)  # full width
    rest = (x1, lx, y0, y1) if x0 == 0.0 else (0.0, x0, y0, y1)
    # the square where the two arms meet: the full-width strip's rows, the other arm's columns
    meet = (rest[0], rest[1], strip[2], strip[3])
    return tuple(pts), (strip, rest), meet


def _ccw_from_low_left(pts: list) -> list:
    p = np.asarray(pts)
    x, y = p[:, 0], p[:, 1]
    if (x * np.roll(y, -1) - np.roll(x, -1) * y).sum() < 0:
        pts = pts[::-1]
    k = min(range(len(pts)), key=lambda i: (pts[i][1], pts[i][0]))
    pts = pts[k:] + pts[:k]
    # drop collinear points (shapely may keep one where the notch met the box)
    out = []
    for i, q in enumerate(pts):
        a, b = pts[i - 1], pts[(i + 1) % len(pts)]
        if (q[0] - a[0]) * (b[1] - q[1]) - (q[1] - a[1]) * (b[0] - q[0]) != 0:
            out.append(q)
    return out


def arm_loops(lx: float, ly: float, tiles: tuple) -> tuple[tuple[float, float, float, float], ...]:
    """One camera ellipse (cx, cy, a, b) in each arm of the L, as a rectangular room of the
    arm's size has it: the full-width strip, then the full-height arm."""
    strip, rest = tiles
    out = []
    for x0, x1, y0, y1 in (strip, (rest[0], rest[1], 0.0, ly)):
        w, h = x1 - x0, y1 - y0
        a, b = max(0.6, w / 2 - LOOP_WALL), max(0.5, h / 2 - LOOP_WALL)
        out.append((round((x0 + x1) / 2, 6), round((y0 + y1) / 2, 6), round(a, 6), round(b, 6)))
    return tuple(out)


def draw_gaps(seed: int, n: int, faces: list[Face]) -> list[Door]:
    """`n` doors in distinct walls long enough for one (the rectangle's draw_doors' stream)."""
    rng = np.random.default_rng([seed, 2])
    room_for = [f for f in faces if f.length >= 2 * CORNER + WIDTH[1] + 0.2]
    if not 0 <= n <= len(room_for):
        raise ValueError(f"doors must be in 0..{len(room_for)} for this room, got {n}")
    out = []
    for k in rng.permutation(len(room_for))[:n]:
        f = room_for[int(k)]
        lo = _lo(f)
        w = round(float(rng.uniform(*WIDTH)), 3)
        s = round(float(lo + rng.uniform(CORNER, f.length - CORNER - w)), 3)
        out.append(Door(f.name, s, round(s + w, 3)))
    return out


def _concave_pairs(faces: list[Face]) -> list[tuple[str, str]]:
    """The names of the two walls meeting at each concave corner (the notch's)."""
    out = []
    for f, g in zip(faces, faces[1:] + faces[:1], strict=True):
        u, v = np.subtract(f.b, f.a), np.subtract(g.b, g.a)
        if u[0] * v[1] - u[1] * v[0] < 0:  # a right turn walking counter-clockwise
            out.append((f.name, g.name))
    return out


def _lo(f: Face) -> float:
    """Where the face starts along its axis (x along x, y along y)."""
    return min(f.a[0], f.b[0]) if f.along_x else min(f.a[1], f.b[1])


def _span(d: Door, f: Face, depth: float) -> Polygon:
    """The door's span on face f, reaching `depth` along the outward normal (< 0: inwards)."""
    n = f.normal
    if f.along_x:
        y = f.a[1]
        return box(d.start, min(y, y + n[1] * depth), d.end, max(y, y + n[1] * depth))
    x = f.a[0]
    return box(min(x, x + n[0] * depth), d.start, max(x, x + n[0] * depth), d.end)


def _concat(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    out = trimesh.util.concatenate(meshes)
    assert isinstance(out, trimesh.Trimesh)
    return out


def _beyond(d: Door, f: Face, t: float, h: float) -> Bounds:
    """A wall BEYOND metres past the door's wall, facing it, 0.5 m wider on each side (within
    the wall's face): the views see depth through the doorway, as they would in a house."""
    lo, hi = sorted((f.a[0], f.b[0]) if f.along_x else (f.a[1], f.b[1]))
    s0, s1 = max(lo, d.start - 0.5), min(hi, d.end + 0.5)
    n = f.normal
    if f.along_x:
        y = f.a[1] + n[1] * (t + BEYOND)
        return (s0, s1, min(y, y + n[1] * 0.1), max(y, y + n[1] * 0.1), 0.0, h)
    x = f.a[0] + n[0] * (t + BEYOND)
    return (min(x, x + n[0] * 0.1), max(x, x + n[0] * 0.1), s0, s1, 0.0, h)


def build_l_room(seed: int, ceiling: bool = True, doors: int = 0, passages: int = 0) -> Room:
    """The seed's L-shaped room (its rectangle's draws, grown, with a notch), `doors` doors
    and `passages` passages in distinct walls."""
    rng = np.random.default_rng([seed, 1])
    lx, ly = round(float(rng.uniform(4.0, 7.0)), 3), round(float(rng.uniform(3.5, 6.0)), 3)
    height, wall = round(float(rng.uniform(2.5, 2.8)), 3), round(float(rng.uniform(0.1, 0.15)), 3)
    lx, ly = round(lx * GROW, 3), round(ly * GROW, 3)
    shape_rng = np.random.default_rng([seed, 3])
    notch = tuple(round(float(shape_rng.uniform(*NOTCH)) * s, 3) for s in (lx, ly))
    poly, tiles, _ = ell(lx, ly, notch, int(shape_rng.integers(4)))  # type: ignore[arg-type]
    faces = faces_of(poly, wall, height)
    loops = arm_loops(lx, ly, tiles)
    ring = unary_union([_ellipse(*lp).exterior.buffer(LOOP_CLEAR) for lp in loops])
    gaps = draw_gaps(seed, doors, faces)
    if passages:
        taken = {d.wall for d in gaps}
        # not facing a door across the notch (their walls beyond would cross there)
        near = {n for f, g in _concave_pairs(faces) for n, m in ((f, g), (g, f)) if m in taken}
        spans = [(f.name, _lo(f), f.length) for f in faces if f.name not in taken | near]
        gaps += draw_passages(seed, passages, spans)
    by_name = {f.name: f for f in faces}
    keep_out = [_span(d, by_name[d.wall], -depth_clear(d)) for d in gaps]
    lay = _Layout((lx, ly), ring, keep_out, inside=Polygon(poly))
    furnish(rng, lay, (lx, ly))

    floor = [bounds_mesh((*b, -0.05, 0.0)) for b in tiles]
    for d in gaps:
        x0, y0, x1, y1 = _span(d, by_name[d.wall], wall).bounds
        floor.append(bounds_mesh((x0, x1, y0, y1, -0.05, 0.0)))
    parts = [Part(_concat(floor), FLOOR, 0, FLOOR_NAME, _jitter(rng, PALETTE[FLOOR]))]
    for f in faces:
        cut = [d for d in gaps if d.wall == f.name]
        pieces = wall_pieces(f.name, cut, f.bounds, f.along_x) if cut else [f.bounds]
        mesh = _concat([bounds_mesh(b) for b in pieces])
        parts.append(Part(mesh, WALL, 0, f.name, _jitter(rng, PALETTE[WALL])))
    for i, d in enumerate(gaps):  # what a view sees through the door: a wall beyond it
        parts.append(
            Part(
                bounds_mesh(_beyond(d, by_name[d.wall], wall, height)),
                WALL,
                0,
                f"beyond_{i + 1}",
                _jitter(rng, PALETTE[WALL]),
            )
        )
    color = _jitter(rng, PALETTE[CEILING])
    if ceiling:
        top = [bounds_mesh((*b, height, height + 0.05)) for b in tiles]
        parts.append(Part(_concat(top), CEILING, 0, CEILING_NAME, color))
    parts += furniture_parts(rng, lay)
    log.info(
        "L room %.2f x %.2f (notch %.2f x %.2f) x %.2f m, %d pieces of furniture",
        lx,
        ly,
        *notch,
        height,
        len(lay.placed),
    )
    return Room((lx, ly), height, wall, tuple(parts), loops[0], tuple(gaps), poly, loops)


def build_shaped_room(
    seed: int, ceiling: bool = True, doors: int = 0, shape: str = "rect", passages: int = 0
) -> Room:
    """The room of a seed in the given outline: "rect" (room.build_room) or "L"."""
    if shape == "L":
        return build_l_room(seed, ceiling, doors, passages)
    if shape != "rect":
        raise ValueError(f"shape must be rect or L, got {shape!r}")
    return build_room(seed, ceiling, doors, passages)

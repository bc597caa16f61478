"""The floor plan of a procedural home (`blunf synth --rooms N`): rooms on a grid of cells.

The home is a grid of `cols` x `rows` cells, `wall` metres of wall between neighbouring
cells and round the whole. Each cell belongs to one room; a room is one cell, two
neighbouring cells (a long rectangle) or three cells of a 2 x 2 block (an L). A room's
interior is its cells and the wall bands between two of its own cells (never a band's
crossing, so an L's inner corner is square); everything else inside the outer band is wall.
Rooms are numbered in walking order: room k and room k + 1 share a wall, and a door or a
passage joins them; some plans also join the last room to the first (a loop), and the
first room may have a door to the outside. All coordinates are metres, rounded to 1 mm;
the home's interior bounding box starts at the origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from stages.synth.doors import CORNER, LINTEL, PASSAGE, WIDTH
from stages.synth.shape import _ccw_from_low_left

# Room assignments (rows from the south, cells from the west), walk order 0, 1, ...; a plan
# whose last room touches room 0 gets a passage or door there too (the walk's loop).
TEMPLATES: dict[int, tuple[tuple[tuple[int, ...], ...], ...]] = {
    2: (((0, 1),), ((0, 0), (0, 1))),
    3: (((0, 1, 2),), ((0, 1), (0, 2)), ((0, 0, 1), (0, 2, 2))),
    4: (((0, 1), (3, 2)), ((0, 0, 1), (0, 3, 2))),
    5: (((0, 1, 2), (0, 4, 3)), ((0, 0, 1, 2), (0, 4, 4, 3))),
}
CELL_W = (3.4, 4.8)  # a cell's width range (metres)
CELL_D = (3.3, 4.4)  # a cell's depth range (metres); one-row plans draw from ONE_ROW
ONE_ROW = (3.8, 5.2)
PASSAGE_SHARE = 0.35  # chance that a join long enough for a passage is one
ENTRANCE = 0.6  # chance that room 0 has a door to the outside


@dataclass(frozen=True)
class Gap:
    """A door or passage: a gap through one wall band, the floor running through it."""

    rooms: tuple[int, ...]  # (i, j): from room i into room j; (i,): a door to the outside
    along_x: bool  # the wall runs along x (the gap's start/end are x), else along y
    band: tuple[float, float]  # the wall band across: (y0, y1) when along_x, else (x0, x1)
    start: float
    end: float
    normal: tuple[int, int]  # unit step from rooms[0] through the gap
    kind: str = "door"
    top: float | None = None  # a passage's lintel underside (None: full height)

    @property
    def width(self) -> float:
        return self.end - self.start

    @property
    def rect(self) -> tuple[float, float, float, float]:
        """The gap's floor (x0, x1, y0, y1)."""
        if self.along_x:
            return (self.start, self.end, *self.band)
        return (*self.band, self.start, self.end)

    @property
    def centre(self) -> np.ndarray:
        x0, x1, y0, y1 = self.rect
        return np.array([(x0 + x1) / 2, (y0 + y1) / 2])


@dataclass(frozen=True)
class HomePlan:
    xs: tuple[float, ...]  # each column's west edge
    widths: tuple[float, ...]
    ys: tuple[float, ...]  # each row's south edge
    depths: tuple[float, ...]
    cells: tuple[tuple[int, ...], ...]  # [row][col] -> room
    wall: float
    height: float
    gaps: tuple[Gap, ...]  # walk order: (0, 1), (1, 2), ..., then the loop's and the entrance

    @property
    def n_rooms(self) -> int:
        return 1 + max(max(r) for r in self.cells)

    @property
    def size(self) -> tuple[float, float]:
        return (
            round(self.xs[-1] + self.widths[-1], 6),
            round(self.ys[-1] + self.depths[-1], 6),
        )

    def cell_box(self, c: int, r: int) -> tuple[float, float, float, float]:
        x, y = self.xs[c], self.ys[r]
        return (x, round(x + self.widths[c], 6), y, round(y + self.depths[r], 6))

    def cells_of(self, k: int) -> list[tuple[int, int]]:
        """(col, row) of room k's cells, row by row."""
        return [(c, r) for r, row in enumerate(self.cells) for c, v in enumerate(row) if v == k]

    def boxes_of(self, k: int) -> list[tuple[float, float, float, float]]:
        """Room k's interior as boxes (x0, x1, y0, y1): its cells and its own bands."""
        cells = self.cells_of(k)
        out = [self.cell_box(c, r) for c, r in cells]
        for c, r in cells:
            x0, x1, y0, y1 = self.cell_box(c, r)
            if (c + 1, r) in cells:
                out.append((x1, self.xs[c + 1], y0, y1))
            if (c, r + 1) in cells:
                out.append((x0, x1, y1, self.ys[r + 1]))
        return out

    def polygon(self, k: int) -> tuple[tuple[float, float], ...]:
        """Room k's interior outline, counter-clockwise from its lowest then leftmost corner."""
        shape = unary_union([box(x0, y0, x1, y1) for x0, x1, y0, y1 in self.boxes_of(k)])
        assert isinstance(shape, Polygon)
        pts = [(round(float(x), 6), round(float(y), 6)) for x, y in shape.exterior.coords[:-1]]
        return tuple(_ccw_from_low_left(pts))

    def joins(self, i: int, j: int) -> list[tuple[tuple[int, int], tuple[int, int]]]:
        """Pairs of neighbouring cells (one of room i, one of room j)."""
        out = []
        for c, r in self.cells_of(i):
            for dc, dr in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                cc, rr = c + dc, r + dr
                if 0 <= rr < len(self.cells) and 0 <= cc < len(self.cells[0]):
                    if self.cells[rr][cc] == j:
                        out.append(((c, r), (cc, rr)))
        return out


def _edges(start: float, sizes: list[float], wall: float) -> list[float]:
    out, x = [], start
    for s in sizes:
        out.append(round(x, 6))
        x = round(x + s + wall, 6)
    return out


def draw_plan(seed: int, n: int) -> HomePlan:
    """The home of a seed with n (2..5) rooms: template, cell sizes, doors and passages."""
    rng = np.random.default_rng([seed, 10, n])
    cells = TEMPLATES[n][int(rng.integers(len(TEMPLATES[n])))]
    rows, cols = len(cells), len(cells[0])
    height = round(float(rng.uniform(2.5, 2.8)), 3)
    wall = round(float(rng.uniform(0.1, 0.15)), 3)
    widths = [round(float(rng.uniform(*CELL_W)), 3) for _ in range(cols)]
    depths = [round(float(rng.uniform(*(CELL_D if rows > 1 else ONE_ROW))), 3) for _ in range(rows)]
    plan = HomePlan(
        tuple(_edges(0.0, widths, wall)),
        tuple(widths),
        tuple(_edges(0.0, depths, wall)),
        tuple(depths),
        cells,
        wall,
        height,
        (),
    )
    pairs = [(k, k + 1) for k in range(n - 1)]
    if n > 2 and plan.joins(n - 1, 0):
        pairs.append((n - 1, 0))
    gaps = [_join(rng, plan, i, j) for i, j in pairs]
    if rng.random() < ENTRANCE:
        gaps.append(_entrance(rng, plan))
    return HomePlan(
        plan.xs, plan.widths, plan.ys, plan.depths, plan.cells, wall, height, tuple(gaps)
    )


def _gap_on(
    rng: np.random.Generator, plan: HomePlan, a: tuple[int, int], step: tuple[int, int]
) -> tuple[bool, tuple[float, float], float, float]:
    """(along_x, band, lo, hi) of the wall band on cell a's side `step` (lo..hi: the span a
    gap may take along it, CORNER clear of the cell's corners)."""
    x0, x1, y0, y1 = plan.cell_box(*a)
    t = plan.wall
    if step[0] == 0:  # a wall along x
        band = (y1, round(y1 + t, 6)) if step[1] > 0 else (round(y0 - t, 6), y0)
        return True, band, x0 + CORNER, x1 - CORNER
    band = (x1, round(x1 + t, 6)) if step[0] > 0 else (round(x0 - t, 6), x0)
    return False, band, y0 + CORNER, y1 - CORNER


def _cut(
    rng: np.random.Generator, lo: float, hi: float, kind: str
) -> tuple[float, float, float | None]:
    w = round(float(rng.uniform(*(WIDTH if kind == "door" else PASSAGE))), 3)
    s = round(float(rng.uniform(lo, hi - w)), 3)
    top = None
    if kind == "passage" and rng.random() < 0.5:
        top = round(float(rng.uniform(*LINTEL)), 3)
    return s, round(s + w, 3), top


def _join(rng: np.random.Generator, plan: HomePlan, i: int, j: int) -> Gap:
    """A door or passage between rooms i and j, on one of their shared cell sides."""
    pairs = plan.joins(i, j)
    a, b = pairs[int(rng.integers(len(pairs)))]
    step = (b[0] - a[0], b[1] - a[1])
    along_x, band, lo, hi = _gap_on(rng, plan, a, step)
    kind = "passage" if hi - lo >= PASSAGE[1] + 0.2 and rng.random() < PASSAGE_SHARE else "door"
    s, e, top = _cut(rng, lo, hi, kind)
    return Gap((i, j), along_x, band, s, e, step, kind, top)


def _entrance(rng: np.random.Generator, plan: HomePlan) -> Gap:
    """A door from room 0 to the outside, in one of its cells' outer sides."""
    rows, cols = len(plan.cells), len(plan.cells[0])
    sides = []
    for c, r in plan.cells_of(0):
        for dc, dr in ((0, -1), (1, 0), (0, 1), (-1, 0)):
            if not (0 <= c + dc < cols and 0 <= r + dr < rows):
                sides.append(((c, r), (dc, dr)))
    a, step = sides[int(rng.integers(len(sides)))]
    along_x, band, lo, hi = _gap_on(rng, plan, a, step)
    s, e, _ = _cut(rng, lo, hi, "door")
    return Gap((0,), along_x, band, s, e, step)


def interior(plan: HomePlan) -> Polygon:
    """The rooms' union with the gaps' floors: where a person can stand."""
    shapes = [
        box(x0, y0, x1, y1) for k in range(plan.n_rooms) for x0, x1, y0, y1 in plan.boxes_of(k)
    ] + [box(g.rect[0], g.rect[2], g.rect[1], g.rect[3]) for g in plan.gaps]
    return unary_union(shapes)

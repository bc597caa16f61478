"""The camera's walk through a procedural home, as a person films it room after room.

The walk starts at room 0's first spot and looks round there, goes to the room's other
spots and looks round at each, then walks through the door or passage into the next room,
and so on to the last room. It ends back in an earlier room (through the passage to room 0
when the plan has that loop, else back into the last room but one) and looks round once
more where it first did there, so that the walk closes a loop. To look round it steps once
round a small circle about the spot, looking outwards (a full turn with parallax: SfM
registers no view of a turn on the spot that sees new walls). In a room it moves from cell
to cell through cell centres (so it keeps off the walls and round an L's inner corner),
turning while it walks, and lines up with a gap STEP_IN metres before it. The views are
spaced evenly along the walk, a radian of turning counting as R_TURN metres; each looks
along its heading, CAM_Z high and pitched down by PITCH degrees, both varying slowly, with
a small seeded jitter.
"""

from __future__ import annotations

import math

import numpy as np

from stages.synth.home_plan import Gap, HomePlan
from stages.synth.render import look

R_TURN = 0.8  # metres of walk a radian of turning counts for when spacing the views
STEP_IN = 1.0  # metres: the walk lines up with a gap this far before it and goes as far past
CAM_Z = (1.37, 1.53)  # camera height range (metres): median 1.45, as the single room's
# downward pitch range (degrees): the 7-Scenes kitchen's and Replica office0's views look down
# a median 27.6 and 27.3 degrees (quartiles 23.5-30.6, 22.1-38.4). The walk's earlier 8-14
# degrees saw the floor only from 2 m on (its lowest rays 37 degrees down from 1.45 m), so
# the floor round each spot where the walk looks round, and what stood there, went unseen:
# the 3-room home's sensor plan 84.4 -> 89.6 fwIoU (docs/figures.md#synth-home-pitch)
PITCH = (20.0, 35.0)
SPLIT = 4.0  # metres: a one-cell room this long or longer gets two spots along its length
RING = 0.45  # metres: the circle the walk steps round where it looks round
RING_STEPS = 36  # keyframes round that circle
TURN_IN = 0.6  # metres: the walk turns to a new heading over this much of the segment

Cell = tuple[int, int]


def spots(plan: HomePlan, k: int) -> list[tuple[Cell, np.ndarray]]:
    """Where the walk looks round in room k: a one-cell room's centre (two spots along its
    length when it is long), the centres of a two-cell room's cells, an L's two arms' ends."""
    cells = plan.cells_of(k)
    if len(cells) == 1:
        x0, x1, y0, y1 = plan.cell_box(*cells[0])
        c = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
        long_x = x1 - x0 >= y1 - y0
        length = max(x1 - x0, y1 - y0)
        if length < SPLIT:
            return [(cells[0], c)]
        d = np.array([0.2 * length, 0.0] if long_x else [0.0, 0.2 * length])
        return [(cells[0], c - d), (cells[0], c + d)]
    ends = [a for a in cells if len(_neighbours(a, cells)) == 1] if len(cells) == 3 else cells
    return [(a, _centre(plan, a)) for a in ends]


def _centre(plan: HomePlan, a: Cell) -> np.ndarray:
    x0, x1, y0, y1 = plan.cell_box(*a)
    return np.array([(x0 + x1) / 2, (y0 + y1) / 2])


def _neighbours(a: Cell, cells: list[Cell]) -> list[Cell]:
    return [b for b in cells if abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1]


def _cell_path(a: Cell, b: Cell, cells: list[Cell]) -> list[Cell]:
    """The cells from a to b (both included) through neighbouring cells of one room."""
    prev: dict[Cell, Cell | None] = {a: None}
    queue = [a]
    while queue:
        c = queue.pop(0)
        for d in _neighbours(c, cells):
            if d not in prev:
                prev[d] = c
                queue.append(d)
    out: list[Cell] = [b]
    while prev[out[-1]] is not None:
        out.append(prev[out[-1]])  # type: ignore[arg-type]
    return out[::-1]


def _cell_at(plan: HomePlan, p: np.ndarray) -> Cell:
    for r, _ in enumerate(plan.cells):
        for c, _ in enumerate(plan.cells[0]):
            x0, x1, y0, y1 = plan.cell_box(c, r)
            if x0 <= p[0] <= x1 and y0 <= p[1] <= y1:
                return (c, r)
    raise ValueError(f"point {p} is in no cell")


class _Walk:
    def __init__(self, plan: HomePlan) -> None:
        self.plan = plan
        self.points: list[tuple[np.ndarray, bool]] = []  # (x, y), turn round there
        self.cell: Cell = (0, 0)

    def go(self, cell: Cell, p: np.ndarray, turn: bool = False) -> None:
        """To p in `cell` of the current room, through the centres of the cells between."""
        if self.points:
            room = self.plan.cells[self.cell[1]][self.cell[0]]
            cells = self.plan.cells_of(room)
            for c in _cell_path(self.cell, cell, cells)[1:-1]:
                self.points.append((_centre(self.plan, c), False))
        self.points.append((p, turn))
        self.cell = cell

    def cross(self, g: Gap, forward: bool = True) -> None:
        """Line up with the gap STEP_IN before it, walk through to STEP_IN past it."""
        n = np.asarray(g.normal, np.float64) * (1.0 if forward else -1.0)
        reach = self.plan.wall / 2 + STEP_IN
        before, after = g.centre - n * reach, g.centre + n * reach
        self.go(_cell_at(self.plan, before), before)
        self.points.append((after, False))
        self.cell = _cell_at(self.plan, after)


def route(plan: HomePlan) -> list[tuple[np.ndarray, bool]]:
    """The walk's points (x, y) in order, each with whether the walk turns round there."""
    n = plan.n_rooms
    by_rooms = {g.rooms: g for g in plan.gaps}
    w = _Walk(plan)
    first = spots(plan, 0)[0]
    w.go(*first, turn=True)
    for k in range(n):
        todo = spots(plan, k)[1 if k == 0 else 0 :]
        while todo:
            here = w.points[-1][0]
            todo.sort(key=lambda s: float(np.linalg.norm(s[1] - here)))
            w.go(*todo.pop(0), turn=True)
        if k < n - 1:
            w.cross(by_rooms[(k, k + 1)])
    if (n - 1, 0) in by_rooms:
        w.cross(by_rooms[(n - 1, 0)])
        w.go(*first, turn=True)
    else:
        w.cross(by_rooms[(n - 2, n - 1)], forward=False)
        w.go(*spots(plan, n - 2)[0], turn=True)
    return w.points


def keyframes(points: list[tuple[np.ndarray, bool]]) -> np.ndarray:
    """(x, y, yaw) [K, 3] of the walk. Between points it walks straight, turning to its new
    heading over the segment's first TURN_IN metres; where it looks round it steps once
    round a circle of RING metres about the point, counter-clockwise, looking outwards
    (starting and ending on the circle where its heading meets it). Never a turn on the
    spot: every view moves, so that the photos see parallax. Yaw is continuous."""
    pts = [p for p, _ in points]
    turns = [t for _, t in points]
    heads = [math.atan2(*(q - p)[::-1]) for p, q in zip(pts, pts[1:], strict=False)]
    heads = [heads[0], *heads, heads[-1]]  # heading into and out of each point
    keys: list[tuple[float, float, float]] = []
    yaw = heads[0]
    for i, p in enumerate(pts):
        h_in = heads[i]
        yaw += (h_in - yaw + math.pi) % (2 * math.pi) - math.pi
        if i > 0:  # the segment into p: turn over its first TURN_IN metres
            a = np.asarray(keys[-1][:2])
            end = p + RING * np.array([math.cos(h_in), math.sin(h_in)]) if turns[i] else p
            d = float(np.linalg.norm(end - a))
            mid = a + (end - a) * min(TURN_IN, d / 2) / max(d, 1e-12)
            keys += [(*mid, yaw), (*end, yaw)]
        elif turns[i]:
            keys.append((*(p + RING * np.array([math.cos(yaw), math.sin(yaw)])), yaw))
        else:
            keys.append((*p, yaw))
        if turns[i]:
            for k in range(1, RING_STEPS + 1):
                phi = yaw + 2 * math.pi * k / RING_STEPS
                keys.append((*(p + RING * np.array([math.cos(phi), math.sin(phi)])), phi))
            yaw += 2 * math.pi
    return np.array(keys, np.float64)


def sample(keys: np.ndarray, views: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y, yaw) [views, 3] spaced evenly along the keyframes, and the walk's length
    there [views] (metres, a radian counting R_TURN)."""
    step = np.hypot(*np.diff(keys[:, :2], axis=0).T) + R_TURN * np.abs(np.diff(keys[:, 2]))
    cum = np.concatenate([[0.0], np.cumsum(step)])
    s = cum[-1] * np.arange(views) / max(views - 1, 1)
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(keys) - 2)
    f = np.where(step[i] > 0, (s - cum[i]) / np.where(step[i] > 0, step[i], 1.0), 0.0)
    f = np.clip(f, 0.0, 1.0)[:, None]
    return keys[i] * (1 - f) + keys[i + 1] * f, s


def home_path(plan: HomePlan, views: int, seed: int) -> np.ndarray:
    """Camera-to-world poses [views, 4, 4] along the walk (OpenCV axes)."""
    rng = np.random.default_rng([seed, 13, views])
    ph = rng.uniform(0, 2 * np.pi, 2)
    xyyaw, s = sample(keyframes(route(plan)), views)
    z_mid, z_amp = (CAM_Z[0] + CAM_Z[1]) / 2, (CAM_Z[1] - CAM_Z[0]) / 2 - 0.01
    p_mid, p_amp = (PITCH[0] + PITCH[1]) / 2, (PITCH[1] - PITCH[0]) / 2
    poses = []
    for (x, y, yaw), sk in zip(xyyaw, s, strict=True):
        z = z_mid + z_amp * math.sin(2 * math.pi * sk / 7.0 + ph[0]) + rng.uniform(-0.01, 0.01)
        pitch = p_mid + p_amp * math.sin(2 * math.pi * sk / 5.0 + ph[1])
        yaw_j = yaw + math.radians(rng.uniform(-1.0, 1.0))
        poses.append(look(np.array([x, y, z]), yaw_j, -math.radians(pitch)))
    return np.stack(poses)

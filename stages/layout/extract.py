"""Rooms, walls and openings read off the blueprint raster.

The wall cells are closed along the room's two directions over gaps up to `max_opening`
(the wall line runs through a doorway); each closed space left is a room (split further where
it narrows to a door: rooms.py), its outline traced on cell edges (skimage's marching
squares), simplified, each edge snapped to the room's directions and refitted on the traced
points, short edges merged away and neighbouring edges intersected at the corners. A wall is
an outline edge (its interior face) with the thickness of the wall cells behind it; an
opening is floor inside the closed wall line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import approximate_polygon, find_contours

from stages.common.blueprint import Blueprint, Grid
from stages.layout.config import LayoutConfig

PASSAGE_FLOOR = 0.4  # share of a passage's gap that is floor (the rest: unseen beyond)
PASSAGE_BESIDE = 0.3  # share of wall cells beside a passage's gap, across, on either side


@dataclass(frozen=True)
class Frame:
    """The blueprint resampled on a grid turned by `angle` (rad): rows and columns run along
    the room's two directions. World xy = rot(angle) @ frame xy."""

    labels: np.ndarray  # uint8 [H, W]
    grid: Grid  # in the turned frame
    angle: float

    def to_world(self, xy: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.angle), math.sin(self.angle)
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]], axis=1)

    def xy(self, rc: np.ndarray) -> np.ndarray:
        """Frame xy of fractional (row, col) positions [N, 2] (cell centres at integers)."""
        rc = np.asarray(rc, np.float64).reshape(-1, 2)
        (ox, oy), h = self.grid.origin, self.grid.shape[0]
        return np.stack(
            [ox + (rc[:, 1] + 0.5) * self.grid.cell, oy + (h - rc[:, 0] - 0.5) * self.grid.cell], 1
        )


def class_id(bp: Blueprint, name: str) -> int | None:
    ids = [k for k, v in bp.classes.items() if v == name]
    return ids[0] if ids else None


def dominant_angle(mask: np.ndarray) -> float:
    """The direction (rad, in [-pi/4, pi/4)) the mask's edges run along, modulo 90 degrees."""
    f = ndi.gaussian_filter(mask.astype(np.float64), 1.0)
    gy, gx = ndi.sobel(f, 0), ndi.sobel(f, 1)
    mag = np.hypot(gx, gy)
    keep = mag > 0.1 * mag.max() if mag.max() > 0 else mag > 0
    if not keep.any():
        return 0.0
    ang = np.arctan2(-gy[keep], gx[keep])  # rows grow downwards: y = -row
    # angles modulo 90 degrees as a doubled-doubled circular mean (4 theta)
    z = (mag[keep] * np.exp(4j * ang)).sum()
    return float(np.angle(z) / 4)


def frame_of(bp: Blueprint, angle: float) -> Frame:
    """The blueprint on a grid turned by `angle` (nearest cell; identity when angle is ~0)."""
    if abs(angle) < math.radians(0.5):
        return Frame(bp.labels, bp.grid, 0.0)
    (ox, oy), cell, (h, w) = bp.grid.origin, bp.grid.cell, bp.grid.shape
    corners = np.array(
        [[ox, oy], [ox + w * cell, oy], [ox, oy + h * cell], [ox + w * cell, oy + h * cell]]
    )
    c, s = math.cos(angle), math.sin(angle)
    fr = corners @ np.array([[c, -s], [s, c]])  # world -> frame: rot(-angle)
    grid = Grid.covering(fr.min(0), fr.max(0), cell)
    tmp = Frame(np.zeros(grid.shape, np.uint8), grid, angle)
    world = tmp.to_world(grid.centers().reshape(-1, 2))
    return Frame(bp.sample(world).reshape(grid.shape), grid, angle)


def _gap_pieces(padded: np.ndarray, n: int, run: int, across: int):
    """The gaps of up to n cells between wall runs of at least `run` cells in `padded` (the
    wall, padded by n + 1), along rows (axis 0) and along columns (axis 1): yields (axis,
    slice, piece [bool within the slice]) for each piece between 3 and `across` cells across
    its direction."""
    for axis, gap, keep, join in (
        (0, np.ones((1, n + 1), bool), np.ones((1, run), bool), np.ones((9, 1), bool)),
        (1, np.ones((n + 1, 1), bool), np.ones((run, 1), bool), np.ones((1, 9), bool)),
    ):
        # runs one cell thicker across, so that a ragged band's rows still meet over a gap
        thick = np.ones((3, 1) if axis == 0 else (1, 3), bool)
        runs = ndi.binary_dilation(ndi.binary_opening(padded, keep), thick)
        fill = ndi.binary_closing(runs, gap) & ~runs
        # pieces a few cells apart across are one (a ragged edge fills in strips)
        lab, _ = ndi.label(ndi.binary_dilation(fill, join))
        for i, sl in enumerate(ndi.find_objects(lab), start=1):
            if 3 + 8 <= sl[axis].stop - sl[axis].start <= across + 8:  # a wall is > 2 cells
                yield axis, sl, (lab[sl] == i) & fill[sl]


def close_lines(wall: np.ndarray, n: int, run: int, across: int) -> np.ndarray:
    """Wall cells with gaps up to n cells filled between wall runs of at least `run` cells
    along rows and along columns (a doorway between two stretches of wall). Stray wall cells
    inside a room make no run; a filled piece wider than `across` cells across its direction
    is no doorway (wall-labelled clutter facing a wall), nor one under 3 cells (the ragged
    edge of such clutter), and stays open."""
    p = n + 1
    padded = np.pad(wall, p)
    out = padded.copy()
    for _, sl, piece in _gap_pieces(padded, n, run, across):
        out[sl] |= piece
    return out[p:-p, p:-p]


def close_passages(
    wall: np.ndarray, floor: np.ndarray, n: int, run: int, across: int
) -> np.ndarray:
    """The gaps of up to n cells in a wall line that the floor runs through (a passage wider
    than close_lines' doorways): filled between wall runs of at least `run` cells as there,
    and kept where it is at least 4 cells across, at least PASSAGE_FLOOR of it is floor and
    the cells beside it across are no wall (at most PASSAGE_BESIDE of them on either side).
    A strip along a ragged wall face, which the wider closing also fills, is thinner or has
    the wall's band beside it; a passage has the room on one side and what lies beyond on
    the other."""
    p = n + 1
    padded, fl = np.pad(wall, p), np.pad(floor, p)
    out = np.zeros_like(padded)
    for axis, sl, piece in _gap_pieces(padded, n, run, across):
        if piece.any(1 - axis).sum() < 4 or fl[sl][piece].mean() < PASSAGE_FLOOR:
            continue  # a strip under 4 cells across is a ragged face's, not a wall's gap
        lines = np.nonzero(piece.any(axis))[0]  # positions along the wall line
        off = sl[1 - axis].start
        lo, hi = sl[axis].start - 1, sl[axis].stop
        idx = lines + off
        beside = [
            padded[lo, idx] if axis == 0 else padded[idx, lo],
            padded[hi, idx] if axis == 0 else padded[idx, hi],
        ]
        if max(b.mean() for b in beside) <= PASSAGE_BESIDE:
            out[sl] |= piece
    return out[p:-p, p:-p]


@dataclass
class Line:
    p: np.ndarray  # a point on the line (frame xy)
    d: np.ndarray  # unit direction (the outline's walking direction)
    weight: float  # support length (metres)
    snapped: bool = True  # along one of the room's two directions
    # the traced lines merged into this one: (a point on each, its support); () = itself
    parts: tuple[tuple[np.ndarray, float], ...] = ()

    def pieces(self) -> tuple[tuple[np.ndarray, float], ...]:
        return self.parts or ((self.p, self.weight),)


def intersect(a: Line, b: Line, tol: float = 1e-6) -> np.ndarray | None:
    """Where lines a and b meet [2]; None when they are parallel within `tol` (the
    determinant of their directions: the sine of the angle between them)."""
    m = np.array([a.d, -b.d]).T
    if abs(np.linalg.det(m)) < tol:
        return None
    t = np.linalg.solve(m, b.p - a.p)
    return a.p + t[0] * a.d


def _corners(lines: list[Line]) -> np.ndarray:
    """Where each line meets the one before it [N, 2] (neighbours are never parallel here:
    those were merged; a pair that still is meets halfway between their points)."""
    out = []
    for i in range(len(lines)):
        c = intersect(lines[i - 1], lines[i])
        out.append((lines[i - 1].p + lines[i].p) / 2 if c is None else c)
    return np.array(out)


def _parallel(a: Line, b: Line) -> bool:
    return abs(a.d[0] * b.d[1] - a.d[1] * b.d[0]) < math.sin(math.radians(3))


def _merge(a: Line, b: Line, step: float) -> Line:
    """One line for two nearly parallel ones, from all the traced lines merged into them:
    the offset along the normal best supported within `step` (the support-weighted mean of
    the lines within `step` of it). A doorway's bump or a shallow alcove, left when the short
    edges round it went, is not the wall's face: the face's pieces on both sides of it
    together outweigh it, whichever side was merged first."""
    n = np.array([-a.d[1], a.d[0]])
    parts = a.pieces() + b.pieces()
    off = np.array([p @ n for p, _ in parts])
    w = np.array([wt for _, wt in parts])
    near = np.abs(off[:, None] - off[None, :]) <= step  # [P, P]
    best = near[int(np.argmax(near @ w))]
    o = float((w[best] * off[best]).sum() / w[best].sum())
    return Line(a.p + (o - a.p @ n) * n, a.d, a.weight + b.weight, a.snapped and b.snapped, parts)


def _axis(d: np.ndarray, snap_deg: float) -> np.ndarray | None:
    """The frame's axis direction nearest d when within snap_deg of it, else None."""
    ang = math.degrees(math.atan2(d[1], d[0]))
    if min(ang % 90, 90 - ang % 90) > snap_deg:
        return None
    return np.array([[1, 0], [0, 1], [-1, 0], [0, -1]][round(ang / 90) % 4], np.float64)


def _fit(a: np.ndarray, b: np.ndarray, pts: np.ndarray, cfg: LayoutConfig, cell: float) -> Line:
    """The line of the edge a->b, snapped to the frame's axes when near them, refitted on the
    traced points along its inner 80 %. A free edge whose refitted direction lies near an
    axis is snapped too: a short edge of a ragged face (furniture against the wall) leans
    more than the face its points lie along."""
    d = b - a
    length = float(np.linalg.norm(d))
    d = d / length
    axis = _axis(d, cfg.snap_deg)
    if axis is not None:
        d = axis
    n = np.array([-d[1], d[0]])
    t = (pts - a) @ d
    near = (
        (np.abs((pts - a) @ n) < max(2 * cfg.tolerance, 2 * cell))
        & (t > 0.1 * length)
        & (t < 0.9 * length)
    )
    sel = pts[near]
    if len(sel) < 2:
        return Line(a.astype(np.float64), d, length, snapped=axis is not None)
    if axis is None:
        c = sel.mean(0)
        u = np.linalg.svd(sel - c)[2][0]
        u = u if u @ d > 0 else -u
        axis = _axis(u, cfg.snap_deg)
        if axis is None:
            return Line(c, u, length, snapped=False)
        d, n = axis, np.array([-axis[1], axis[0]])
    off = float(np.median(sel @ n))
    return Line(a + (off - a @ n) * n, d, length)


def outline(mask: np.ndarray, fr: Frame, cfg: LayoutConfig) -> np.ndarray | None:
    """The room's corners (frame xy, counter-clockwise) from its cell mask."""
    cs = find_contours(np.pad(mask, 1).astype(np.float64), 0.5)
    if not cs:
        return None
    c = max(cs, key=len) - 1.0  # back to unpadded (row, col)
    pts = fr.xy(c)
    cell = fr.grid.cell
    simple = approximate_polygon(pts, cfg.tolerance)
    if len(simple) > 1 and np.allclose(simple[0], simple[-1]):
        simple = simple[:-1]
    lines = [
        _fit(simple[i], simple[(i + 1) % len(simple)], pts, cfg, cell) for i in range(len(simple))
    ]
    while len(lines) >= 3:
        # neighbouring parallel lines become one
        for i in range(len(lines)):
            j = (i + 1) % len(lines)
            if len(lines) > 3 and _parallel(lines[i], lines[j]):
                lines[i] = _merge(lines[i], lines[j], 2 * cfg.tolerance)
                del lines[j]
                break
        else:
            corners = _corners(lines)
            lens = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
            # a short edge, or an edge off the room's directions too short to be believed:
            # such an edge counts the traced length behind it, not how far its corners lie
            # apart (a short slanted piece of a ragged face meets a wall far off)
            free = ~np.array([ln.snapped for ln in lines])
            short = np.where(free, cfg.min_free_wall, cfg.min_wall)
            lens[free] = np.minimum(lens[free], [ln.weight for ln in lines if not ln.snapped])
            k = int(np.argmin(lens - short))
            if lens[k] >= short[k] or len(lines) <= 3:
                break
            del lines[k]
    if len(lines) < 3:
        return None
    poly = _corners(lines)
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())
    return poly if area > 0 else poly[::-1]

"""The architectural plan's shapes and its picture, shared by the layout stage (plan.svg,
plan.dxf) and the export stage (blueprint.png): the walls as one polygon, dimension lines, and
the blueprint's class colours with the walls, openings, objects and lengths drawn over them."""

from __future__ import annotations

import math

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from shapely import make_valid, union_all
from shapely.geometry import Polygon

from stages.common.blueprint import Grid

PAD_M = 0.8  # metres of paper round the walls (dimension lines live there)
DIM_OFF = 0.35  # metres: a dimension line's distance outside the wall's outer face
GRID_M = 1e-4  # metres: the precision grid of the wall overlay


def area_text(room: dict) -> str:
    """A room's area as drawn: "12.30 m2", "12.30 m2, continues" when an inferred wall closes
    it (the room goes on beyond what the views saw)."""
    return f"{room['area']:.2f} m2" + (", continues" if room.get("continues") else "")


def dashes(a: np.ndarray, b: np.ndarray, on: float, off: float) -> list[np.ndarray]:
    """The dashes [2, 2] of a dashed line a -> b (any units): `on` long, `off` apart."""
    length = float(np.linalg.norm(b - a))
    if length <= 0:
        return []
    d = (b - a) / length
    out, t = [], 0.0
    while t < length:
        out.append(np.array([a + d * t, a + d * min(length, t + on)]))
        t += on + off
    return out


def _reach(d: np.ndarray, v: dict) -> float:
    """How far a wall along d is lengthened at its end next to wall v: v's thickness, 0
    when v runs along the same line."""
    e = np.asarray(v["end"], np.float64) - np.asarray(v["start"], np.float64)
    e = e / max(float(np.linalg.norm(e)), 1e-12)
    return 0.0 if abs(float(d[0] * e[1] - d[1] * e[0])) < 0.05 else float(v["thickness"])


def wall_shapes(plan: dict, seen: bool | None = None) -> Polygon:
    """The walls as one (multi)polygon: each wall a band from its face outwards by its
    thickness, lengthened at both ends by its neighbours' thickness, openings cut out.
    seen True / False: only the seen / the inferred walls (`"seen"` absent: seen)."""
    bands, cuts = [], []
    walls = plan["walls"]
    for w in walls:
        if seen is not None and bool(w.get("seen", True)) != seen:
            continue
        a, b, t = np.asarray(w["start"]), np.asarray(w["end"]), float(w["thickness"])
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([d[1], -d[0]])
        same = [v for v in walls if v["room"] == w["room"]]
        k = same.index(w)
        # lengthened by the neighbours round a corner; a piece of the same face (the seen and
        # the inferred pieces of one wall) meets its neighbour end to end
        tp, tn = (_reach(d, same[i]) for i in (k - 1, (k + 1) % len(same)))
        a2, b2 = a - d * tp, b + d * tn
        bands.append(Polygon([a2, b2, b2 + n * t, a2 + n * t]))
    for o in plan.get("openings", []):
        w = walls[o["wall"]]
        p, q = np.asarray(o["start"]), np.asarray(o["end"])
        d = np.asarray(w["end"]) - np.asarray(w["start"])
        d = d / np.linalg.norm(d)
        n = np.array([d[1], -d[0]])
        t = float(w["thickness"]) + 0.01
        cuts.append(Polygon([p - n * 0.01, q - n * 0.01, q + n * t, p + n * t]))
    # overlay on a 0.1 mm grid: GEOS's floating overlay fails on near-coincident edges
    # ("non-noded intersection") that degenerate plans give; the fixed grid never does
    g = GRID_M
    shape = union_all([make_valid(b) for b in bands], grid_size=g)
    rooms = union_all([make_valid(Polygon(r["polygon"])) for r in plan["rooms"]], grid_size=g)
    cut = union_all(cuts, grid_size=g)
    return shape.difference(rooms, grid_size=g).difference(cut, grid_size=g)


def dimension(w: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A wall's dimension line (start, end) outside it and the text position (world)."""
    a, b = np.asarray(w["start"]), np.asarray(w["end"])
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([d[1], -d[0]])
    off = n * (float(w["thickness"]) + DIM_OFF)
    return a + off, b + off, (a + b) / 2 + off + n * 0.12


def overlay(rgb: np.ndarray, grid: Grid, plan: dict, long_px: int = 1400) -> Image.Image:
    """rgb uint8 [H, W, 3] on `grid` (row 0 at the highest y), upscaled by a whole factor to at
    least long_px on the long side, with plan.json's walls, openings and objects drawn on it."""
    pad = math.ceil(PAD_M / grid.cell)  # white paper round the raster: the dimension lines
    rgb = np.pad(np.asarray(rgb, np.uint8), ((pad, pad), (pad, pad), (0, 0)), constant_values=255)
    grid = Grid(
        (grid.origin[0] - pad * grid.cell, grid.origin[1] - pad * grid.cell),
        grid.cell,
        rgb.shape[:2],
    )
    h, w = rgb.shape[:2]
    k = max(1, math.ceil(long_px / max(h, w)))
    img = Image.fromarray(np.asarray(rgb, np.uint8)).resize(
        (w * k, h * k), Image.Resampling.NEAREST
    )
    px_per_m = k / grid.cell
    (ox, oy) = grid.origin
    top = oy + h * grid.cell

    def px(xy: np.ndarray) -> list[tuple[float, float]]:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return [((x - ox) * px_per_m, (top - y) * px_per_m) for x, y in xy]

    # text about 12 cm high on the floor, 12 to 26 px
    size = int(min(26, max(12, 0.12 * px_per_m)))
    try:
        font = ImageFont.load_default(size=size)
        big = ImageFont.load_default(size=int(size * 1.4))
    except (OSError, ImportError, TypeError):  # Pillow without FreeType: its bitmap font
        font = big = ImageFont.load_default()
    walls = wall_shapes(plan, seen=True)
    mask = Image.new("L", img.size, 0)
    md = ImageDraw.Draw(mask)
    for poly in getattr(walls, "geoms", [walls]):
        if poly.is_empty or poly.geom_type != "Polygon":
            continue
        md.polygon(px(np.asarray(poly.exterior.coords)), fill=255)
        for ring in poly.interiors:  # the room inside its walls
            md.polygon(px(np.asarray(ring.coords)), fill=0)
    img.paste((0, 0, 0), mask=mask)
    draw = ImageDraw.Draw(img)
    for wl in plan.get("walls", []):  # inferred walls: their face dashed
        if not wl.get("seen", True):
            pa, pb = px(np.array([wl["start"], wl["end"]]))
            for seg in dashes(np.array(pa), np.array(pb), 4.0 * k, 3.0 * k):
                draw.line([tuple(p) for p in seg], fill=(0, 0, 0), width=max(2, k))
    for o in plan.get("objects", []):
        ring = px(np.asarray(o["polygon"]))
        draw.line([*ring, ring[0]], fill=(20, 40, 120), width=max(1, k // 2))
        cx, cy = px(np.asarray(o["center"]))[0]
        draw.text(
            (cx, cy),
            f"{o['class']}\n{o['width']:.2f} x {o['depth']:.2f}",
            fill=(0, 0, 0),
            anchor="mm",
            font=font,
            align="center",
        )
    for wl in plan.get("walls", []):
        a, b, t = dimension(wl)
        draw.line(px(np.array([a, b])), fill=(60, 60, 60), width=1)
        draw.text(px(t)[0], f"{wl['length']:.2f} m", fill=(0, 0, 0), anchor="mm", font=font)
    for r in plan.get("rooms", []):
        c = np.asarray(Polygon(r["polygon"]).representative_point().coords)[0]
        draw.text(px(c)[0], f"{r['name']}  {area_text(r)}", fill=(0, 0, 0), anchor="mm", font=big)
    return img

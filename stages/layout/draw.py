"""plan.svg and plan.dxf from plan.json: walls thick and black with the openings cut out
(door leaf and swing drawn), dimension lines with each wall's length, room name and area,
object outlines with class and size."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ezdxf
import numpy as np
from shapely.geometry import Polygon

from stages.common.architect import DIM_OFF, PAD_M, area_text, dimension, wall_shapes

SVG_NS = "http://www.w3.org/2000/svg"
LONG_PX = 1400.0  # the plan's longer side in the SVG (px)
LAYERS = {
    "WALLS": 7,
    "WALLS_INFERRED": 8,
    "OPENINGS": 3,
    "OBJECTS": 5,
    "DIMENSIONS": 1,
    "TEXT": 7,
}  # ACI colours
FONT = "font-family:sans-serif;fill:#111"


@dataclass(frozen=True)
class Page:
    """World metres -> SVG pixels (y down)."""

    x0: float
    y1: float
    scale: float  # px per metre
    width: float
    height: float

    def px(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.stack([(xy[:, 0] - self.x0) * self.scale, (self.y1 - xy[:, 1]) * self.scale], 1)


def page_of(plan: dict, walls: Polygon) -> Page:
    pts = [np.asarray(r["polygon"]) for r in plan["rooms"]] + [
        np.asarray(o["polygon"]) for o in plan.get("objects", [])
    ]
    lo = np.min([p.min(0) for p in pts], 0) if pts else np.zeros(2)
    hi = np.max([p.max(0) for p in pts], 0) if pts else np.ones(2)
    if not walls.is_empty:
        b = walls.bounds
        lo, hi = np.minimum(lo, b[:2]), np.maximum(hi, b[2:])
    lo, hi = lo - PAD_M, hi + PAD_M
    scale = LONG_PX / float(max(hi - lo))
    return Page(
        float(lo[0]), float(hi[1]), scale, float((hi - lo)[0] * scale), float((hi - lo)[1] * scale)
    )


def _path(poly: Polygon, page: Page) -> str:
    rings = [poly.exterior, *poly.interiors]
    return " ".join(
        "M " + " L ".join(f"{x:.2f},{y:.2f}" for x, y in page.px(np.asarray(r.coords))) + " Z"
        for r in rings
    )


def _polys(shape) -> list[Polygon]:  # noqa: ANN001 - any shapely geometry
    return [
        g for g in getattr(shape, "geoms", [shape]) if isinstance(g, Polygon) and not g.is_empty
    ]


def _text(parent: ET.Element, xy: np.ndarray, s: str, size: float, angle: float = 0.0) -> None:
    x, y = xy
    el = ET.SubElement(
        parent,
        "text",
        {
            "x": f"{x:.1f}",
            "y": f"{y:.1f}",
            "style": f"{FONT};font-size:{size:.0f}px",
            "text-anchor": "middle",
            "dominant-baseline": "middle",
        },
    )
    if angle:
        el.set("transform", f"rotate({angle:.1f} {x:.1f} {y:.1f})")
    el.text = s


def door_swing(o: dict, w: dict) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Hinge, leaf end (open, into the room), radius and the arc's start angle (deg, world)."""
    p, q = np.asarray(o["start"]), np.asarray(o["end"])
    d = np.asarray(w["end"]) - np.asarray(w["start"])
    d = d / np.linalg.norm(d)
    inward = np.array([-d[1], d[0]])
    r = float(np.linalg.norm(q - p))
    return p, p + inward * r, r, math.degrees(math.atan2(*(q - p)[::-1]))


def write_svg(plan: dict, path: Path, title: str = "") -> Page:
    walls = wall_shapes(plan, seen=True)
    page = page_of(plan, wall_shapes(plan))
    root = ET.Element(
        "svg",
        {
            "xmlns": SVG_NS,
            "width": f"{page.width:.0f}",
            "height": f"{page.height:.0f}",
            "viewBox": f"0 0 {page.width:.1f} {page.height:.1f}",
        },
    )
    ET.SubElement(root, "rect", {"width": "100%", "height": "100%", "fill": "white"})
    if title:
        _text(root, np.array([page.width / 2, 20]), title, 18)
    for r in plan["rooms"]:
        poly = Polygon(r["polygon"])
        ET.SubElement(root, "path", {"d": _path(poly, page), "fill": "#f4f1ea", "stroke": "none"})
        c = page.px(np.asarray(poly.representative_point().coords))[0]
        _text(root, c - [0, 12], r["name"], 22)
        _text(root, c + [0, 14], area_text(r).replace("m2", "m²"), 18)
    for o in plan.get("objects", []):
        ring = Polygon(o["polygon"])
        ET.SubElement(
            root,
            "path",
            {"d": _path(ring, page), "fill": "none", "stroke": "#3060a0", "stroke-width": "2"},
        )
        c = page.px(np.asarray(o["center"]))[0]
        size = f"{o['width']:.2f} x {o['depth']:.2f}" + (
            f" x {o['height']:.2f}" if o.get("height") else ""
        )
        _text(root, c - [0, 8], o["class"], 13)
        _text(root, c + [0, 8], size, 11)
    for poly in _polys(walls):
        ET.SubElement(
            root, "path", {"d": _path(poly, page), "fill": "#000000", "fill-rule": "evenodd"}
        )
    for poly in _polys(wall_shapes(plan, seen=False)):  # inferred: outlined, dashed
        ET.SubElement(
            root,
            "path",
            {
                "d": _path(poly, page),
                "fill": "none",
                "stroke": "#000000",
                "stroke-width": "2",
                "stroke-dasharray": "8,6",
                "class": "wall-inferred",
            },
        )
    for o in plan.get("openings", []):
        w = plan["walls"][o["wall"]]
        hinge, leaf, r, _ = door_swing(o, w)
        (hx, hy), (lx, ly), (qx, qy) = page.px(np.array([hinge, leaf, o["end"]]))
        st = {"fill": "none", "stroke": "#a03020", "stroke-width": "2"}
        if o["kind"] == "door":
            ET.SubElement(
                root,
                "line",
                {"x1": f"{hx:.1f}", "y1": f"{hy:.1f}", "x2": f"{lx:.1f}", "y2": f"{ly:.1f}", **st},
            )
            rp = r * page.scale
            ET.SubElement(
                root,
                "path",
                {
                    "d": f"M {lx:.1f},{ly:.1f} A {rp:.1f},{rp:.1f} 0 0 0 {qx:.1f},{qy:.1f}",
                    **st,
                    "stroke-dasharray": "6,4",
                },
            )
        c = page.px((np.asarray(o["start"]) + o["end"]) / 2)[0]
        _text(root, c, f"{o['width']:.2f}", 11)
    for w in plan["walls"]:
        a, b, tx = dimension(w)
        (ax, ay), (bx, by), (cx, cy) = page.px(np.array([a, b, tx]))
        st = {"stroke": "#444", "stroke-width": "1"}
        ET.SubElement(
            root,
            "line",
            {"x1": f"{ax:.1f}", "y1": f"{ay:.1f}", "x2": f"{bx:.1f}", "y2": f"{by:.1f}", **st},
        )
        for x, y in ((ax, ay), (bx, by)):
            ET.SubElement(
                root, "circle", {"cx": f"{x:.1f}", "cy": f"{y:.1f}", "r": "3", "fill": "#444"}
            )
        ang = math.degrees(math.atan2(by - ay, bx - ax))
        ang = ang - 180 if ang > 90 else ang + 180 if ang < -90 else ang
        _text(root, np.array([cx, cy]), f"{w['length']:.2f} m", 14, ang)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
    return page


def write_dxf(plan: dict, path: Path) -> None:
    """DXF R2010 in metres, one layer per kind: WALLS, WALLS_INFERRED (dashed outlines of the
    walls no view saw), OPENINGS, OBJECTS, DIMENSIONS, TEXT."""
    doc = ezdxf.new("R2010", setup=True)
    doc.units = ezdxf.units.M
    for name, color in LAYERS.items():
        # keyword arguments of LayerTable.add (its other keywords take ints and bools)
        attribs: dict[str, Any] = {"linetype": "DASHED"} if name == "WALLS_INFERRED" else {}
        doc.layers.add(name, color=color, **attribs)
    msp = doc.modelspace()
    for poly in _polys(wall_shapes(plan, seen=False)):
        for ring in [poly.exterior, *poly.interiors]:
            msp.add_lwpolyline(
                list(ring.coords)[:-1], close=True, dxfattribs={"layer": "WALLS_INFERRED"}
            )
    for poly in _polys(wall_shapes(plan, seen=True)):
        for ring in [poly.exterior, *poly.interiors]:
            msp.add_lwpolyline(list(ring.coords)[:-1], close=True, dxfattribs={"layer": "WALLS"})
        hatch = msp.add_hatch(color=7, dxfattribs={"layer": "WALLS"})
        hatch.paths.add_polyline_path(list(poly.exterior.coords)[:-1], is_closed=True)
        for ring in poly.interiors:
            hatch.paths.add_polyline_path(list(ring.coords)[:-1], is_closed=True)
    for o in plan.get("openings", []):
        w = plan["walls"][o["wall"]]
        hinge, leaf, r, start = door_swing(o, w)
        msp.add_line(tuple(o["start"]), tuple(o["end"]), dxfattribs={"layer": "OPENINGS"})
        if o["kind"] == "door":
            msp.add_line(tuple(hinge), tuple(leaf), dxfattribs={"layer": "OPENINGS"})
            leaf_ang = math.degrees(math.atan2(*(leaf - hinge)[::-1]))
            msp.add_arc(tuple(hinge), r, start, leaf_ang, dxfattribs={"layer": "OPENINGS"})
    for o in plan.get("objects", []):
        msp.add_lwpolyline(o["polygon"], close=True, dxfattribs={"layer": "OBJECTS"})
        size = f"{o['class']} {o['width']:.2f} x {o['depth']:.2f}"
        msp.add_text(size, height=0.08, dxfattribs={"layer": "TEXT"}).set_placement(
            tuple(o["center"])
        )
    for w in plan["walls"]:
        a, b, _ = dimension(w)
        dim = msp.add_aligned_dim(
            p1=tuple(w["start"]),
            p2=tuple(w["end"]),
            distance=-(float(w["thickness"]) + DIM_OFF),
            dxfattribs={"layer": "DIMENSIONS"},
        )
        dim.render()
    for r in plan["rooms"]:
        c = Polygon(r["polygon"]).representative_point()
        msp.add_text(
            f"{r['name']} {area_text(r)}", height=0.15, dxfattribs={"layer": "TEXT"}
        ).set_placement((c.x, c.y))
    doc.saveas(path)

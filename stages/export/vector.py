"""Vector plans: the blueprint's components as SVG, GeoJSON and DXF, in world metres.

Geometry comes from `stages.common.components` (exact cell outlines, optionally simplified);
colours are `stages.common.plan_picture.class_color`, the PNG's colours (one fixed colour per
class id).
"""

from __future__ import annotations

import json
import logging
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import ezdxf
import ezdxf.colors
import numpy as np
from ezdxf.lldxf.validator import INVALID_LAYER_NAME_CHARACTERS

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import UNKNOWN_NAME, class_color
from stages.common.components import (
    class_name,
    component_map,
    components,
    plan_summary,
    polygons,
    rings,
)

__all__ = [
    "class_color",
    "component_map",
    "components",
    "plan_summary",
    "polygons",
    "write_dxf",
    "write_geojson",
    "write_svg",
]

log = logging.getLogger(__name__)

SVG_NS = "http://www.w3.org/2000/svg"
PLAN_PX = 800.0  # longer side of the drawn plan (px)
MARGIN = 16.0  # px around the plan, legend and scale bar
LEGEND_W = 220.0  # px width of the legend column
ROW = 20.0  # px per legend line
FONT = "font-family:sans-serif;font-size:13px;fill:#222"
FRAME = "#555555"  # plan frame and swatch outline
# Characters a DXF layer name may not hold ('|' marks xref layers), plus control characters.
DXF_BAD = re.compile(
    "[" + re.escape("".join(sorted(INVALID_LAYER_NAME_CHARACTERS)) + "|") + "\\x00-\\x1f]+"
)


def _hex(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def _num(v: float) -> str:
    """A coordinate as short text, to the micrometre."""
    s = f"{v:.6f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _path_d(geom) -> str:
    """SVG path data of a (Multi)Polygon, y negated (SVG y points down, world y north)."""
    parts = []
    for ext, holes in rings(geom):
        for ring in (ext, *holes):
            pts = " L".join(f"{_num(x)},{_num(-y)}" for x, y in ring[:-1])
            parts.append(f"M{pts} Z")
    return " ".join(parts)


def _scale_length(width_m: float) -> float:
    """The largest 1, 2 or 5 x 10^k metres not over a quarter of the plan width."""
    target = max(width_m / 4.0, 1e-9)
    k = math.floor(math.log10(target))
    fits = [m * 10.0**k for m in (1.0, 2.0, 5.0) if m * 10.0**k <= target]
    return max(fits, default=0.5 * 10.0**k)  # the default only when log10 rounded up


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrs) -> ET.Element:
    el = ET.SubElement(parent, tag, {k.replace("_", "-"): str(v) for k, v in attrs.items()})
    if text is not None:
        el.text = text
    return el


def write_svg(
    bp: Blueprint,
    path: Path,
    title: str = "",
    tolerance_m: float = 0.02,
    polys: list[dict] | None = None,
) -> None:
    """The plan as standalone SVG 1.1: one filled path per component, legend, scale bar.

    The plan sits in a nested <svg> whose viewBox is in world metres (x east, -y north), so
    path coordinates are world metres with y negated; the page around it is in pixels.
    """
    polys = polygons(bp, tolerance_m) if polys is None else polys
    h, w = bp.grid.shape
    (ox, oy), cell = bp.grid.origin, bp.grid.cell
    wm, hm = w * cell, h * cell
    ppm = PLAN_PX / max(wm, hm)  # px per metre
    pw, ph = wm * ppm, hm * ppm
    top = MARGIN + (28.0 if title else 0.0)
    areas: dict[int, float] = {}  # class id -> m2
    for p in polys:
        areas[p["class_id"]] = areas.get(p["class_id"], 0.0) + p["area_m2"]
    unknown = int((bp.labels == UNKNOWN).sum())
    if unknown:
        areas[UNKNOWN] = unknown * cell * cell
    legend = [
        (cid, UNKNOWN_NAME if cid == UNKNOWN else class_name(bp, cid), a)
        for cid, a in sorted(areas.items())
    ]
    width = MARGIN + pw + MARGIN + LEGEND_W + MARGIN
    height = top + max(ph, ROW * len(legend)) + 48.0 + MARGIN

    svg = ET.Element(
        "svg",
        {
            "xmlns": SVG_NS,
            "version": "1.1",
            "width": _num(width),
            "height": _num(height),
            "viewBox": f"0 0 {_num(width)} {_num(height)}",
        },
    )
    _sub(svg, "title", title or "blueprint")
    _sub(svg, "rect", x=0, y=0, width=_num(width), height=_num(height), fill="#ffffff")
    if title:
        _sub(
            svg,
            "text",
            title,
            x=_num(MARGIN),
            y=_num(MARGIN + 16),
            style=FONT.replace("13px", "17px"),
        )

    plan = _sub(
        svg,
        "svg",
        x=_num(MARGIN),
        y=_num(top),
        width=_num(pw),
        height=_num(ph),
        viewBox=f"{_num(ox)} {_num(-(oy + hm))} {_num(wm)} {_num(hm)}",
    )
    _sub(
        plan,
        "rect",
        x=_num(ox),
        y=_num(-(oy + hm)),
        width=_num(wm),
        height=_num(hm),
        fill=_hex(class_color(UNKNOWN)),
    )
    seam = _num(0.6 / ppm)  # a hairline stroke in the fill colour hides anti-aliasing seams
    for p in polys:
        color = _hex(class_color(p["class_id"]))
        el = _sub(
            plan,
            "path",
            d=_path_d(p["geometry"]),
            fill=color,
            stroke=color,
            stroke_width=seam,
            fill_rule="evenodd",
            id=f"c{p['id']}",
        )
        el.set("class", f"k{p['class_id']}")
        inst = f" (instance {p['instance']})" if p.get("instance") else ""
        _sub(el, "title", f"{p['class']} #{p['id']}{inst}: {p['area_m2']:.3f} m²")
    _sub(
        svg,
        "rect",
        x=_num(MARGIN),
        y=_num(top),
        width=_num(pw),
        height=_num(ph),
        fill="none",
        stroke=FRAME,
        stroke_width=1,
    )

    lx = MARGIN + pw + MARGIN
    for i, (cid, name, area) in enumerate(legend):
        y = top + i * ROW
        _sub(
            svg,
            "rect",
            x=_num(lx),
            y=_num(y),
            width=14,
            height=14,
            fill=_hex(class_color(cid)),
            stroke=FRAME,
            stroke_width=0.5,
        )
        _sub(svg, "text", f"{name}  {area:.2f} m²", x=_num(lx + 20), y=_num(y + 12), style=FONT)

    length = _scale_length(wm)
    bx, by, bl = MARGIN, top + max(ph, ROW * len(legend)) + 18.0, length * ppm
    bar = _sub(svg, "g", stroke="#222222", stroke_width=1.5)
    _sub(bar, "line", x1=_num(bx), y1=_num(by), x2=_num(bx + bl), y2=_num(by))
    for x in (bx, bx + bl):
        _sub(bar, "line", x1=_num(x), y1=_num(by - 5), x2=_num(x), y2=_num(by + 5))
    label = f"{length:g} m" if length >= 1 else f"{length * 100:g} cm"
    _sub(svg, "text", label, x=_num(bx + bl + 8), y=_num(by + 5), style=FONT)
    _sub(
        svg,
        "text",
        f"cell {cell * 100:g} cm, north up",
        x=_num(bx + bl + 70),
        y=_num(by + 5),
        style=FONT.replace("#222", "#777"),
    )

    ET.indent(svg)
    ET.ElementTree(svg).write(path, encoding="utf-8", xml_declaration=True)
    log.info("export: %s, %d components", Path(path).name, len(polys))


def _coords(ring: np.ndarray) -> list[list[float]]:
    return [[round(float(x), 9), round(float(y), 9)] for x, y in ring]


def write_geojson(
    bp: Blueprint, path: Path, tolerance_m: float = 0.02, polys: list[dict] | None = None
) -> None:
    """The components as a GeoJSON FeatureCollection in scene metres (not WGS84).

    One feature per component: a Polygon, or a MultiPolygon when its cells touch only at
    corners; exteriors counter-clockwise, holes clockwise (RFC 7946 winding). Properties:
    id, class, class_id, instance (0 = none), area_m2, cells.
    """
    features = []
    for p in polygons(bp, tolerance_m) if polys is None else polys:
        parts = [
            [_coords(ext), *(_coords(hl) for hl in holes)] for ext, holes in rings(p["geometry"])
        ]
        geom = (
            {"type": "Polygon", "coordinates": parts[0]}
            if len(parts) == 1
            else {"type": "MultiPolygon", "coordinates": parts}
        )
        features.append(
            {
                "type": "Feature",
                "id": p["id"],
                "geometry": geom,
                "properties": {
                    k: p[k] for k in ("id", "class", "class_id", "instance", "area_m2", "cells")
                },
            }
        )
    data = {
        "type": "FeatureCollection",
        "units": "metres",
        "frame": "blunf scene frame (x, y in metres on the floor plane, z up); not geographic",
        "grid": bp.grid.to_json(),
        "classes": {str(k): v for k, v in sorted(bp.classes.items())},
        "features": features,
    }
    Path(path).write_text(json.dumps(data, separators=(",", ":")) + "\n")
    log.info("export: %s, %d features", Path(path).name, len(features))


def _nearest_aci(rgb: tuple[int, int, int]) -> int:
    """The AutoCAD colour index (1..255) closest to rgb, for viewers without true colour."""
    pal = np.array([tuple(ezdxf.colors.aci2rgb(i)) for i in range(1, 256)], np.float64)
    return int(np.argmin(((pal - np.asarray(rgb, np.float64)) ** 2).sum(1))) + 1


def dxf_layer_name(bp: Blueprint, class_id: int) -> str:
    """The class name made a legal DXF layer name (invalid characters become '_')."""
    name = DXF_BAD.sub("_", class_name(bp, class_id)).strip("_ ")
    return name or f"class_{class_id}"


def write_dxf(
    bp: Blueprint, path: Path, tolerance_m: float = 0.02, polys: list[dict] | None = None
) -> None:
    """The components as DXF R2010: one layer per class (true colour), units metres.

    Every ring (exteriors and holes) is a closed LWPOLYLINE on its class's layer.
    """
    doc = ezdxf.new("R2010")
    doc.units = ezdxf.units.M
    doc.header["$MEASUREMENT"] = 1  # metric
    msp = doc.modelspace()
    layers: dict[int, str] = {}
    for p in polygons(bp, tolerance_m) if polys is None else polys:
        cid = p["class_id"]
        if cid not in layers:
            name = dxf_layer_name(bp, cid)
            taken = {n.lower() for n in layers.values()} | {"0", "defpoints"}  # case-blind
            if name.lower() in taken:
                name = f"{name}_{cid}"
            rgb = class_color(cid)
            doc.layers.add(name, color=_nearest_aci(rgb), true_color=ezdxf.colors.rgb2int(rgb))
            layers[cid] = name
        for ext, holes in rings(p["geometry"]):
            for ring in (ext, *holes):
                msp.add_lwpolyline(
                    ring[:-1].tolist(), close=True, dxfattribs={"layer": layers[cid]}
                )
    doc.saveas(path)
    log.info("export: %s, %d layers", Path(path).name, len(layers))

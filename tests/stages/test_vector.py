"""Blueprint components, polygons and the SVG / GeoJSON / DXF writers on a plan drawn by hand."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET

import ezdxf
import numpy as np
import pytest
import shapely
from shapely.geometry import shape

from stages.common.blueprint import Blueprint, Grid
from stages.common.errors import BlunfError
from stages.export.vector import (
    class_color,
    component_map,
    components,
    dxf_layer_name,
    plan_summary,
    polygons,
    write_dxf,
    write_geojson,
    write_svg,
)

U, F, C, T = 255, 0, 1, 2  # unknown, floor, chair, table
# 8 rows x 10 columns, row 0 = north. Chair A = (2,1) (2,2) (3,1) + (4,2), which touches (3,1)
# only at a corner: one component under 8-connectivity (two under 4). Chair B = (4,5) (5,5)
# (5,6), separated from A by floor. Table = rows 2-3, cols 7-8. Every chair and the table lie
# inside the floor, so the floor has holes. Unknown: row 0, (7,0), (7,1), (7,9).
PLAN = np.array(
    [
        [U, U, U, U, U, U, U, U, U, U],
        [F, F, F, F, F, F, F, F, F, F],
        [F, C, C, F, F, F, F, T, T, F],
        [F, C, F, F, F, F, F, T, T, F],
        [F, F, C, F, F, C, F, F, F, F],
        [F, F, F, F, F, C, C, F, F, F],
        [F, F, F, F, F, F, F, F, F, F],
        [U, U, F, F, F, F, F, F, F, U],
    ],
    np.uint8,
)
ORIGIN, CELL = (-3.2, 10.0), 0.05
SVG = "http://www.w3.org/2000/svg"
CLASSES = {F: "floor", C: "chair", T: "table"}
# Ids in raster order of each component's first cell: floor (1,0), chair A (2,1), table (2,7),
# chair B (4,5).
FLOOR, CHAIR_A, TABLE, CHAIR_B = 1, 2, 3, 4
# Table corners: cols 7..9 -> x = -3.2 + 7 * 0.05 .. -3.2 + 9 * 0.05; rows 2..4 -> y = 10.3 .. 10.2.
TABLE_CORNERS = [(-2.85, 10.2), (-2.85, 10.3), (-2.75, 10.2), (-2.75, 10.3)]


@pytest.fixture
def bp() -> Blueprint:
    return Blueprint(PLAN.copy(), Grid(ORIGIN, CELL, PLAN.shape), dict(CLASSES))


def centres(bp: Blueprint) -> tuple[np.ndarray, np.ndarray]:
    c = bp.grid.centers()  # [H, W, 2]
    return c[..., 0], c[..., 1]


def raster(geom, bp: Blueprint) -> np.ndarray:
    """Cells whose centre lies inside geom. Returns bool [H, W]."""
    return shapely.contains_xy(geom, *centres(bp))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return (a & b).sum() / (a | b).sum()


def test_component_map_joins_diagonals_and_keeps_class_zero(bp):
    cmap = component_map(bp)
    assert cmap.dtype == np.int32 and cmap.shape == (8, 10)
    assert (cmap[PLAN == U] == 0).all() and (cmap[PLAN != U] > 0).all()  # class 0 is not "none"
    assert cmap[4, 2] == cmap[3, 1] == cmap[2, 1] == CHAIR_A  # corner contact joins
    assert cmap[4, 5] == cmap[5, 6] == CHAIR_B
    assert cmap[3, 2] == cmap[4, 1] == FLOOR  # the floor crosses the same corner too
    assert set(np.unique(cmap).tolist()) == {0, 1, 2, 3, 4}


def test_components_areas_centroids_bboxes(bp):
    comps = {c["id"]: c for c in components(bp)}
    assert sorted(comps) == [1, 2, 3, 4]
    assert [comps[i]["class"] for i in (1, 2, 3, 4)] == ["floor", "chair", "table", "chair"]
    # 80 cells - 13 unknown - 4 - 3 - 4 = 56 floor cells; one cell is 0.05^2 = 0.0025 m2.
    assert {i: c["cells"] for i, c in comps.items()} == {1: 56, 2: 4, 3: 4, 4: 3}
    for i, cells in ((1, 56), (2, 4), (3, 4), (4, 3)):
        assert comps[i]["area_m2"] == pytest.approx(cells * 0.0025)
    # Chair A: mean row (2+2+3+4)/4 = 2.75, mean col (1+2+1+2)/4 = 1.5;
    # x = -3.2 + (1.5 + 0.5) * 0.05 = -3.1, y = 10 + (8 - 2.75 - 0.5) * 0.05 = 10.2375.
    assert comps[CHAIR_A]["centroid"] == pytest.approx([-3.1, 10.2375])
    # cols 1..2 -> x in [-3.15, -3.05]; rows 2..4 -> y from 10 + (8-5)*0.05 to 10 + (8-2)*0.05.
    assert comps[CHAIR_A]["bbox"] == pytest.approx([-3.15, 10.15, -3.05, 10.3])
    # Chair B: mean row 14/3, mean col 16/3.
    assert comps[CHAIR_B]["centroid"] == pytest.approx(
        [-3.2 + (16 / 3 + 0.5) * 0.05, 10 + (8 - 14 / 3 - 0.5) * 0.05]
    )
    assert comps[CHAIR_B]["bbox"] == pytest.approx([-2.95, 10.1, -2.85, 10.2])
    assert comps[TABLE]["centroid"] == pytest.approx([-2.8, 10.25])
    assert comps[TABLE]["bbox"] == pytest.approx([-2.85, 10.2, -2.75, 10.3])
    assert comps[FLOOR]["bbox"] == pytest.approx([-3.2, 10.0, -2.7, 10.35])  # rows 1..7
    # min_area drops chair B (0.0075 m2) and keeps the others' ids.
    assert [c["id"] for c in components(bp, min_area_m2=0.008)] == [1, 2, 3]


# Instances of the hand plan: chair A's corner cell (4,2) is another object (2) than the rest
# of chair A (1); chair B is object 2 as well, the table 3, the floor none.
INSTANCES = np.zeros(PLAN.shape, np.int32)
INSTANCES[2, 1] = INSTANCES[2, 2] = INSTANCES[3, 1] = 1
INSTANCES[4, 2] = INSTANCES[4, 5] = INSTANCES[5, 5] = INSTANCES[5, 6] = 2
INSTANCES[2:4, 7:9] = 3


def test_component_map_keeps_instances_of_one_class_apart(bp):
    inst = Blueprint(bp.labels, bp.grid, bp.classes, INSTANCES.copy())
    cmap = component_map(inst)
    # raster order of first cells: floor (1,0), chair A without its corner (2,1), table (2,7),
    # the corner cell (4,2) now its own (same class, other instance), chair B (4,5): chair B
    # shares instance 2 with the corner cell but does not touch it
    assert cmap[2, 1] == cmap[2, 2] == cmap[3, 1] == 2
    assert cmap[4, 2] == 4 and cmap[4, 5] == cmap[5, 6] == 5 and cmap[2, 7] == 3
    assert set(np.unique(cmap).tolist()) == {0, 1, 2, 3, 4, 5}
    comps = {c["id"]: c for c in components(inst)}
    got = {i: (c["class"], c["instance"], c["cells"]) for i, c in comps.items()}
    assert got == {
        1: ("floor", 0, 56),
        2: ("chair", 1, 3),
        3: ("table", 3, 4),
        4: ("chair", 2, 1),
        5: ("chair", 2, 3),
    }
    assert plan_summary(inst)["classes"]["chair"]["components"] == 3
    # an instance layer of zeros changes nothing: same ids as the class-only map
    zero = Blueprint(bp.labels, bp.grid, bp.classes, np.zeros(PLAN.shape, np.int32))
    np.testing.assert_array_equal(component_map(zero), component_map(bp))
    assert {c["instance"] for c in components(bp)} == {0}


def test_instances_reach_geojson_and_svg(bp, tmp_path):
    inst = Blueprint(bp.labels, bp.grid, bp.classes, INSTANCES.copy())
    write_geojson(inst, tmp_path / "plan.geojson")
    feats = json.loads((tmp_path / "plan.geojson").read_text())["features"]
    assert {f["properties"]["id"]: f["properties"]["instance"] for f in feats} == {
        1: 0,
        2: 1,
        3: 3,
        4: 2,
        5: 2,
    }
    write_svg(inst, tmp_path / "plan.svg")
    titles = [t.text for t in ET.parse(tmp_path / "plan.svg").getroot().iter(f"{{{SVG}}}title")]
    assert "chair #4 (instance 2): 0.003 m²" in titles and "floor #1: 0.140 m²" in titles
    write_dxf(inst, tmp_path / "plan.dxf")  # one polyline per component ring, as before
    layers = [e.dxf.layer for e in ezdxf.readfile(tmp_path / "plan.dxf").modelspace()]
    assert layers.count("chair") == 3


def test_polygons_exact_at_zero_tolerance(bp):
    cmap = component_map(bp)
    polys = {p["id"]: p for p in polygons(bp, tolerance_m=0.0)}
    for i, p in polys.items():
        g = p["geometry"]
        assert g.is_valid
        assert (raster(g, bp) == (cmap == i)).all(), p["class"]
        assert g.area == pytest.approx(p["cells"] * CELL**2, rel=1e-9)
    a = polys[CHAIR_A]["geometry"]  # the L and the corner cell, meeting at one point
    assert a.geom_type == "MultiPolygon" and sorted(
        q.area / CELL**2 for q in a.geoms
    ) == pytest.approx([1, 3])
    floor = polys[FLOOR]["geometry"]
    # Holes: chair A's L, chair A's corner cell, chair B, the table.
    assert floor.geom_type == "Polygon" and len(floor.interiors) == 4
    # Exterior corners (collinear ones dropped): the rectangle rows 1-7 with notches at the
    # unknown cells (7,0)-(7,1) and (7,9): 4 + 2 + 2 = 8 corners.
    assert len(floor.exterior.coords) == 8 + 1
    assert floor.exterior.is_ccw and not any(r.is_ccw for r in floor.interiors)
    table = polys[TABLE]["geometry"]
    np.testing.assert_allclose(sorted(table.exterior.coords[:-1]), TABLE_CORNERS)


def test_polygons_default_and_coarse_tolerance_on_a_disc():
    # A disc of radius 20 cells: staircase edges that Douglas-Peucker can shorten.
    r, c = np.mgrid[:48, :48]
    lab = np.where((r - 23.5) ** 2 + (c - 23.5) ** 2 < 20**2, C, F).astype(np.uint8)
    disc = Blueprint(lab, Grid(ORIGIN, CELL, lab.shape), dict(CLASSES))
    exact = polygons(disc, 0.0)[1]["geometry"]
    for tol in (0.02, 0.05):
        g = polygons(disc, tol)[1]["geometry"]
        assert g.is_valid and iou(raster(g, disc), lab == C) >= 0.95
    coarse = polygons(disc, 0.05)[1]["geometry"]
    assert len(coarse.exterior.coords) < len(exact.exterior.coords) / 2
    with pytest.raises(BlunfError, match="tolerance"):
        polygons(disc, -1.0)


def test_polygons_default_tolerance_on_plan(bp):
    cmap = component_map(bp)
    for p in polygons(bp):
        assert iou(raster(p["geometry"], bp), cmap == p["id"]) >= 0.95


def parse_path(d: str) -> list[np.ndarray]:
    """Rings [N, 2] of an SVG path "M x,y L x,y ... Z ...", back in world y (north up)."""
    out = []
    for ring in re.findall(r"M([^Z]*)Z", d):
        pts = [tuple(map(float, p.split(","))) for p in ring.replace("L", " ").split()]
        out.append(np.array(pts) * [1, -1])
    return out


def test_svg_parses_colours_and_rasterises_back(bp, tmp_path):
    path = tmp_path / "plan.svg"
    write_svg(bp, path, title="room <1> & co")
    ns = {"s": "http://www.w3.org/2000/svg"}
    root = ET.parse(path).getroot()
    assert root.tag == "{http://www.w3.org/2000/svg}svg" and root.get("version") == "1.1"
    plan = root.find("s:svg", ns)
    # Plan viewBox in metres: x from -3.2, y from -(10 + 8 * 0.05), 0.5 m wide, 0.4 m high.
    assert [float(v) for v in plan.get("viewBox").split()] == pytest.approx([-3.2, -10.4, 0.5, 0.4])
    paths = plan.findall("s:path", ns)
    assert len(paths) == 4
    cls_of = {FLOOR: F, CHAIR_A: C, TABLE: T, CHAIR_B: C}
    drawn = np.full(PLAN.shape, U, np.uint8)
    for el in paths:
        cid = cls_of[int(el.get("id")[1:])]
        assert el.get("fill") == "#{:02x}{:02x}{:02x}".format(*class_color(cid))
        # even-odd fill: a cell is painted when its centre is inside an odd number of rings.
        odd = (
            sum(
                shapely.contains_xy(shapely.Polygon(r), *centres(bp)).astype(int)
                for r in parse_path(el.get("d"))
            )
            % 2
            == 1
        )
        assert not (odd & (drawn != U)).any()  # no cell painted twice
        drawn[odd] = cid
    # Default tolerance 0.02 m is under every corner's offset from its neighbours' chord here
    # (>= 0.05 / sqrt(2)), so the drawn plan is the plan exactly.
    assert (drawn == PLAN).all()
    texts = " ".join(t.text for t in root.iter("{http://www.w3.org/2000/svg}text"))
    for word in ("floor", "chair", "table", "unknown", "room <1> & co", "10 cm"):
        assert word in texts  # legend, title (escaped in the file), scale bar (0.5 m / 4 -> 0.1)


def test_geojson_round_trip(bp, tmp_path):
    path = tmp_path / "plan.geojson"
    write_geojson(bp, path)
    data = json.loads(path.read_text())
    assert data["type"] == "FeatureCollection" and data["units"] == "metres"
    feats = {f["properties"]["id"]: f for f in data["features"]}
    comps = {c["id"]: c for c in components(bp)}
    polys = {p["id"]: p["geometry"] for p in polygons(bp)}
    assert sorted(feats) == [1, 2, 3, 4]
    for i, f in feats.items():
        props = f["properties"]
        assert (props["class"], props["class_id"]) == (comps[i]["class"], comps[i]["class_id"])
        assert props["area_m2"] == pytest.approx(comps[i]["area_m2"])
        g = shape(f["geometry"])
        assert g.symmetric_difference(polys[i]).area < 1e-12
    assert feats[CHAIR_A]["geometry"]["type"] == "MultiPolygon"
    assert feats[TABLE]["geometry"]["type"] == "Polygon"
    assert len(feats[FLOOR]["geometry"]["coordinates"]) == 1 + 4  # exterior + 4 holes


def test_dxf_layers_and_closed_polylines(tmp_path):
    classes = {F: "floor", C: "chair", T: "table: dining"}  # ':' is not allowed in a layer name
    bp = Blueprint(PLAN.copy(), Grid(ORIGIN, CELL, PLAN.shape), classes)
    assert dxf_layer_name(bp, T) == "table_ dining"
    path = tmp_path / "plan.dxf"
    write_dxf(bp, path)
    doc = ezdxf.readfile(path)
    assert doc.header["$INSUNITS"] == 6  # metres
    names = {"floor": F, "chair": C, "table_ dining": T}
    for name, cid in names.items():
        layer = doc.layers.get(name)
        assert layer.rgb == class_color(cid)
    counts = {}
    for e in doc.modelspace().query("LWPOLYLINE"):
        assert e.closed
        counts[e.dxf.layer] = counts.get(e.dxf.layer, 0) + 1
    # floor: exterior + 4 holes; chair: A's two parts + B; table: one rectangle.
    assert counts == {"floor": 5, "chair": 3, "table_ dining": 1}
    (table,) = doc.modelspace().query('LWPOLYLINE[layer=="table_ dining"]')
    np.testing.assert_allclose(sorted(table.get_points("xy")), TABLE_CORNERS)


def test_plan_summary(bp):
    s = plan_summary(bp)
    assert s["classes"]["chair"] == {
        "class_id": C,
        "area_m2": pytest.approx(7 * 0.0025),
        "cells": 7,
        "components": 2,
    }
    assert s["classes"]["floor"]["area_m2"] == pytest.approx(56 * 0.0025)
    assert s["unknown_area_m2"] == pytest.approx(13 * 0.0025)
    assert [c["id"] for c in s["components"]] == [1, 2, 3, 4]
    json.dumps(s)  # report.json-ready


def test_bad_plan_raises():
    bad = Blueprint(PLAN.astype(np.int32), Grid(ORIGIN, CELL, PLAN.shape), CLASSES)
    with pytest.raises(BlunfError, match="uint8"):
        components(bad)
    empty = Blueprint(np.full((3, 4), U, np.uint8), Grid(ORIGIN, CELL, (3, 4)), CLASSES)
    assert components(empty) == [] and polygons(empty) == []


def test_dxf_layer_names_stay_distinct(tmp_path):
    # DXF layer names are case-blind: "Chair" and "chair" must not land on one layer.
    bp = Blueprint(PLAN.copy(), Grid(ORIGIN, CELL, PLAN.shape), {F: "Chair", C: "chair", T: "0"})
    write_dxf(bp, tmp_path / "plan.dxf")
    layers = {e.dxf.layer for e in ezdxf.readfile(tmp_path / "plan.dxf").modelspace()}
    assert layers == {"Chair", "chair_1", "0_2"}

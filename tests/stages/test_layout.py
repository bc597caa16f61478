"""The layout stage: walls, rooms, openings and objects read off a blueprint, scored against
exact layouts (the procedural room's gt/layout.json, and hand-built L-shaped and two-room
plans turned off the axes); plan.dxf holds its layers, plan.svg draws the walls black."""

from __future__ import annotations

import io
import json
import math

import ezdxf
import numpy as np
import pytest
import resvg_py
from PIL import Image
from shapely import affinity, contains_xy
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from stages.common.architect import overlay
from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN
from stages.common.classes import class_color
from stages.evaluate.layout import interior_angles, score_layout
from stages.export.config import ExportInputs
from stages.export.files import _picture as export_picture
from stages.layout import IMPLS, LayoutConfig, LayoutInputs
from stages.layout.draw import write_svg
from stages.layout.extract import Frame, Line, _fit, _merge, outline
from stages.layout.walls import build_plan
from stages.synth import make_room

GT_PLAN = LayoutConfig(face_offset=0.0)  # plans of vertical rays through the cell centres
# sensor-depth targets of the layout scores
TARGET = {"room_f1": 0.95, "corner_f1": 0.9, "angle_f1": 0.9}


def _meets_targets(s: dict, doors: int, passages: int = 0) -> None:
    for k, v in TARGET.items():
        assert s[k] >= v, (k, s)
    assert s["wall_length_err_m"] <= 0.03, s
    assert s["doors_found"] == s["doors_total"] == doors, s
    if doors:
        assert s["door_width_err_m"] <= 0.05, s
    assert s["passages_found"] == s["passages_total"] == passages, s
    if passages:
        assert s["passage_width_err_m"] <= 0.05, s


def test_scores_by_hand():
    gt = {
        "rooms": [{"polygon": [[0, 0], [4, 0], [4, 3], [0, 3]]}],
        "openings": [
            {"start": [1, 0], "end": [1.9, 0], "width": 0.9},
            {"start": [4, 1], "end": [4, 2], "width": 1.0},
        ],
    }
    pred = {
        "rooms": [  # one corner 15 cm off (no match), one 5 cm off; a room that is not there
            {"polygon": [[0.05, 0], [4, 0], [4, 3], [0, 3.15]]},
            {"polygon": [[10, 10], [11, 10], [11, 11], [10, 11]]},
        ],
        "openings": [{"start": [1.05, 0], "end": [1.9, 0], "width": 0.85}],
    }
    s = score_layout(pred, gt)
    assert (s["room_precision"], s["room_recall"]) == (0.5, 1.0)
    assert s["room_f1"] == pytest.approx(2 / 3, abs=1e-4)
    # 3 of 4 corners match; precision counts the other room's 4 corners too
    assert (s["corner_precision"], s["corner_recall"], s["corner_f1"]) == (0.375, 0.75, 0.5)
    # the matched corners' angles: 90.9, 90 and 87.9 degrees: all within 5
    assert (s["angle_precision"], s["angle_recall"]) == (0.375, 0.75)
    # wall errors 0.05, 0, 0.0028, 0.1504: median (0.0028 + 0.05) / 2
    assert s["wall_length_err_m"] == pytest.approx(0.0264, abs=1e-4)
    assert (s["doors_found"], s["doors_total"], s["door_width_err_m"]) == (1, 2, 0.05)
    assert (s["passages_found"], s["passages_total"], s["passage_width_err_m"]) == (0, 0, None)


def test_passages_are_scored_apart_from_doors():
    gt = {
        "rooms": [{"polygon": [[0, 0], [4, 0], [4, 3], [0, 3]]}],
        "openings": [
            {"kind": "door", "start": [1, 0], "end": [1.9, 0], "width": 0.9},
            {"kind": "passage", "start": [4, 0.5], "end": [4, 2.3], "width": 1.8},
            {"kind": "passage", "start": [0, 0.5], "end": [0, 2.1], "width": 1.6},
        ],
    }
    pred = {
        "rooms": gt["rooms"],
        "openings": [  # the door called a passage is no door; one passage found 4 cm wide
            {"kind": "passage", "start": [1, 0], "end": [1.9, 0], "width": 0.9},
            {"kind": "passage", "start": [4, 0.5], "end": [4, 2.34], "width": 1.84},
            {"kind": "door", "start": [0, 0.9], "end": [0, 1.7], "width": 0.8},
        ],
    }
    s = score_layout(pred, gt)
    assert (s["doors_found"], s["doors_total"], s["door_width_err_m"]) == (0, 1, None)
    assert (s["passages_found"], s["passages_total"]) == (1, 2)
    assert s["passage_width_err_m"] == pytest.approx(0.04)


def test_interior_angles_of_an_l():
    ell = np.array([[0, 0], [4, 0], [4, 2], [2, 2], [2, 4], [0, 4]], float)
    np.testing.assert_allclose(interior_angles(ell), [90, 90, 90, 270, 90, 90])


# rect seed 3 with a passage: 1.73 m under a lintel at 2.15 m; L seed 4 with two: 1.64 m full
# height, 1.88 m under a lintel at 2.24 m
@pytest.mark.parametrize(
    ("seed", "shape", "passages"),
    [(3, "rect", 0), (5, "rect", 0), (0, "L", 0), (4, "L", 0), (3, "rect", 1), (4, "L", 2)],
)
def test_exact_room_with_doors_meets_the_targets(tmp_path, seed, shape, passages):
    cap = make_room(
        tmp_path / "cap",
        views=1,
        seed=seed,
        size=(16, 12),
        doors=2,
        shape=shape,
        passages=passages,
    )
    out = IMPLS["walls"](
        GT_PLAN,
        LayoutInputs(cap / "gt" / "blueprint.npz", cap / "gt" / "mesh.ply"),
        tmp_path / "layout",
    )
    plan = json.loads(out.plan_json.read_text())
    gt = json.loads((cap / "gt" / "layout.json").read_text())
    _meets_targets(score_layout(plan, gt), doors=2, passages=passages)
    kinds = sorted(o["kind"] for o in plan["openings"])
    assert kinds == ["door"] * 2 + ["passage"] * passages
    # one room, named; its doors and passages lead outside it
    assert [r["name"] for r in plan["rooms"]] == ["room 1"]
    assert all(o["rooms"] == [0] for o in plan["openings"]), plan["openings"]
    assert all(abs(w["thickness"] - gt["walls"][0]["thickness"]) <= 0.02 for w in plan["walls"])
    inst = json.loads((cap / "gt" / "instances.json").read_text())
    assert len(plan["objects"]) == len(inst)
    # a height is the 98th percentile of the object's top: a bed's headboard (3 % of its
    # footprint) stands above it, so beds are left out here
    want = sorted(v["bbox"][5] for v in inst.values() if not v["name"].startswith("bed"))
    got = sorted(o["height"] for o in plan["objects"] if o["class"] != "bed")
    np.testing.assert_allclose(got, want, atol=0.01)

    layers = {layer.dxf.name for layer in ezdxf.readfile(out.plan_dxf).layers}
    kinds = {"WALLS", "OPENINGS", "OBJECTS", "DIMENSIONS", "TEXT"}
    assert kinds <= layers
    used = {e.dxf.layer for e in ezdxf.readfile(out.plan_dxf).modelspace()}
    assert kinds <= used

    # the SVG, drawn: black along the middle of every wall, not black in the doorways
    page = write_svg(plan, tmp_path / "plan.svg")
    png = Image.open(
        io.BytesIO(bytes(resvg_py.svg_to_bytes(svg_string=(tmp_path / "plan.svg").read_text())))
    )
    img = np.asarray(png.convert("L")).astype(int)
    assert max(img.shape) >= 1200
    walls = _wall_midlines(gt)
    xy = page.px(walls).astype(int)
    assert (img[xy[:, 1], xy[:, 0]] < 60).all()
    for o in gt["openings"]:
        w = gt["walls"][o["wall"]]
        d = np.subtract(w["end"], w["start"]) / w["length"]
        # along the gap in the wall's middle (the width's label may sit on one point)
        f = np.linspace(0.2, 0.8, 7)[:, None]
        pts = np.asarray(o["start"]) * (1 - f) + np.asarray(o["end"]) * f
        xy = page.px(pts + np.array([d[1], -d[0]]) * w["thickness"] / 2).astype(int)
        assert np.median(img[xy[:, 1], xy[:, 0]]) > 200

    # the plan picture: classes in grey, the walls black over them, >= 1200 px
    bp = Blueprint.load(cap / "gt" / "blueprint.npz")
    pic = overlay(np.full((*bp.labels.shape, 3), 200, np.uint8), bp.grid, plan)
    assert max(pic.size) >= 1200
    grey = np.asarray(pic.convert("L"))
    k = round(pic.size[0] / (bp.labels.shape[1] + 2 * math.ceil(0.8 / bp.grid.cell)))
    top = bp.grid.origin[1] + (bp.labels.shape[0] + math.ceil(0.8 / bp.grid.cell)) * bp.grid.cell
    left = bp.grid.origin[0] - math.ceil(0.8 / bp.grid.cell) * bp.grid.cell
    for pts, black in ((walls, True), (_wall_midlines(gt, inside=0.04), False)):
        col = ((pts[:, 0] - left) / bp.grid.cell * k).astype(int)
        row = ((top - pts[:, 1]) / bp.grid.cell * k).astype(int)
        assert ((grey[row, col] < 30) == black).all()  # object outlines are dark blue, not black


def _wall_midlines(gt: dict, inside: float | None = None) -> np.ndarray:
    """Points along the middle of every ground-truth wall, away from its doors [N, 2]; or
    `inside` metres inside the room from its face."""
    doors = [
        Polygon([o["start"], o["end"], np.add(o["end"], 0.01), np.add(o["start"], 0.01)]).buffer(
            0.3
        )
        for o in gt["openings"]
    ]
    out = []
    for w in gt["walls"]:
        a, b, t = np.asarray(w["start"]), np.asarray(w["end"]), w["thickness"]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([d[1], -d[0]])
        off = t / 2 if inside is None else -inside
        pts = a + np.linspace(0.02, 0.98, 60)[:, None] * (b - a) + n * off
        out += [p for p in pts if not any(contains_xy(g, *p) for g in doors)]
    return np.array(out)


def _raster(rooms: list[Polygon], t: float, gaps: list[Polygon], angle: float) -> Blueprint:
    """A blueprint of rooms (interiors) with walls `t` thick round them, the floor running
    through the gaps, everything turned by `angle` degrees about the origin."""
    inside = unary_union(rooms)
    walls = unary_union([r.buffer(t, join_style="mitre") for r in rooms]).difference(inside)
    gap = unary_union(gaps).intersection(walls)
    walls, inside = walls.difference(gap), inside.union(gap)
    walls, inside = (affinity.rotate(g, angle, origin=(0, 0)) for g in (walls, inside))
    lo, hi = np.array(walls.bounds[:2]), np.array(walls.bounds[2:])
    grid = Grid.covering(lo, hi, 0.02, pad=0.2)
    c = grid.centers()
    labels = np.full(grid.shape, UNKNOWN, np.uint8)
    labels[contains_xy(inside, c[..., 0], c[..., 1])] = 0
    labels[contains_xy(walls, c[..., 0], c[..., 1])] = 1
    return Blueprint(labels, grid, {0: "floor", 1: "wall"})


def _turn(xy, angle: float) -> list:
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    x, y = np.asarray(xy, float).T
    return np.stack([c * x - s * y, s * x + c * y], -1).tolist()


def _outline(poly) -> np.ndarray:  # noqa: ANN001
    """The outline traced round a room mask painted from `poly` on a 2 cm grid."""
    grid = Grid.covering(np.array([-0.5, -0.5]), np.array([4.5, 3.5]), 0.02)
    c = grid.centers()
    mask = contains_xy(poly, c[..., 0], c[..., 1])
    return outline(mask, Frame(mask.astype(np.uint8), grid, 0.0), GT_PLAN)


def test_a_doorway_bump_does_not_move_the_wall_face():
    # the room's mask reaches 12 cm into a 1.9 m doorway of its south wall (the closed
    # doorway joined the room); the face on either side is 1.0 and 1.1 m long, each shorter
    # than the bump, both together longer: the face stays at y = 0 whichever side merges first
    poly = _outline(box(0, 0, 4, 3).union(box(1.0, -0.12, 2.9, 0)))
    np.testing.assert_allclose(
        sorted(map(tuple, poly)), [(0, 0), (0, 3), (4, 0), (4, 3)], atol=0.011
    )


def test_merged_faces_take_the_offset_their_pieces_support_most():
    x = np.array([1.0, 0.0])
    face_a = Line(np.array([0.0, 0.0]), x, 1.0)
    bump = Line(np.array([1.0, -0.12]), x, 1.9)
    face_b = Line(np.array([2.9, 0.0]), x, 1.1)
    for first, second in ((face_a, face_b), (face_b, face_a)):
        merged = _merge(_merge(first, bump, 0.06), second, 0.06)
        assert merged.p[1] == pytest.approx(0.0) and merged.weight == pytest.approx(4.0)
    # within the step the offsets are averaged by their support
    assert _merge(face_a, Line(np.array([0.0, 0.03]), x, 3.0), 0.06).p[1] == pytest.approx(0.0225)


def test_a_slanted_edge_whose_points_run_along_an_axis_is_snapped():
    # the simplified edge leans 12 degrees (a step of a ragged face), the traced points along
    # it 4 degrees: the refit line is the axis through them
    a, b = np.array([0.0, 0.0]), np.array([1.0, -math.tan(math.radians(12))])
    t = np.linspace(0, 1, 50)
    pts = np.stack([t, -0.05 - t * math.tan(math.radians(4))], 1)
    line = _fit(a, b, pts, GT_PLAN, 0.02)
    assert line.snapped and line.d.tolist() == [1.0, 0.0]
    assert line.p[1] == pytest.approx(-0.085, abs=0.01)  # the points' middle


@pytest.mark.parametrize("angle", [0.0, 23.0])
def test_l_shaped_room_and_two_rooms_meet_the_targets(angle):
    t = 0.12
    ell = Polygon([(0, 0), (5, 0), (5, 2.5), (2.4, 2.5), (2.4, 4.5), (0, 4.5)])
    door = box(1.0, -0.2, 1.85, 0.05)  # 0.85 m in the south wall
    a, b = box(0, 0, 3, 4), box(3 + t, 0, 7, 4)
    passage = box(2.9, 1.5, 3.3, 2.4)  # 0.9 m through the wall between a and b
    cases = [
        ([ell], [door], [[(1.0, 0), (1.85, 0)]]),
        ([a, b], [passage], [[(3, 1.5), (3, 2.4)]]),
    ]
    for rooms, gaps, openings in cases:
        bp = _raster(rooms, t, gaps, angle)
        plan = build_plan(bp, GT_PLAN)
        assert abs(plan["angle_deg"] - angle) < 0.5
        gt = {
            "rooms": [{"polygon": _turn(r.exterior.coords[:-1], angle)} for r in rooms],
            "openings": [
                {
                    "start": _turn([p], angle)[0],
                    "end": _turn([q], angle)[0],
                    "width": math.dist(p, q),
                }
                for p, q in openings
            ],
        }
        s = score_layout(plan, gt)
        _meets_targets(s, doors=1)
        assert s["corner_f1"] == 1.0 and s["angle_f1"] == 1.0, s
        assert len(plan["rooms"]) == len(rooms)
        for r, g in zip(
            sorted(plan["rooms"], key=lambda r: r["area"]),
            sorted(rooms, key=lambda r: r.area),
            strict=True,
        ):
            assert r["area"] == pytest.approx(g.area, rel=0.01)


@pytest.mark.parametrize("angle", [0.0, 23.0])
def test_a_passage_wider_than_a_doorway_closes_the_wall_line_between_two_rooms(angle):
    # 1.8 m through the wall between a and b: wider than max_opening (1.3 m), the floor
    # running through it, no wall beside it across (the rooms on either side)
    t = 0.12
    a, b = box(0, 0, 3, 4), box(3 + t, 0, 7, 4)
    bp = _raster([a, b], t, [box(2.9, 0.8, 3.3, 2.6)], angle)
    plan = build_plan(bp, GT_PLAN)
    gt = {
        "rooms": [{"polygon": _turn(r.exterior.coords[:-1], angle)} for r in (a, b)],
        "openings": [
            {
                "kind": "passage",
                "start": _turn([(3, 0.8)], angle)[0],
                "end": _turn([(3, 2.6)], angle)[0],
                "width": 1.8,
            }
        ],
    }
    s = score_layout(plan, gt)
    _meets_targets(s, doors=0, passages=1)
    assert s["corner_f1"] == 1.0, s
    assert [o["kind"] for o in plan["openings"]] == ["passage"]
    # without the passage closing the room split still finds the two rooms (the gap is one
    # in a partition: its stubs run on from both ends, a room on either side); without
    # either the two rooms are one
    off = build_plan(bp, LayoutConfig(face_offset=0.0, max_passage=0.0))
    assert len(off["rooms"]) == 2 and [o["kind"] for o in off["openings"]] == ["passage"]
    off = build_plan(bp, LayoutConfig(face_offset=0.0, max_passage=0.0, room_split_h=0.0))
    assert len(off["rooms"]) == 1 and off["openings"] == []


def test_a_removed_object_leaves_the_plan(tmp_path):
    room = box(0, 0, 4, 3)
    bp = _raster([room], 0.12, [], 0.0)
    c = bp.grid.centers()
    labels = bp.labels.copy()
    table = affinity.rotate(box(1.0, 1.0, 2.2, 1.8), 20)  # 1.2 x 0.8 m, turned 20 degrees
    labels[contains_xy(table, c[..., 0], c[..., 1])] = 2
    classes = {**bp.classes, 2: "table"}
    plan = build_plan(Blueprint(labels, bp.grid, classes), GT_PLAN)
    (obj,) = plan["objects"]
    assert obj["class"] == "table" and obj["shape"] == "rect"
    assert (obj["width"], obj["depth"]) == pytest.approx((1.2, 0.8), abs=0.03)
    assert abs(obj["angle_deg"] - 20) < 2
    write_svg(plan, tmp_path / "before.svg")
    assert ">table<" in (tmp_path / "before.svg").read_text()
    labels[labels == 2] = 0  # the edit stage's plan: the removed object's cells become floor
    edited = build_plan(Blueprint(labels, bp.grid, classes), GT_PLAN)
    assert edited["objects"] == []
    write_svg(edited, tmp_path / "after.svg")
    assert ">table<" not in (tmp_path / "after.svg").read_text()
    assert edited["rooms"] == plan["rooms"]


def test_objects_outside_the_rooms_are_left_out_of_the_drawing():
    # a room whose walls are 0.12 m thick; a chair beyond the south wall (the next room's,
    # seen through a doorway), a cabinet against the east wall's inner face
    bp = _raster([box(0, 0, 4, 3)], 0.12, [], 0.0)
    c = bp.grid.centers()
    labels = bp.labels.copy()
    chair = box(1.2, -0.3, 1.8, -0.14)  # 0.6 x 0.16 m outside the wall band
    cabinet = box(3.4, 1.0, 4.0, 2.0)
    labels[contains_xy(chair, c[..., 0], c[..., 1])] = 2
    labels[contains_xy(cabinet, c[..., 0], c[..., 1])] = 3
    classes = {**bp.classes, 2: "chair", 3: "cabinet"}
    plan = build_plan(Blueprint(labels, bp.grid, classes), GT_PLAN)
    assert len(plan["rooms"]) == 1
    assert [o["class"] for o in plan["objects"]] == ["cabinet"]
    assert plan["objects_outside"] == 1


def test_blueprint_png_draws_the_walls_over_the_classes(tmp_path):
    t = 0.12
    ell = Polygon([(0, 0), (5, 0), (5, 2.5), (2.4, 2.5), (2.4, 4.5), (0, 4.5)])
    bp = _raster([ell], t, [box(1.0, -0.2, 1.85, 0.05)], 0.0)
    plan = build_plan(bp, GT_PLAN)
    (tmp_path / "plan.json").write_text(json.dumps(plan))
    none = tmp_path / "absent"
    png = tmp_path / "blueprint.png"
    given = ExportInputs(none, none, none, layout=tmp_path / "plan.json")
    pad = math.ceil(0.8 / bp.grid.cell)
    h, w = bp.labels.shape
    k = math.ceil(1400 / (max(h, w) + 2 * pad))
    left = bp.grid.origin[0] - pad * bp.grid.cell
    top = bp.grid.origin[1] + (h + pad) * bp.grid.cell

    def rgb(img: np.ndarray, xy) -> np.ndarray:  # noqa: ANN001
        x, y = np.asarray(xy, float).T
        cols = (24 + (x - left) / bp.grid.cell * k).astype(int)
        rows = (24 + (top - y) / bp.grid.cell * k).astype(int)
        return img[rows, cols]

    for inputs in (given,):  # the layout stage's plan
        export_picture(bp, inputs, png, "")
        img = np.asarray(Image.open(png).convert("RGB")).astype(int)
        assert max(img.shape[:2]) >= 1200
        # black along the middle of the walls (away from the door), the floor's colour
        # inside the room
        ring = ell.buffer(t / 2, join_style="mitre").exterior
        mid = np.array([ring.interpolate(s).coords[0] for s in np.linspace(0, ring.length, 80)])
        mid = mid[~((mid[:, 0] > 0.8) & (mid[:, 0] < 2.05) & (mid[:, 1] < 0))]
        assert (rgb(img, mid).max(1) < 30).all()
        assert (rgb(img, [[1.0, 1.0], [4.0, 1.5], [1.2, 3.8]]) == class_color(0)).all()
    # no layout plan given: the classes alone, at the plain picture's size
    export_picture(bp, ExportInputs(none, none, none), png, "")
    assert max(np.asarray(Image.open(png)).shape[:2]) < 1200
    # no room in the plan: the classes alone, as before
    export_picture(Blueprint(np.zeros((20, 30), np.uint8), bp.grid, {0: "floor"}), given, png, "")
    bare = {**plan, "rooms": [], "walls": [], "openings": []}
    (tmp_path / "plan.json").write_text(json.dumps(bare))
    export_picture(bp, given, png, "")
    assert max(Image.open(png).size) < 1200

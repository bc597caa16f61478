"""The L-shaped procedural room (`blunf synth --shape L`): its walls tile the wall band round
the outline, its camera loop and furniture stay inside, and its ground truth (gt/layout.json,
gt/blueprint.npz) agrees with the outline. Passages (`--passages`): wider gaps than doors,
some under a lintel, in the ground truth as they are in the mesh."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh
from shapely import contains_xy
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.layout.openings import scene_of
from stages.synth import make_room
from stages.synth.doors import PASSAGE
from stages.synth.render import camera_paths
from stages.synth.room import FLOOR, WALL, _ellipse, build_room
from stages.synth.shape import build_shaped_room, ell, faces_of


def test_walls_of_an_outline_tile_its_wall_band():
    # every notch corner: six walls whose boxes cover the band exactly once
    for corner in range(4):
        poly, tiles, meet = ell(6.0, 5.0, (2.5, 2.0), corner)
        assert len(poly) == 6 and Polygon(poly).exterior.is_ccw
        inside = Polygon(poly)
        assert inside.area == pytest.approx(30.0 - 5.0)
        t = 0.12
        band = inside.buffer(t, join_style="mitre").difference(inside)
        boxes = [box(b[0], b[2], b[1], b[3]) for b in (f.bounds for f in faces_of(poly, t, 2.6))]
        assert sum(b.area for b in boxes) == pytest.approx(band.area, abs=1e-9)
        union = unary_union(boxes)
        assert union.symmetric_difference(band).area < 1e-9  # no gap, no overlap (sum = area)
        # the floor tiles cover the L once; the arms meet in the square `meet`
        tb = [box(x0, y0, x1, y1) for x0, x1, y0, y1 in tiles]
        assert sum(b.area for b in tb) == pytest.approx(inside.area)
        assert unary_union(tb).symmetric_difference(inside).area < 1e-9
        m = box(meet[0], meet[2], meet[1], meet[3])
        assert m.area > 0 and inside.contains(m)
    # a rectangle's walls are the rectangular room's, named as gt/layout.json names them
    rect = ((0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0))
    faces = faces_of(rect, 0.1, 2.5)
    assert [f.name for f in faces] == ["wall_south", "wall_east", "wall_north", "wall_west"]
    assert faces[2].bounds == (-0.1, 4.1, 3.0, 3.1, 0.0, 2.5)
    assert faces[1].bounds == (4.0, 4.1, 0.0, 3.0, 0.0, 2.5)


@pytest.mark.parametrize("seed", [0, 4])
def test_l_room_loop_furniture_and_doors_inside(seed):
    room = build_shaped_room(seed, doors=2, shape="L")
    inside = Polygon(room.polygon)
    assert len(room.polygon) == 6
    assert len(room.loops) == 2 and room.loop == room.loops[0]
    for lp in room.loops:  # each arm's loop: well inside the L
        assert inside.buffer(-0.5).contains(_ellipse(*lp))
    for p in room.furniture:
        xy = np.asarray(p.mesh.vertices)[:, :2]
        assert contains_xy(inside.buffer(1e-6), xy[:, 0], xy[:, 1]).all(), p.name
    names = {p.name for p in room.parts}
    assert all(d.wall in names for d in room.doors) and len(room.doors) == 2
    # the cameras: half the views on each loop, every one inside the L
    poses = camera_paths(room, 9, seed)
    assert poses.shape == (9, 4, 4)
    assert contains_xy(inside.buffer(-0.5), poses[:, 0, 3], poses[:, 1, 3]).all()
    # the same seed's rectangle keeps its own bytes: its shape differs
    assert build_room(seed).polygon != room.polygon


def test_l_capture_ground_truth_agrees_with_the_outline(tmp_path):
    cap = make_room(tmp_path / "cap", views=1, seed=1, size=(16, 12), doors=2, shape="L")
    lay = read_json(cap / "gt" / "layout.json")
    room = read_json(cap / "gt" / "room.json")
    (r,) = lay["rooms"]
    poly = Polygon(r["polygon"])
    assert len(r["polygon"]) == 6 and r["polygon"] == room["outline"]
    assert r["area"] == pytest.approx(poly.area) and poly.exterior.is_ccw
    assert len(lay["walls"]) == 6
    assert sum(w["length"] for w in lay["walls"]) == pytest.approx(poly.length)
    bp = Blueprint.load(cap / "gt" / "blueprint.npz")

    def label(xy) -> int:
        row, col, ok = bp.grid.cell_of(np.asarray([xy], float))
        assert ok[0]
        return int(bp.labels[row[0], col[0]])

    t = lay["walls"][0]["thickness"]
    assert len(lay["openings"]) == 2
    for o in lay["openings"]:
        w = lay["walls"][o["wall"]]
        a, b = np.asarray(w["start"]), np.asarray(w["end"])
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([d[1], -d[0]])
        for end in (o["start"], o["end"]):  # on the wall's face, between its ends
            s = np.asarray(end) - a
            assert abs(s @ n) < 1e-9 and 0 < s @ d < w["length"]
        mid = (np.asarray(o["start"]) + o["end"]) / 2
        assert label(mid + n * t / 2) == FLOOR  # the floor runs through the gap
        s0, s1 = sorted((np.asarray(e) - a) @ d for e in (o["start"], o["end"]))
        assert s1 - s0 == pytest.approx(o["width"])
        for s in (s0 - 0.1, s1 + 0.1):  # wall on either side of the gap
            assert label(a + d * s + n * t / 2) == WALL
    # the notch is outside: nothing there; the reflex corner's wall is wall
    hull = poly.envelope.difference(poly)
    c = np.asarray(hull.representative_point().coords)[0]
    assert label(c) == UNKNOWN


@pytest.mark.parametrize(("seed", "shape"), [(3, "rect"), (4, "L")])
def test_passages_leave_the_doors_and_cut_wider_gaps_some_under_a_lintel(tmp_path, seed, shape):
    # rect seed 3: a passage under a lintel at 2.153 m; L seed 4: one full height, one under
    # a lintel at 2.241 m (the first passage is the same either way: its own random stream)
    n = 1 if shape == "rect" else 2
    plain = build_shaped_room(seed, doors=2, shape=shape)
    room = build_shaped_room(seed, doors=2, shape=shape, passages=n)
    doors = [d for d in room.doors if d.kind == "door"]
    passages = [d for d in room.doors if d.kind == "passage"]
    assert doors == list(plain.doors) and len(passages) == n
    walls = [d.wall for d in room.doors]
    assert len(set(walls)) == len(walls)  # distinct walls
    assert all(PASSAGE[0] <= p.width <= PASSAGE[1] for p in passages)
    assert any(p.top is not None for p in passages)

    cap = make_room(
        tmp_path / "cap", views=1, seed=seed, size=(16, 12), doors=2, shape=shape, passages=n
    )
    lay = read_json(cap / "gt" / "layout.json")
    got = [o for o in lay["openings"] if o["kind"] == "passage"]
    assert [o["width"] for o in got] == pytest.approx([p.width for p in passages])
    assert [o["top"] for o in got] == [room.height if p.top is None else p.top for p in passages]
    bp = Blueprint.load(cap / "gt" / "blueprint.npz")
    mesh = trimesh.load(cap / "gt" / "mesh.ply", force="mesh")
    scene = scene_of(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    for o in got:
        w = lay["walls"][o["wall"]]
        a, b = np.asarray(w["start"]), np.asarray(w["end"])
        d = (b - a) / np.linalg.norm(b - a)
        nrm = np.array([d[1], -d[0]])
        mid = (np.asarray(o["start"]) + o["end"]) / 2 + nrm * w["thickness"] / 2
        row, col, _ = bp.grid.cell_of(mid[None])
        # seen from above: the lintel (wall) over one, the floor through the other
        want = FLOOR if o["top"] == room.height else WALL
        assert bp.labels[row[0], col[0]] == want
        # the mesh: along the wall's middle at 1 m high nothing across the gap; cast up from
        # the threshold, the lintel's underside (nothing without one)
        e = np.subtract(o["end"], o["start"]) / o["width"]  # across the gap
        start = np.asarray(o["start"]) + e * 0.05 + nrm * w["thickness"] / 2
        rays = np.array([[*start, 1.0, *e, 0.0], [*mid, 0.05, 0.0, 0.0, 1.0]], np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        assert t[0] == pytest.approx(o["width"] - 0.05, abs=1e-3)
        assert t[1] == pytest.approx(o["top"] - 0.05, abs=1e-3) if want == WALL else np.isinf(t[1])


def test_more_gaps_than_walls_is_a_user_error(tmp_path):
    with pytest.raises(BlunfError, match="passages"):
        make_room(tmp_path / "cap", views=1, seed=3, size=(16, 12), doors=2, passages=3)
    with pytest.raises(BlunfError, match="passages"):
        make_room(tmp_path / "cap2", views=1, seed=3, size=(16, 12), passages=5)

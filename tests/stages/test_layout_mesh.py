"""The layout stage against a mesh shaped as fusion leaves it: surfaces one-sided, facing the
room (the side the views saw), a door's jamb leaning into the gap, floor missing where no view
saw it. Exact layouts built by hand, scored against their truth; and a procedural room's
passages read off its sensor-depth fusion."""

from __future__ import annotations

import numpy as np
import pytest
from shapely import contains_xy
from shapely.geometry import box

from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN, read_layout
from stages.common.io import read_json
from stages.evaluate.layout import score_layout
from stages.fusion import IMPLS as FUSION
from stages.fusion import FusionConfig, FusionInputs
from stages.layout import LayoutConfig
from stages.layout.openings import ceiling, enclosed, mesh_openings, scene_of
from stages.layout.walls import build_plan
from stages.synth import make_room

H = 2.5  # wall height, metres


class _Mesh:
    """Triangles [T, 3] over vertices [V, 3], built from one-sided quads."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []

    def quad(self, a, b, c, d) -> None:  # noqa: ANN001
        """A quad a-b-c-d (counter-clockwise seen from the side it faces)."""
        n = sum(len(v) for v in self.verts)
        self.verts.append(np.array([a, b, c, d], np.float64))
        self.tris.append(np.array([[0, 1, 2], [0, 2, 3]]) + n)

    def wall(self, p, q, z0: float = 0.0, z1: float = H) -> None:  # noqa: ANN001
        """A vertical face from p to q (xy), z0 to z1 high, facing left of p -> q."""
        self.quad((*q, z0), (*p, z0), (*p, z1), (*q, z1))

    def floor(self, x0, y0, x1, y1) -> None:  # noqa: ANN001
        self.quad((x0, y0, 0.0), (x1, y0, 0.0), (x1, y1, 0.0), (x0, y1, 0.0))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate(self.verts), np.concatenate(self.tris)


def _write_ply(path, verts: np.ndarray, tris: np.ndarray) -> None:  # noqa: ANN001
    import trimesh

    trimesh.Trimesh(verts, tris, process=False).export(path)


def _plan(parts: list, classes: dict) -> Blueprint:
    """A 2 cm blueprint over [-0.3, 6] x [-0.3, 3.3] m: each (polygon, class) painted in turn
    over unknown."""
    grid = Grid.covering(np.array([-0.3, -0.3]), np.array([6.0, 3.3]), 0.02)
    c = grid.centers()
    labels = np.full(grid.shape, UNKNOWN, np.uint8)
    for poly, k in parts:
        labels[contains_xy(poly, c[..., 0], c[..., 1])] = k
    return Blueprint(labels, grid, classes)


def test_a_door_is_read_where_the_face_starts_not_where_a_fused_jamb_closes_it():
    # the south wall's face at y = 0 (the room north of it), 0.12 m thick, a door from x = 1.0
    # to 1.9; its west jamb as fusion rounds a corner seen at a slant: the face bends back from
    # x = 0.98 to 4 cm deep at x = 1.05, 5 cm into the gap, then runs back to the wall's far side
    m = _Mesh()
    t = 0.12
    m.wall((1.9, 0.0), (3.0, 0.0))
    m.wall((1.9, -t), (1.9, 0.0))  # the east jamb, facing the gap
    m.wall((0.0, 0.0), (0.98, 0.0))
    m.wall((0.98, 0.0), (1.05, -0.04))  # the lean, facing the room
    m.wall((1.05, -0.04), (1.05, -t))
    m.wall((0.6, -1.0 - t), (2.3, -1.0 - t))  # a wall a metre past the door, facing it
    m.floor(0.0, 0.0, 3.0, 2.0)
    m.floor(1.0, -t, 1.9, 0.0)  # the floor runs through the door
    verts, tris = m.arrays()
    wall = {"start": [0.0, 0.0], "end": [3.0, 0.0], "thickness": t}
    (door,) = mesh_openings([wall], verts, tris, LayoutConfig())
    assert door["kind"] == "door"
    # where every ray passes the wall line the gap starts 5 cm late (the width 0.85); the
    # face's own depth ends at the true jamb
    xs = sorted((door["start"][0], door["end"][0]))
    assert xs == pytest.approx([1.0, 1.9], abs=0.01)
    assert door["width"] == pytest.approx(0.9, abs=0.01)


@pytest.mark.parametrize("fleck", [False, True])
def test_a_fleck_of_noise_in_a_passage_does_not_cut_it(fleck):
    # a 1.7 m passage from x = 1.0 to 2.7 in the south wall (the room north of it); a fleck
    # of stereo's noise 1 cm wide floats 3 cm inside the room at 1 m high, beside x = 2.29
    m = _Mesh()
    t = 0.12
    m.wall((0.0, 0.0), (1.0, 0.0))
    m.wall((1.0, -t), (1.0, 0.0))
    m.wall((2.7, 0.0), (4.0, 0.0))
    m.wall((2.7, 0.0), (2.7, -t))
    m.floor(0.0, -2.0, 4.0, 2.0)  # the floor runs through into the next room
    if fleck:
        m.quad((2.285, 0.03, 0.95), (2.295, 0.03, 0.95), (2.295, 0.03, 1.05), (2.285, 0.03, 1.05))
    wall = {"start": [0.0, 0.0], "end": [4.0, 0.0], "thickness": t}
    (o,) = mesh_openings([wall], *m.arrays(), LayoutConfig())
    assert o["kind"] == "passage"
    assert sorted((o["start"][0], o["end"][0])) == pytest.approx([1.0, 2.7], abs=0.02)


def test_a_window_is_a_hole_in_a_wall_not_a_wall_seen_only_low_down():
    t = 0.12
    seen_low = _Mesh()  # the views saw this wall up to 0.8 m only (far off, at a slant)
    seen_low.wall((0.0, 0.0), (3.0, 0.0), 0.0, 0.8)
    seen_low.floor(0.0, 0.0, 3.0, 2.0)
    window = _Mesh()  # a 1 m window from x = 1 to 2, 0.8 to 2.0 m high
    window.wall((0.0, 0.0), (1.0, 0.0))
    window.wall((2.0, 0.0), (3.0, 0.0))
    window.wall((1.0, 0.0), (2.0, 0.0), 0.0, 0.8)
    window.wall((1.0, 0.0), (2.0, 0.0), 2.0, H)
    window.floor(0.0, 0.0, 3.0, 2.0)
    wall = {"start": [0.0, 0.0], "end": [3.0, 0.0], "thickness": t}
    assert mesh_openings([wall], *seen_low.arrays(), LayoutConfig()) == []
    (o,) = mesh_openings([wall], *window.arrays(), LayoutConfig())
    assert o["kind"] == "window" and o["width"] == pytest.approx(1.0, abs=0.03)


def _room_mesh(shadow: tuple[float, float, float, float]) -> _Mesh:
    """A 4 x 3 m room of fused surfaces: walls facing in, the floor missing over `shadow`
    (x0, y0, x1, y1), a stretch against the north wall no view saw."""
    m = _Mesh()
    corners = [(0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0)]
    for p, q in zip(corners, corners[1:] + corners[:1], strict=True):
        m.wall(p, q)  # counter-clockwise: facing into the room
    x0, y0, x1, y1 = shadow
    m.floor(0.0, 0.0, 4.0, y0)
    m.floor(0.0, y0, x0, 3.0)
    m.floor(x1, y0, 4.0, 3.0)
    return m


def test_floor_no_view_saw_inside_the_walls_is_the_room_outside_them_is_none(tmp_path):
    t = 0.12
    shadow = (1.5, 2.2, 2.7, 3.0)  # 1.2 x 0.8 m against the north wall (behind a bed)
    verts, tris = _room_mesh(shadow).arrays()
    scene = scene_of(verts, tris)
    # inside the walls every way meets a wall's face; beyond the east wall its back
    inside = enclosed(scene, np.array([[2.1, 2.6], [0.3, 0.3], [4.8, 1.5], [5.6, 0.2]]))
    assert inside.tolist() == [True, True, False, False]

    # the plan: the room's floor, walls 0.12 m thick, and east of it the field's floor filling
    # a closed space of 1.5 x 3 m that no view saw (as an L's notch)
    bp = _plan(
        [(box(-t, -t, 5.6 + t, 3 + t), 1), (box(0, 0, 4, 3), 0), (box(4 + t, 0, 5.6, 3), 0)],
        {0: "floor", 1: "wall"},
    )
    _write_ply(tmp_path / "mesh.ply", verts, tris)
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    # one room, its outline along the north wall behind the shadow (not round it)
    _assert_the_4x3_room(plan)


def _assert_the_4x3_room(plan: dict) -> None:
    """`plan` draws one room, the 4 x 3 m rectangle from the origin, within 2 cm."""
    gt = {"rooms": [{"polygon": [[0, 0], [4, 0], [4, 3], [0, 3]]}], "openings": []}
    s = score_layout(plan, gt)
    assert len(plan["rooms"]) == 1, plan["rooms"]
    assert s["corner_f1"] == s["angle_f1"] == 1.0, s
    assert s["wall_length_err_m"] <= 0.02, s


def test_floor_behind_a_tall_cabinet_before_a_wall_no_view_fused_is_the_room(tmp_path):
    # a 4 x 3 m room whose north wall the views fused only east of x = 2.4 (photos alone: a
    # plain stretch behind a cabinet); the cabinet, 1.9 m tall, stands 10 cm off that wall
    # from x = 0.8 to 1.9, its front and sides fused, its back not; no floor was fused behind
    # it, under it or west of it up to the wall. Rays from there meet the cabinet's back and
    # nothing, no wall's back: the room, not ground outside its walls
    t, z = 0.12, 1.9
    m = _Mesh()
    m.wall((0.0, 0.0), (4.0, 0.0))
    m.wall((4.0, 0.0), (4.0, 3.0))
    m.wall((4.0, 3.0), (2.4, 3.0))
    m.wall((0.0, 3.0), (0.0, 0.0))
    m.wall((0.8, 2.4), (1.9, 2.4), 0.0, z)  # the cabinet's front, facing the room
    m.wall((0.8, 2.9), (0.8, 2.4), 0.0, z)  # its west side
    m.wall((1.9, 2.4), (1.9, 2.9), 0.0, z)  # its east side
    m.floor(0.0, 0.0, 4.0, 2.2)
    m.floor(2.4, 2.2, 4.0, 3.0)
    verts, tris = m.arrays()
    _write_ply(tmp_path / "mesh.ply", verts, tris)
    # the plan: the walls all round (the field draws the north wall on), floor under and
    # behind the cabinet (the floor seen through its unfused front), the front as object
    bp = _plan(
        [
            (box(-t, -t, 4 + t, 3 + t), 1),
            (box(0, 0, 4, 3), 0),
            (box(0.8, 2.36, 1.9, 2.44), 2),
        ],
        {0: "floor", 1: "wall", 2: "object"},
    )
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    # before, the floor there was dropped (a quarter of the rays met nothing): the outline
    # stepped round it 0.8 m inside the north wall
    _assert_the_4x3_room(plan)


def test_walls_are_drawn_on_the_mesh_faces_not_on_the_plan_cells(tmp_path):
    # a 4 x 3 m room whose mesh has its faces where they are; the plan's walls start 4 cm
    # inside the east and north faces and 2 cm outside the west one (the field's boundary
    # wanders by a few cells), a sofa 30 cm off the north wall; the east wall's back face,
    # 0.12 m behind its face, seen from the next room
    t = 0.12
    m = _room_mesh((0.0, 3.0, 0.0, 3.0))  # all the floor seen
    m.wall((1.0, 2.4), (2.5, 2.4), 0.0, 0.8)  # the sofa's front, below most of the rays
    m.wall((4 + t, 3.0), (4 + t, 0.0))  # facing east, away from the room
    verts, tris = m.arrays()
    _write_ply(tmp_path / "mesh.ply", verts, tris)
    bp = _plan(
        [(box(-t, -t, 4 + t, 3 + t), 1), (box(-0.02, 0, 3.96, 2.96), 0)],
        {0: "floor", 1: "wall"},
    )
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    gt = {"rooms": [{"polygon": [[0, 0], [4, 0], [4, 3], [0, 3]]}], "openings": []}
    s = score_layout(plan, gt)
    # traced on the plan's cells: 3.98 x 2.96 m, the median wall length 4 cm off
    assert s["corner_f1"] == 1.0 and s["wall_length_err_m"] <= 0.005, s
    assert plan["rooms"][0]["area"] == pytest.approx(12.0, abs=0.03)
    east = [
        w for w in plan["walls"] if abs(w["start"][0] - w["end"][0]) < 1e-6 and w["start"][0] > 2
    ]
    # the east wall's thickness is read between its two faces; the others show one face only:
    # the default, not the plan's band behind them (0.12 m, 0.16 m behind the north face)
    assert east[0]["thickness"] == pytest.approx(t, abs=0.01)
    rest = [w["thickness"] for w in plan["walls"] if w is not east[0]]
    assert rest == [LayoutConfig().default_thickness] * 3


def test_a_closed_space_of_objects_is_no_room():
    # east of a 4 x 3 m room, a 1.5 x 3 m closed space labelled object with a 0.5 x 0.5 m
    # speck of floor (stereo's noise behind a photos-only plan's walls)
    t = 0.12
    bp = _plan(
        [
            (box(-t, -t, 5.6 + t, 3 + t), 1),
            (box(0, 0, 4, 3), 0),
            (box(4 + t, 0, 5.6, 3), 2),
            (box(4.5, 1.0, 5.0, 1.5), 0),
        ],
        {0: "floor", 1: "wall", 2: "object"},
    )
    plan = build_plan(bp, LayoutConfig(face_offset=0.0))
    assert len(plan["rooms"]) == 1
    assert plan["rooms"][0]["area"] == pytest.approx(12.0, rel=0.01)


def test_passages_of_a_sensor_depth_room_are_found_with_their_widths(tmp_path):
    # the procedural room of seed 7 with two passages (1.74 m under a lintel at 2.07 m in the
    # east wall, 1.53 m full height in the west one), 16 views of 160x120 with sensor depth
    # fused at 2 cm; the plan is the exact one, the openings are read off the fused mesh.
    # Measured: both found, 1.76 and 1.55 m wide (2.7 cm off at most), every corner in place.
    cap = make_room(tmp_path / "cap", views=16, seed=7, size=(160, 120), passages=2)
    read_layout(cap).save(tmp_path / "frames.json")
    (tmp_path / "fusion").mkdir()
    fused = FUSION["tsdf"](
        FusionConfig(), FusionInputs(tmp_path / "frames.json"), tmp_path / "fusion"
    )
    bp = Blueprint.load(cap / "gt" / "blueprint.npz")
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), fused.mesh)
    gt = read_json(cap / "gt" / "layout.json")
    assert sorted(o["kind"] for o in gt["openings"]) == ["passage", "passage"]
    assert any(o["top"] < 2.2 for o in gt["openings"])  # one under a lintel
    s = score_layout(plan, gt)
    assert s["passages_found"] == s["passages_total"] == 2, s
    assert s["passage_width_err_m"] <= 0.05, s
    assert s["doors_found"] == s["doors_total"] == 0, s
    assert s["corner_f1"] == s["angle_f1"] == 1.0, s
    assert [o["kind"] for o in plan["openings"]] == ["passage", "passage"]


def test_an_objects_footprint_is_where_its_surfaces_stand(tmp_path):
    # a 1.2 x 0.6 m island, 0.9 m high, in the 4 x 3 m room; the plan paints object over
    # 2.0 x 1.4 m round it (the field fills floor no view saw with the nearest object)
    m = _room_mesh((0.0, 3.0, 0.0, 3.0))
    x0, y0, x1, y1, h = 1.4, 1.2, 2.6, 1.8, 0.9
    m.quad((x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h))  # its top, facing up
    m.wall((x0, y0), (x1, y0), 0.0, h)  # its south front (the other sides alike)
    verts, tris = m.arrays()
    _write_ply(tmp_path / "mesh.ply", verts, tris)
    bp = _plan(
        [(box(-0.12, -0.12, 4.12, 3.12), 1), (box(0, 0, 4, 3), 0), (box(1.0, 0.8, 3.0, 2.2), 2)],
        {0: "floor", 1: "wall", 2: "object"},
    )
    (obj,) = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")["objects"]
    assert (obj["width"], obj["depth"]) == pytest.approx((x1 - x0, y1 - y0), abs=0.03)
    assert obj["center"] == pytest.approx([2.0, 1.5], abs=0.02)
    assert obj["height"] == pytest.approx(h, abs=0.01) and obj["top"] == pytest.approx(h, abs=0.01)


@pytest.mark.parametrize(("top", "fused"), [(1.6, 4.0), (H, 4.0), (1.6, 1.6)])
def test_a_tall_cabinet_the_plan_drew_as_wall_is_no_notch_in_the_room(tmp_path, top, fused):
    # a 4 x 3 m room under a ceiling; against its south wall a cabinet 0.9 m wide and 0.5 m
    # deep that the plan labelled wall (the 3-room home's living room: a notch of four corners
    # it does not have). Above a 1.6 m cabinet the mesh shows the wall's face: the outline
    # runs along it. Up to the ceiling (a pillar, a chimney breast) it is the room's shape.
    # The ceiling fused from x = 0 to `fused` only (40 % of the floor: the 3-room home's
    # sensor mesh holds its ceiling over 46-49 % of the floor) is the ceiling all the same
    t = 0.12
    m = _Mesh()
    corners = [(0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0)]
    for p, q in zip(corners, corners[1:] + corners[:1], strict=True):
        m.wall(p, q)
    m.wall((1.9, 0.0), (1.9, 0.5), 0.0, top)  # the cabinet's west side, facing west
    m.wall((1.9, 0.5), (2.8, 0.5), 0.0, top)  # its front, facing north
    m.wall((2.8, 0.5), (2.8, 0.0), 0.0, top)  # its east side
    m.quad((1.9, 0.0, top), (2.8, 0.0, top), (2.8, 0.5, top), (1.9, 0.5, top))  # its top
    m.floor(0.0, 0.0, 4.0, 3.0)
    m.quad((0.0, 0.0, H), (0.0, 3.0, H), (fused, 3.0, H), (fused, 0.0, H))  # the ceiling
    verts, tris = m.arrays()
    _write_ply(tmp_path / "mesh.ply", verts, tris)
    bp = _plan(
        [(box(-t, -t, 4 + t, 3 + t), 1), (box(0, 0, 4, 3), 0), (box(1.9, 0, 2.8, 0.5), 1)],
        {0: "floor", 1: "wall"},
    )
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    if top < H:
        _assert_the_4x3_room(plan)
        assert plan["rooms"][0]["area"] == pytest.approx(12.0, abs=0.05)
    else:
        assert len(plan["rooms"][0]["polygon"]) == 8, plan["rooms"]


def test_a_ceiling_fused_in_patches_is_the_ceiling_furniture_overhead_is_none():
    # rays up from the floor points of a 4 x 3 m room, every 10 cm: a ceiling fused over 40 %
    # of the floor is the ceiling, at its height; without one, the undersides of a table
    # (0.7 m) and of a shelf (1.8 m) over 15 % of the floor each are no level surface
    x, y = np.meshgrid(np.arange(0.05, 4.0, 0.1), np.arange(0.05, 3.0, 0.1))
    floor = np.stack([x.ravel(), y.ravel()], 1)
    furniture = _Mesh()
    furniture.quad((0.0, 0.0, 0.7), (0.0, 1.8, 0.7), (1.0, 1.8, 0.7), (1.0, 0.0, 0.7))
    furniture.quad((3.4, 0.0, 1.8), (3.4, 3.0, 1.8), (4.0, 3.0, 1.8), (4.0, 0.0, 1.8))
    assert ceiling(scene_of(*furniture.arrays()), floor) is None
    patch = _Mesh()
    patch.quad((0.0, 0.0, H), (0.0, 3.0, H), (1.6, 3.0, H), (1.6, 0.0, H))
    assert ceiling(scene_of(*patch.arrays()), floor) == pytest.approx(H, abs=1e-3)


def test_an_open_side_is_no_opening_across_its_whole_length(tmp_path):
    # a 4 x 3 m room open to the south: no wall there, the fused floor running on 1 m beyond
    # the side where the plan stops (its field called it unknown). The closing wall is
    # inferred, all of it a gap: no door or passage spans it (the 3-room home from photos drew
    # a 3.96 m "passage" along such a side, where a wall no view saw stands)
    t = 0.12
    m = _Mesh()
    m.wall((4.0, 0.0), (4.0, 3.0))
    m.wall((4.0, 3.0), (0.0, 3.0))
    m.wall((0.0, 3.0), (0.0, 0.0))
    m.floor(0.0, -1.0, 4.0, 3.0)
    verts, tris = m.arrays()
    _write_ply(tmp_path / "mesh.ply", verts, tris)
    bp = _plan([(box(-t, 0, 4 + t, 3 + t), 1), (box(0, 0, 4, 3), 0)], {0: "floor", 1: "wall"})
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    assert len(plan["rooms"]) == 1
    south = [w for w in plan["walls"] if max(w["start"][1], w["end"][1]) < 0.1]
    assert len(south) == 1 and not south[0]["seen"], plan["walls"]
    assert plan["openings"] == [], plan["openings"]


def test_a_door_in_a_partition_the_mesh_lacks_is_read_off_the_plan(tmp_path):
    # two rooms of a home side by side, 2.8 and 2.68 x 3 m, a partition 0.12 m thick between
    # them at x = 2.8 to 2.92 with a 0.9 m door from y = 1.0 to 1.9; the plan holds the
    # partition (the views' readings), the mesh neither of its faces: stereo fused the outer
    # walls and the floors, and no ray cast along the partition meets anything
    t = 0.12
    m = _Mesh()
    corners = [(0.0, 0.0), (5.6, 0.0), (5.6, 3.0), (0.0, 3.0)]
    for p, q in zip(corners, corners[1:] + corners[:1], strict=True):
        m.wall(p, q)
    m.floor(0.0, 0.0, 2.8, 3.0)
    m.floor(2.8 + t, 0.0, 5.6, 3.0)
    _write_ply(tmp_path / "mesh.ply", *m.arrays())
    bp = _plan(
        [
            (box(-t, -t, 5.6 + t, 3 + t), 1),
            (box(0, 0, 5.6, 3), 0),
            (box(2.8, 0, 2.8 + t, 1.0), 1),
            (box(2.8, 1.9, 2.8 + t, 3), 1),
        ],
        {0: "floor", 1: "wall"},
    )
    plan = build_plan(bp, LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    assert len(plan["rooms"]) == 2
    (door,) = plan["openings"]
    assert door["kind"] == "door" and door["rooms"] == [0, 1]
    assert door["width"] == pytest.approx(0.9, abs=0.03)
    assert sorted((door["start"][1], door["end"][1])) == pytest.approx([1.0, 1.9], abs=0.03)
    assert door["start"][0] == pytest.approx(door["end"][0]) and 2.78 <= door["start"][0] <= 2.94

"""What the plan knows: cells near a projected point, cells free-space rays crossed, the room's
extent; the blueprint's seen / inside; walls the outline closes over unseen space drawn
inferred (plan.json, plan.svg, plan.dxf); the observation metrics worked out by hand."""

from __future__ import annotations

import ezdxf
import numpy as np
from shapely import contains_xy
from shapely.geometry import box

from stages.common.blueprint import Blueprint, Grid, read_observed
from stages.common.capture import UNKNOWN
from stages.common.io import read_json, save_npz
from stages.evaluate.observation import invented_pct, vertical_points, wall_support
from stages.layout import LayoutConfig
from stages.layout.draw import write_dxf, write_svg
from stages.layout.walls import build_plan
from stages.project.observed import observed, point_distance, ray_cells, room_inside

GRID = Grid((0.0, 0.0), 0.1, (10, 20))  # 2 m east x 1 m north, 10 cm cells


def test_near_cells_have_a_point_within_the_radius():
    # one point at the centre of the cell at x 0.45, y 0.55 (row 4, col 4)
    xy = np.array([[0.45, 0.55]])
    dist = point_distance(GRID, xy)
    exact = np.linalg.norm(GRID.centers() - xy[0], axis=-1)
    assert np.all(dist >= exact - 1e-9)  # an upper bound: a near cell always has its point
    assert dist[4, 4] <= 0.071  # half a cell's diagonal off at most
    near, free, _ = observed(GRID, xy, np.zeros((1, 2)), np.zeros(1, int), 0.25, 0)
    # 0.1 m east: near (bound 0.17 m); 0.2 m east: its bound 0.27 m is past 0.25, so not near
    # (a point anywhere in that cell might lie 0.27 m off); 0.3 m: not
    assert near[4, 4] and near[4, 5] and near[3, 5] and not near[4, 6] and not near[4, 7]
    assert not free.any()  # no rays asked for


def test_a_ray_marks_the_cells_it_crosses():
    # a camera at (0.05, 0.55) looking east to a point at (1.55, 0.55): row 4, cols 0..15
    cells = ray_cells(GRID, np.array([[0.05, 0.55]]), np.array([[1.55, 0.55]]))
    assert cells[4, :16].all() and cells.sum() == 16


def test_the_room_extent_fills_holes_but_not_the_world():
    near = np.zeros((10, 20), bool)
    near[2:8, 2:18] = True
    near[4:6, 8:12] = False  # a hole inside (a table top seen, the floor under it not)
    inside = room_inside(near, np.zeros_like(near), 0)
    assert inside[4:6, 8:12].all()  # the hole is the room's
    assert not inside[0].any() and not inside[:, 19].any()  # beyond the views: outside


def test_blueprint_keeps_seen_and_inside_and_counts_its_cells(tmp_path):
    labels = np.zeros((4, 5), np.uint8)
    labels[:, 4] = UNKNOWN  # a column outside
    labels[0, 0] = UNKNOWN  # a cell inside, too far from what was seen to guess
    seen = np.ones((4, 5), np.uint8)
    seen[:, 3] = 0  # labelled but unseen: inferred
    seen[:, 4] = 0
    inside = np.ones((4, 5), np.uint8)
    inside[:, 4] = 0
    grid = Grid((0.0, 0.0), 0.5, (4, 5))
    Blueprint(labels, grid, {0: "floor"}, None, seen, inside).save(tmp_path / "b.npz")
    bp = Blueprint.load(tmp_path / "b.npz")
    assert np.array_equal(bp.seen, seen) and np.array_equal(bp.inside, inside)
    # 20 cells: seen 11 (12 seen cells but one unknown), inferred 4, unknown 1, outside 4
    assert bp.shares() == {
        "seen_pct": 55.0,
        "inferred_pct": 20.0,
        "unknown_pct": 5.0,
        "outside_pct": 20.0,
    }


def test_read_observed_names_a_bad_file(tmp_path):
    save_npz(tmp_path / "o.npz", near=np.zeros((2, 2), np.uint8))
    try:
        read_observed(tmp_path / "o.npz", (2, 2))
    except Exception as e:  # noqa: BLE001 - the message is what is checked
        assert "o.npz" in str(e) and "observed" in str(e)
    else:
        raise AssertionError("a file without inside / labelled was read")


def _open_room() -> Blueprint:
    """A 4 x 3 m room with 0.12 m walls on its north, west and south sides; its east side
    opens onto space no view reached (unknown beyond x = 4.0)."""
    grid = Grid.covering(np.array([-0.3, -0.3]), np.array([4.0, 3.3]), 0.02)
    c = grid.centers()
    x, y = c[..., 0], c[..., 1]
    labels = np.full(grid.shape, UNKNOWN, np.uint8)
    labels[contains_xy(box(0, 0, 4.0, 3), x, y)] = 0
    walls = box(-0.12, -0.12, 4.0, 3.12).difference(box(0, 0, 4.0, 3))
    labels[contains_xy(walls, x, y)] = 1
    lab = labels != UNKNOWN
    return Blueprint(labels, grid, {0: "floor", 1: "wall"}, None, lab, lab)


def test_the_open_side_is_an_inferred_wall_drawn_dashed(tmp_path):
    plan = build_plan(_open_room(), LayoutConfig(face_offset=0.0))
    assert len(plan["rooms"]) == 1 and plan["rooms"][0]["continues"]
    east = [w for w in plan["walls"] if min(w["start"][0], w["end"][0]) > 3.8]
    rest = [w for w in plan["walls"] if w not in east]
    assert len(east) == 1 and east[0]["seen"] is False, plan["walls"]
    assert len(rest) == 3 and all(w["seen"] for w in rest), plan["walls"]
    write_svg(plan, tmp_path / "plan.svg")
    svg = (tmp_path / "plan.svg").read_text()
    assert svg.count("wall-inferred") == 1 and "stroke-dasharray" in svg
    assert "continues" in svg
    write_dxf(plan, tmp_path / "plan.dxf")
    doc = ezdxf.readfile(tmp_path / "plan.dxf")
    inferred = doc.modelspace().query('LWPOLYLINE[layer=="WALLS_INFERRED"]')
    assert len(inferred) == 1
    xs = [p[0] for p in inferred[0].get_points()]
    assert min(xs) >= 3.95  # the east wall's band, from its face outwards
    assert doc.layers.get("WALLS_INFERRED").dxf.linetype == "DASHED"


def test_invented_cells_by_hand():
    # 20 labelled cells of 10 cm in a row; one point at x = 0.05: cells whose centre lies
    # within 0.25 m are the first three (0.05, 0.15, 0.25 m from it), the other 17 invented
    grid = Grid((0.0, 0.0), 0.1, (1, 20))
    bp = Blueprint(np.zeros((1, 20), np.uint8), grid, {0: "floor"})
    assert invented_pct(bp, np.array([[0.05, 0.05]])) == 85.0


def test_observation_from_the_runs_own_files(tmp_path):
    """A plan that carries no seen / inside (another method's) and no points: the shares and
    the invented cells come from observed.npz, worked out by hand."""
    from stages.evaluate.gt import EvaluateConfig, EvaluateInputs, run

    labels = np.zeros((4, 5), np.uint8)
    labels[:, 4] = UNKNOWN  # outside
    labels[0, 0] = UNKNOWN  # inside, unknown
    near = np.ones((4, 5), np.uint8)
    near[:, 3:] = 0  # column 3 labelled but no observation near: inferred, invented
    inside = np.ones((4, 5), np.uint8)
    inside[:, 4] = 0
    grid = Grid((0.0, 0.0), 0.5, (4, 5))
    Blueprint(labels, grid, {0: "floor"}).save(tmp_path / "b.npz")
    z = np.zeros((4, 5), np.uint8)
    save_npz(tmp_path / "observed.npz", near=near, free=z, inside=inside, labelled=inside)
    frames = tmp_path / "frames.json"
    frames.write_text('{"root": ".", "kind": "t", "classes": {}, "frames": []}')
    ins = EvaluateInputs(frames, None, (tmp_path / "b.npz",), ("blunf",), False,
                         observed=tmp_path / "observed.npz")  # fmt: skip
    out = tmp_path / "ev"
    out.mkdir()
    got = read_json(run(EvaluateConfig(), ins, out).metrics)["observation"]
    # 20 cells: seen 11, inferred 4, unknown 1, outside 4; 15 labelled, 4 of them not near
    assert got == {
        "seen_pct": 55.0,
        "inferred_pct": 20.0,
        "unknown_pct": 5.0,
        "outside_pct": 20.0,
        "labelled_pct": 75.0,
        "invented_pct": round(100 * 4 / 15, 3),
    }


def test_seen_wall_support_by_hand():
    # a vertical surface along x = 0 from y = 0 to 1 (points every cm, 0.1 to 1.5 m high)
    ys = np.arange(0.0, 1.0, 0.01)
    zs = np.linspace(0.1, 1.5, 8)
    wall = np.array([[0.0, y, z] for y in ys for z in zs])
    flat = np.array([[0.5, y, 0.9] for y in np.arange(1.0, 2.0, 0.01)])  # a table top
    xyz = np.concatenate([wall, flat])
    assert len(vertical_points(xyz)) == len(wall)  # the table top is no vertical surface
    walls = [  # 5 cm off the surface along y 0..2: supported from 0 to the last point (0.99)
        # and on while it lies within 10 cm: sqrt(0.1^2 - 0.05^2) = 0.0866 m more, 53.8 %
        {"start": [0.05, 0.0], "end": [0.05, 2.0], "length": 2.0, "seen": True},
        {"start": [3.0, 0.0], "end": [3.0, 1.0], "length": 1.0, "seen": False},
    ]
    s = wall_support(walls, xyz)
    assert s["seen_wall_m"] == 2.0 and s["inferred_wall_m"] == 1.0
    assert abs(s["seen_wall_support_pct"] - 53.8) <= 0.3, s
    # a doorway over the unsupported half (y 1.2 to 2.0) is no drawn wall: 1.2 m drawn, of
    # which 1.0766 m supported
    door = [{"wall": 0, "start": [0.05, 1.2], "end": [0.05, 2.0]}]
    s = wall_support(walls, xyz, door)
    assert abs(s["seen_wall_m"] - 1.2) < 0.01 and abs(s["seen_wall_support_pct"] - 89.7) <= 0.5

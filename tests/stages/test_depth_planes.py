"""Plane fill (stages/depth/planes): the expansion solver against brute force, the plane
hypotheses on exact synthetic points, and fill() on a plain procedural room whose blank
walls stereo cannot read, against the room's exact depth."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from stages.common.camera import pixel_grid
from stages.common.capture import read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label
from stages.depth.planes import PlanesConfig
from stages.depth.planes import filling as planes_fill
from stages.depth.planes.appearance import colour_cost, plane_colours
from stages.depth.planes.bases import wall_feet
from stages.depth.planes.filling import fill
from stages.depth.planes.geometry import plane_depth, plane_valid, rays
from stages.depth.planes.hypotheses import Plane, find_planes, floor_axes, room_axes
from stages.depth.planes.merge import merge_view
from stages.depth.planes.solve import energy, expand
from stages.depth.planes.view import Labelling, ViewData, data_costs


def test_expansion_reaches_the_optimum_of_tiny_graphs():
    rng = np.random.default_rng(0)
    n, labels = 6, 3
    exact = 0
    for _ in range(30):
        unary = rng.random((n, labels)) * 2
        edges = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.6])
        edges = edges.reshape(-1, 2)
        # a metric pair cost per edge: weight x (symmetric costs in [1, 1.5] off the diagonal,
        # so every triangle inequality holds): expansion moves are exact there
        w = rng.random(len(edges))
        m = 1 + 0.5 * rng.random((len(edges), labels, labels))
        m = (m + m.transpose(0, 2, 1)) / 2 * w[:, None, None]
        m[:, np.arange(labels), np.arange(labels)] = 0

        def pair(e, a, b, m=m):
            return m[e, a, b]

        x, e = expand(unary, edges, pair, cycles=5)
        assert e == pytest.approx(energy(x, unary, edges, pair))
        every = [
            energy(np.array(lab), unary, edges, pair)
            for lab in itertools.product(range(labels), repeat=n)
        ]
        opt = min(every)
        # the expansion-move bound (Boykov et al. 2001): within 2 x max/min pair cost ratio
        assert e <= 3 * opt + 1e-9
        # and no single expansion move from the result lowers the energy (max-flow is exact)
        for alpha in range(labels):
            for mask in itertools.product((0, 1), repeat=n):
                y = np.where(np.array(mask) == 1, alpha, x)
                assert energy(y, unary, edges, pair) >= e - 1e-3
        exact += e <= opt + 1e-3
    assert exact >= 27  # on these tiny graphs it nearly always finds the optimum itself


def _patch(rng, n, fixed_axis, value, lo, hi, normal):
    p = rng.uniform(lo, hi, (n, 3))
    p[:, fixed_axis] = value + rng.normal(0, 0.003, n)  # 3 mm noise
    return p, np.tile(normal, (n, 1))


def _floor_two_walls_and_a_table(rng) -> list:
    return [
        _patch(rng, 20000, 2, 0.0, (0, 0, 0), (3, 3, 0), (0, 0, 1)),  # floor
        _patch(rng, 15000, 0, 0.0, (0, 0, 0), (0, 3, 2.5), (1, 0, 0)),  # wall x = 0
        _patch(rng, 15000, 1, 3.0, (0, 3, 0), (3, 3, 2.5), (0, -1, 0)),  # wall y = 3
        _patch(rng, 4000, 2, 0.75, (1, 1, 0), (2, 1.8, 0), (0, 0, 1)),  # table top
    ]


def test_hypotheses_on_a_floor_two_walls_and_a_table():
    rng = np.random.default_rng(1)
    parts = _floor_two_walls_and_a_table(rng)
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    planes = find_planes(pts, nrm, PlanesConfig())
    assert planes[0].kind == "floor" and abs(planes[0].offset) < 0.005
    got = {(p.kind, tuple(np.round(np.abs(p.normal)).astype(int))): p for p in planes}
    assert abs(abs(got["wall", (1, 0, 0)].offset) - 0.0) < 0.005
    assert abs(abs(got["wall", (0, 1, 0)].offset) - 3.0) < 0.005
    top = got["top", (0, 0, 1)]
    assert abs(top.offset - 0.75) < 0.005
    # the table top's support box is the table's extent (2nd-98th percentile of inliers)
    np.testing.assert_allclose(top.lo[:2], [1.02, 1.02], atol=0.03)
    np.testing.assert_allclose(top.hi[:2], [1.98, 1.78], atol=0.03)
    assert len(planes) == 4
    for p in planes:
        assert np.degrees(np.arccos(np.max(np.abs(p.normal)))) < 0.5


def test_a_leaning_board_gets_a_plane_of_its_own():
    """A board leaning 13 degrees back (a sofa's back, a whiteboard on its stand) has no peak
    along the room's axes; free_planes finds it among the points they leave, with its
    normal and offset, and only it: the floor, walls and table keep theirs."""
    rng = np.random.default_rng(2)
    parts = _floor_two_walls_and_a_table(rng)
    lean = np.radians(13.0)
    n = np.array([0.0, -np.cos(lean), np.sin(lean)])  # faces the room (-y) and up
    u = rng.uniform(0.5, 2.5, 3000)  # along x
    v = rng.uniform(0.0, 1.2, 3000)  # up the board
    up = np.array([0.0, np.sin(lean), np.cos(lean)])  # in the board, leaning back (+y)
    board = np.array([0.0, 2.5, 0.0]) + u[:, None] * [1.0, 0, 0] + v[:, None] * up
    board += rng.normal(0, 0.003, (3000, 1)) * n
    parts.append((board, np.tile(n, (3000, 1))))
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    planes = find_planes(pts, nrm, PlanesConfig())
    on_axis = [np.degrees(np.arccos(np.max(np.abs(p.normal)))) < 0.5 for p in planes]
    axis = [p for p, a in zip(planes, on_axis, strict=True) if a]
    free = [p for p, a in zip(planes, on_axis, strict=True) if not a]
    assert len(free) == 1
    (b,) = free
    assert b.kind == "front" and np.degrees(np.arccos(abs(b.normal @ n))) < 1.0
    assert abs(b.offset * np.sign(b.normal @ n) - n @ [0.0, 2.5, 0.0]) < 0.01
    np.testing.assert_allclose(b.lo[2], 0.0, atol=0.05)  # its box is the board's
    np.testing.assert_allclose(b.hi[2], 1.2 * np.cos(lean), atol=0.05)
    assert {p.kind for p in axis} >= {"floor", "wall", "top"}
    none = find_planes(pts[:-3000], nrm[:-3000], PlanesConfig())  # a Manhattan room alone
    assert all(np.degrees(np.arccos(np.max(np.abs(p.normal)))) < 0.5 for p in none)
    off = find_planes(pts, nrm, PlanesConfig(free_planes=0))
    assert [(p.kind, p.offset) for p in off] == [(p.kind, p.offset) for p in axis]


def test_a_board_turned_a_few_degrees_gets_one_plane_not_strips_of_it():
    """A board turned 3.5 degrees about the vertical (the office's whiteboard on its stand)
    spreads over 15 cm of offsets along its axis, and the refit within max_tilt_deg keeps
    the strip of it a peak crosses. The turn search gives it one plane through all of it,
    and the strip, all of whose inliers lie on it, gives way; the floor, walls and table
    keep theirs."""
    pts, nrm, board, n = _turned_board(3.5)
    planes = find_planes(pts, nrm, PlanesConfig())
    on_board = [p for p in planes if np.mean(np.abs(board @ p.normal - p.offset) < 0.02) > 0.2]
    assert len(on_board) == 1
    (b,) = on_board
    assert np.degrees(np.arccos(min(1.0, abs(b.normal @ n)))) < 0.5
    assert np.mean(np.abs(board @ b.normal - b.offset) <= 0.01) > 0.95
    assert {p.kind for p in planes} >= {"floor", "wall", "top"}
    assert b.support >= 0.9 * 6000 / 8  # all of it (thinned to 2 cm voxels)
    assert [p.offset for p in find_planes(pts, nrm, PlanesConfig(free_planes=0))] == [
        p.offset for p in planes
    ]  # the turn found it, not the free planes
    # not turned, an axis peak takes a strip of it: under a third of the board
    strips = find_planes(pts, nrm, PlanesConfig(turned_deg=0))
    got = [np.mean(np.abs(board @ p.normal - p.offset) < 0.02) for p in strips]
    assert 0.2 < max(got) < 0.35
    assert len(strips) == len(planes)  # the strip gave way to the board's plane
    # turned past the search (8 degrees), its best turn lies at the search's end: the free
    # planes take it, and the turn search adds nothing
    pts, nrm, board, n = _turned_board(12.0)
    planes = find_planes(pts, nrm, PlanesConfig())
    assert [(p.kind, p.offset) for p in planes] == [
        (p.kind, p.offset) for p in find_planes(pts, nrm, PlanesConfig(turned_deg=0))
    ]
    (b,) = [p for p in planes if np.mean(np.abs(board @ p.normal - p.offset) < 0.02) > 0.2]
    assert np.degrees(np.arccos(min(1.0, abs(b.normal @ n)))) < 0.5


def _turned_board(deg: float) -> tuple:
    """(points, normals, the board's points, its normal): a floor, two walls, a table and a
    2.5 x 1.2 m board turned deg degrees about the vertical off the x axis."""
    rng = np.random.default_rng(4)
    parts = _floor_two_walls_and_a_table(rng)
    yaw = np.radians(deg)
    n = np.array([np.sin(yaw), -np.cos(yaw), 0.0])  # faces the room (-y), turned
    along = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    u = rng.uniform(0.0, 2.5, 6000)
    v = rng.uniform(0.3, 1.5, 6000)
    board = np.array([0.2, 2.3, 0.0]) + u[:, None] * along + v[:, None] * [0, 0, 1.0]
    board += rng.normal(0, 0.003, (6000, 1)) * n
    parts.append((board, np.tile(n, (6000, 1))))
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    return pts, nrm, board, n


def test_a_planes_colours_are_its_own_surface_not_what_stands_on_it():
    """The floor's colours come from the points on it whose normals look up: the dark feet
    of chairs and sofas lie within band of it too, and with their colours counted a dark
    chair seat was as floor-coloured as the grey carpet (the office: 41.6 % of its floor
    fills lay on furniture)."""
    rng = np.random.default_rng(5)
    floor = Plane(
        np.array([0.0, 0.0, 1.0]), 0.0, "floor", np.array([0, 0, -0.1]), np.array([4, 4, 0.1]), 1
    )
    carpet = np.c_[rng.uniform(0, 4, (3000, 2)), rng.normal(0, 0.005, 3000)]
    feet = np.c_[rng.uniform(0, 4, (1500, 2)), rng.uniform(0, 0.02, 1500)]  # legs' bottoms
    pts = np.concatenate([carpet, feet])
    nrm = np.concatenate([np.tile([0.0, 0.0, 1.0], (3000, 1)), np.tile([1.0, 0.0, 0.0], (1500, 1))])
    rgb = np.concatenate([np.full((3000, 3), 0.7), np.tile([0.08, 0.08, 0.14], (1500, 1))])
    seat, grey = np.array([[0.1, 0.1, 0.15]]), np.array([[0.68, 0.7, 0.72]])
    own = plane_colours([floor], pts, rgb, 0.02, nrm, 0.9)
    every = plane_colours([floor], pts, rgb, 0.02)
    assert colour_cost(own, seat)[0, 0] == 1.0 and colour_cost(own, grey)[0, 0] == 0.0
    assert colour_cost(every, seat)[0, 0] == 0.0  # the feet's colours counted


def test_a_floor_tilted_past_the_refit_turns_the_room_axes_with_it(monkeypatch):
    """The align stage's z can lie degrees off the floor (the honest procedural room: 4.7).
    The mean of scattered normals about z leans towards z (here 4 of the 6 degrees are
    found), and a plane refitted within 2 cm and 2 degrees of its axis keeps the axis's
    tilt: the floor comes out 4 degrees off with a strip of its points. The floor's own
    normal taken as up gives the floor, and the table top with it, their true planes."""
    rng = np.random.default_rng(3)
    parts = [
        _patch(rng, 20000, 2, 0.0, (-2, -2, 0), (2, 2, 0), (0, 0, 1)),  # floor
        _patch(rng, 15000, 0, -2.0, (-2, -2, 0), (-2, 2, 2.5), (1, 0, 0)),  # wall x = -2
        _patch(rng, 4000, 2, 0.75, (0, 0, 0), (1, 0.8, 0), (0, 0, 1)),  # table top
    ]
    tilt = np.radians(6.0)
    turn = np.array(  # about x: the room sits tilted in the aligned world
        [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]]
    )
    pts = np.concatenate([p for p, _ in parts]) @ turn.T
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    nrm += rng.normal(0, 0.4, nrm.shape)  # stereo's normals scatter
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)) @ turn.T
    up = turn[:, 2]
    deg = lambda p: np.degrees(np.arccos(min(1.0, abs(p.normal @ up))))  # noqa: E731
    planes = find_planes(pts, nrm, PlanesConfig())
    floor, top = planes[0], next(p for p in planes if p.kind == "top")
    assert floor.kind == "floor" and deg(floor) < 0.3 and abs(floor.offset) < 0.01
    assert deg(top) < 0.3 and abs(top.offset - 0.75) < 0.01
    # the axes as the normals give them: the floor 4 degrees off, a quarter of its inliers
    monkeypatch.setattr("stages.depth.planes.hypotheses.floor_axes", lambda p, n, axes, c: axes)
    before = find_planes(pts, nrm, PlanesConfig())[0]
    assert deg(before) > 3.0 and before.support < floor.support / 4
    # a level floor leaves the axes as they came
    axes = [np.eye(3)[2], np.eye(3)[0], np.eye(3)[1]]
    level = floor_axes(pts[:20000] @ turn, nrm[:20000] @ turn, axes, PlanesConfig())
    assert np.degrees(np.arccos(level[0][2])) < 0.3


def test_the_floor_keeps_the_aligned_z_where_it_holds_the_floor():
    """A level floor seen near the cameras alone (1.5 x 1 m), its readings 0.3 degrees off
    level (stereo's depth error growing with distance; the honest room's refit leaned 0.38
    degrees where the level cameras' z was 0.03 off), leans the refit, and a foot cast on it
    4 m away moves by centimetres: z, which holds those points as well, is kept. A floor 1
    degree off z over 4 m holds a third of its points at z's normal: its own normal is
    taken."""
    rng = np.random.default_rng(5)
    pts, nrm = _patch(rng, 3000, 2, 0.02, (0, 0, 0), (1.5, 1, 0), (0, 0, 1))
    pts[:, 2] += np.tan(np.radians(0.3)) * pts[:, 0]
    axes = [np.eye(3)[2], np.eye(3)[0], np.eye(3)[1]]
    got = floor_axes(pts, nrm.astype(np.float64), axes, PlanesConfig())
    np.testing.assert_array_equal(got[0], [0.0, 0.0, 1.0])
    # the refit alone (the rule before): the readings' lean
    refit = np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2][-1]
    assert np.degrees(np.arccos(abs(refit[2]))) == pytest.approx(0.3, abs=0.05)
    a = np.radians(1.0)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    wide, wn = _patch(rng, 20000, 2, 0.0, (-2, -2, 0), (2, 2, 0), (0, 0, 1))
    got = floor_axes(wide @ turn.T, wn.astype(np.float64) @ turn.T, axes, PlanesConfig())
    assert abs(np.degrees(np.arccos(got[0][2])) - 1.0) < 0.1


def test_the_floor_plane_itself_stays_level_where_the_aligned_z_holds_it(monkeypatch):
    """The floor's peak is refitted within 2 degrees of its axis, so readings leaning 0.3
    degrees near the cameras lean the floor plane too, even with the axes kept level, and
    the walls' feet are cast onto that plane (the honest room's far wall: 3 cm out). Where z
    holds the peak's points as well, the floor is the level plane through their median."""
    rng = np.random.default_rng(6)
    pts, nrm = _patch(rng, 3000, 2, 0.02, (0, 0, 0), (1.5, 1, 0), (0, 0, 1))
    pts[:, 2] += np.tan(np.radians(0.3)) * pts[:, 0]
    floor = find_planes(pts, nrm.astype(np.float64), PlanesConfig())[0]
    assert floor.kind == "floor"
    np.testing.assert_array_equal(floor.normal, [0.0, 0.0, 1.0])
    assert floor.offset == pytest.approx(np.median(pts[:, 2]), abs=1e-3)  # of the 2 cm voxels
    # the peak's own refit: the readings' lean
    monkeypatch.setattr("stages.depth.planes.hypotheses._level_floor", lambda f, *a: f)
    leant = find_planes(pts, nrm.astype(np.float64), PlanesConfig())[0]
    assert np.degrees(np.arccos(leant.normal[2])) == pytest.approx(0.3, abs=0.05)


def _horizontal_normals(rng, n, yaw_deg, noise_deg):
    """n wall normals about the four directions of a room turned yaw_deg from x, each off by
    Gaussian noise_deg, and as many floor normals."""
    a = np.radians(yaw_deg + 90 * rng.integers(0, 4, n) + rng.normal(0, noise_deg, n))
    walls = np.stack([np.cos(a), np.sin(a), np.zeros(n)], 1)
    return np.concatenate([walls, np.tile([0.0, 0.0, 1.0], (n, 1))])


def test_room_axes_take_the_walls_near_the_aligned_axes_and_only_those():
    rng = np.random.default_rng(4)
    yaw = lambda axes: np.degrees(np.arctan2(axes[1][1], axes[1][0]))  # noqa: E731
    # a room turned 4° from the align stage's axes (its walls a few degrees off): found
    turned = _horizontal_normals(rng, 4000, 4.0, 2.0)
    assert yaw(room_axes(turned, 10.0)) == pytest.approx(4.0, abs=0.5)
    # at 0 the align stage's axes are kept, exactly, however clear the normals' peak
    np.testing.assert_array_equal(room_axes(turned, 0.0)[1], [1.0, 0.0, 0.0])
    # normals spread over every direction (stereo's on the 7-Scenes kitchen): no peak stands
    # out, the align stage's axes stay (not a noise peak, up to 45° away)
    a = rng.uniform(0, 2 * np.pi, 4000)
    flat = np.concatenate([np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1), [[0, 0, 1]] * 99])
    assert yaw(room_axes(flat, 10.0)) == 0.0
    # a clear peak 40° away is not the room's walls (the align stage put them on x and y)
    assert yaw(room_axes(_horizontal_normals(rng, 4000, 40.0, 2.0), 10.0)) == 0.0
    # ... unless asked to look that far
    assert yaw(room_axes(_horizontal_normals(rng, 4000, 40.0, 2.0), 45.0)) == pytest.approx(
        40.0, abs=0.5
    )


def test_a_table_top_is_not_extended_across_the_room():
    # a table top in one corner and a cushion at the same height in the opposite corner: the
    # box of their inliers spans the room, the plane's support is the two patches
    rng = np.random.default_rng(2)
    parts = [
        _patch(rng, 30000, 2, 0.0, (0, 0, 0), (4, 4, 0), (0, 0, 1)),  # floor
        _patch(rng, 15000, 0, 0.0, (0, 0, 0), (0, 4, 2.5), (1, 0, 0)),  # wall x = 0
        _patch(rng, 3000, 2, 0.45, (0.5, 0.5, 0), (1.3, 1.3, 0), (0, 0, 1)),  # table top
        _patch(rng, 1000, 2, 0.45, (3.2, 3.2, 0), (3.6, 3.6, 0), (0, 0, 1)),  # cushion
    ]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    at = np.array([[0.9, 0.9, 0.45], [1.4, 1.0, 0.45], [2.3, 2.3, 0.45], [3.4, 0.8, 0.45]])
    cam = np.array([2.0, 2.0, 1.5])  # looking down at those points from above the room
    r = at - cam
    r /= -r[:, 2:]  # unit z towards the floor: any ray scale works for the box test
    for cell, want in ((0.1, [True, True, False, False]), (0.0, [True, True, True, True])):
        planes = find_planes(pts, nrm, PlanesConfig(support_cell=cell))
        k = [i for i, p in enumerate(planes) if p.kind == "top"]
        assert len(k) == 1 and abs(planes[k[0]].offset - 0.45) < 0.005
        assert planes[k[0]].lo[0] < 0.6 and planes[k[0]].hi[0] > 3.5  # the box spans both
        t = plane_depth(r, cam, planes)
        ok = plane_valid(t, r, cam, planes, (0.5, 0.15), None)[k[0]]
        # on the table and 0.1 m past its edge: a top; mid-room and in the far corner: not
        assert ok.tolist() == want, cell
        assert planes[0].kind == "floor" and planes[0].cells is None  # the floor spans the room
    assert planes[k[0]].to_json()["cells"] is None
    with pytest.raises(BlunfError, match="support_cell"):
        PlanesConfig(support_cell=-1)


def _ring(rng, n, z, lo, hi, width, noise):
    """n points of a rectangle's rim (width wide inside lo..hi in x, y) at height z."""
    p = rng.uniform((*lo, 0), (*hi, 0), (4 * n, 3))
    inner = np.all((p[:, :2] > np.add(lo, width)) & (p[:, :2] < np.subtract(hi, width)), 1)
    p = p[~inner][:n]
    p[:, 2] = z + rng.normal(0, noise, len(p))
    return p, np.zeros_like(p)  # normals unknown: sparse stereo at an edge


@pytest.mark.parametrize("floor", [0.0, 0.25])
def test_a_table_read_at_its_rim_gets_its_own_top_over_its_whole_top(floor):
    """A table read only at its rim (0.50 m, 1 cm noise), beside a sofa's noisier seat at
    0.55 m across the room: the room's histogram along up rises through 0.50 to the seat's
    peak and shows none at the table, so its top would take the floor's plane (the office).
    The tiles of the floor find it; its support takes in the unread top the rim encloses.
    With the floor 0.25 m above the aligned z = 0 (the honest room's align stage), a few
    points 6 cm under it (a reflection) make no top, and the floor is still the floor."""
    rng = np.random.default_rng(3)
    parts = [
        _patch(rng, 100, 2, -0.06, (3.0, 3.0, 0), (3.4, 3.4, 0), (0, 0, 0)),  # under the floor
        _patch(rng, 30000, 2, 0.0, (0, 0, 0), (4, 4, 0), (0, 0, 1)),  # floor
        _patch(rng, 15000, 0, 0.0, (0, 0, 0), (0, 4, 2.5), (0, 0, 0)),  # walls, normals
        _patch(rng, 15000, 1, 4.0, (0, 4, 0), (4, 4, 2.5), (0, 0, 0)),  # unknown
        _patch(rng, 6000, 2, 0.55, (0.2, 0.2, 0), (3.8, 0.8, 0), (0, 0, 1)),  # sofa seat
        _ring(rng, 800, 0.50, (1.3, 1.9), (2.5, 2.8), 0.06, 0.01),  # table rim
    ]
    parts[4][0][:, 2] = 0.55 + rng.normal(0, 0.015, len(parts[4][0]))
    pts = np.concatenate([p for p, _ in parts]) + [0, 0, floor]
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    # the table's centre and rim, the middle of the room (no table there)
    at = np.array([[1.9, 2.35, 0.5], [1.32, 2.35, 0.5], [3.0, 3.4, 0.5]]) + [0, 0, floor]
    cam = np.array([2.0, 1.5, 1.6 + floor])
    r = at - cam
    r /= -r[:, 2:]

    def table(cfg):
        planes = find_planes(pts, nrm, cfg)
        k = [
            i
            for i, p in enumerate(planes)
            if p.kind == "top" and abs(p.offset - 0.50 - floor) < 0.02
        ]
        if not k:
            return None, planes
        ok = plane_valid(plane_depth(r, cam, planes), r, cam, planes, (0.5, 0.15), None)
        return (planes[k[0]], ok[k[0]].tolist()), planes

    got, planes = table(PlanesConfig())
    assert got is not None, [(p.kind, round(p.offset, 3)) for p in planes]
    top, valid = got
    assert planes[0].kind == "floor" and abs(planes[0].offset - floor) < 0.005
    assert not any(p.offset < floor - 0.01 for p in planes if abs(p.normal[2]) > 0.9)
    assert abs(top.offset - 0.50 - floor) < 0.005 and np.degrees(np.arccos(top.normal[2])) < 1
    assert valid == [True, True, False]  # the unread centre too; not the room's middle
    assert top.hi[0] < 2.6 and top.lo[0] > 1.2  # its inliers are the table's alone
    assert any(p.kind == "top" and abs(p.offset - 0.55 - floor) < 0.01 for p in planes)  # seat
    # without the tiles the room's histogram has no peak at the table
    assert table(PlanesConfig(top_tile=0))[0] is None
    # and without the holes taken in, only the rim (and 0.15 m into the top) is a top
    assert table(PlanesConfig(top_holes=0))[0][1] == [False, True, False]
    for k in ("top_tile", "top_holes"):
        with pytest.raises(BlunfError, match=k):
            PlanesConfig(**{k: -1.0})


def test_a_seat_read_at_its_front_edge_reaches_over_what_was_not_read_under_it():
    """A sofa's seat (0.3 m) against the wall y = 4, read along its front edge alone; under
    its unread back nothing was read, the floor round it was. The seat's support grows over
    the unread part (the floor's plane filled it, and the plan drew floor through the sofa),
    not over the read floor in front of it, nor past top_grow."""
    rng = np.random.default_rng(4)
    floor, _ = _patch(rng, 40000, 2, 0.0, (0, 0, 0), (4, 4, 0), (0, 0, 1))
    under_sofa = (floor[:, 0] > 0.5) & (floor[:, 0] < 2.5) & (floor[:, 1] > 3.0)
    parts = [
        (floor[~under_sofa], np.tile((0.0, 0.0, 1.0), ((~under_sofa).sum(), 1))),
        _patch(rng, 15000, 0, 0.0, (0, 0, 0), (0, 4, 2.5), (1, 0, 0)),  # wall x = 0
        _patch(rng, 15000, 1, 4.0, (0, 4, 0), (4, 4, 2.5), (0, -1, 0)),  # wall y = 4
        _patch(rng, 1500, 2, 0.3, (0.5, 3.0, 0), (2.5, 3.25, 0), (0, 0, 1)),  # seat's edge
    ]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    # on the seat's unread back; over the read floor 0.4 m before it; past top_grow
    at = np.array([[1.5, 3.75, 0.3], [1.5, 2.6, 0.3], [1.5, 3.9, 0.3]])
    cam = np.array([1.5, 1.0, 1.6])
    r = at - cam
    r /= -r[:, 2:]

    def seat(cfg):
        planes = find_planes(pts, nrm, cfg)
        k = [i for i, p in enumerate(planes) if p.kind == "top" and abs(p.offset - 0.3) < 0.01]
        assert len(k) == 1, [(p.kind, round(p.offset, 3)) for p in planes]
        ok = plane_valid(plane_depth(r, cam, planes), r, cam, planes, (0.5, 0.15), None)
        return ok[k[0]].tolist()

    assert seat(PlanesConfig(top_grow=0.6))[:2] == [True, False]
    assert seat(PlanesConfig(top_grow=0.3))[2] is False  # 0.65 m past the read edge
    assert seat(PlanesConfig(top_grow=0))[0] is False
    with pytest.raises(BlunfError, match="top_grow"):
        PlanesConfig(top_grow=-1.0)


@pytest.fixture(scope="module")
def plain_room(tmp_path_factory):
    from stages.synth import make_room
    from stages.synth.realism import Realism

    root = make_room(
        tmp_path_factory.mktemp("plain") / "capture",
        views=12,
        seed=3,
        size=(160, 120),
        realism=Realism.parse("honest"),
    )
    return read_layout(root)


def test_plain_walls_are_found_by_their_feet_on_the_floor(plain_room):
    # the honest room's walls are plain paint: no stereo reading, no peak of points. Their
    # feet, the edge where floor meets wall in the photos, cast on the floor plane from 12
    # views at 160 x 120 put each of the four within 2 cm of the room's interior faces
    cap = plain_room
    x0, y0, x1, y1 = json.loads((cap.root / "gt" / "room.json").read_text())["interior"]
    rgbs = [read_image(f.image).astype(np.float32) / 255.0 for f in cap.frames]
    none = [np.zeros(r.shape[:2], np.float32) for r in rgbs]
    Ks = [f.intrinsics.K for f in cap.frames]
    poses = [np.asarray(f.pose, np.float64) for f in cap.frames]
    up = np.array([0.0, 0.0, 1.0])
    axes = [np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    got = wall_feet(rgbs, none, Ks, poses, up, 0.0, axes, 3)
    want = {(1, 0): x1, (-1, 0): -x0, (0, 1): y1, (0, -1): -y0}
    assert sorted(tuple(np.round(n[:2]).astype(int)) for n, _, _ in got) == sorted(want)
    for n, d, views in got:
        assert abs(d - want[tuple(np.round(n[:2]).astype(int))]) < 0.02 and views >= 3
    # a wall axis leaning off the floor's normal gives upright walls all the same
    lean = [np.array([1.0, 0.0, 0.05]), np.array([0.0, 1.0, -0.05])]
    for n, d, _ in wall_feet(rgbs, none, Ks, poses, up, 0.0, lean, 3):
        assert abs(n[2]) < 1e-9 and abs(d - want[tuple(np.round(n[:2]).astype(int))]) < 0.02
    # axes 2 degrees off the walls (as the points' normals can give; 16 cm across a 4.7 m
    # wall): the yaws within 3 degrees are tried and each foot's line is refitted on its
    # votes, which turns it back within 0.75 degrees of its wall
    c, s_ = np.cos(np.radians(2.0)), np.sin(np.radians(2.0))
    yawed = [np.array([c, s_, 0.0]), np.array([-s_, c, 0.0])]
    got = wall_feet(rgbs, none, Ks, poses, up, 0.0, yawed, 3)
    assert sorted(tuple(np.round(n[:2]).astype(int)) for n, _, _ in got) == sorted(want)
    for n, d, _ in got:
        key = tuple(np.round(n[:2]).astype(int))
        assert np.degrees(np.arccos(min(1.0, abs(n[:2] @ np.array(key))))) < 0.75
        assert abs(d - want[key]) < 0.04
    # the walls are at least 5 cm beyond (an edge 3 views agree on) when the views must
    # all agree: none is found
    assert wall_feet(rgbs, none, Ks, poses, up, 0.0, axes, len(rgbs) + 1) == []


def test_a_read_wall_spans_the_room_upright_and_a_foot_stands_where_stereo_read_little():
    rng = np.random.default_rng(4)
    lean = np.radians(1.5)  # within max_tilt_deg: the refit keeps the wall leaning
    wz = rng.uniform(0, 2.5, 15000)  # a wall read over 1.5 m of its length, up to 2.5 m
    wall_y = np.stack([rng.uniform(1.0, 2.5, 15000), 3.0 + wz * np.tan(lean), wz], -1)
    low = _patch(rng, 6000, 0, 0.2, (0.2, 0, 0), (0.2, 3, 1.0), (1, 0, 0))  # read to 1 m
    parts = [
        _patch(rng, 20000, 2, 0.0, (0, 0, 0), (3.5, 3, 0), (0, 0, 1)),  # floor
        low,
        (wall_y, np.tile((0.0, -1.0, 0.0), (15000, 1))),
        _patch(rng, 1500, 0, 3.45, (3.45, 1, 0), (3.45, 1.5, 0.5), (-1, 0, 0)),  # behind x = 3.4
    ]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    calls = []

    def feet(up, floor, axes):
        calls.append((up, floor, axes))
        x, y = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
        # plain walls at x = 3.4 and x = 0.25 (the low wall's foot), a mark beyond the read
        # wall at y = 3
        return [(x, 3.4, 9), (-x, -0.25, 9), (y, 3.3, 9)]

    def xy(p):  # a vertical plane's offset along +x or +y
        return round(float(p.offset * max(p.normal[:2], key=abs)), 2)

    def on(planes, axis):
        return [p for p in planes if abs(p.normal[axis]) > 0.9]

    alone = find_planes(pts, nrm, PlanesConfig(walls_span=False))
    (wy,) = on(alone, 1)
    assert wy.lo[0] > 0.95 and wy.hi[0] < 2.55 and abs(wy.normal[2]) > 0.02  # leaning
    assert any(abs(xy(p) - 3.45) < 0.01 for p in alone)
    # the read wall spans the room: upright, through its inliers at their middle height,
    # across; the wall read to 1 m only may be furniture and keeps its box
    spans = find_planes(pts, nrm, PlanesConfig())
    (wy,) = on(spans, 1)
    assert abs(wy.normal @ spans[0].normal) < 1e-9
    assert abs(xy(wy) - (3.0 + 1.25 * np.tan(lean))) < 0.01
    assert wy.lo[0] < 0.15 and wy.hi[0] > 3.3 and wy.hi[2] >= 2.4
    x02 = next(p for p in on(spans, 0) if abs(xy(p) - 0.2) < 0.01)
    assert x02.hi[2] < 1.1
    # with the feet: the low wall and the plane behind x = 3.4 give way to them, and they
    # span the room; the foot beyond the read wall is not a wall
    planes = find_planes(pts, nrm, PlanesConfig(), feet)
    assert len(calls) == 1 and abs(calls[0][1]) < 0.01
    xs = sorted(on(planes, 0), key=xy)
    assert [(xy(p), p.kind, p.support) for p in xs] == [(0.25, "wall", 0), (3.4, "wall", 0)]
    assert xs[1].lo[1] < 0.15 and xs[1].hi[1] > 2.85 and xs[1].hi[2] >= 2.4
    (wy,) = on(planes, 1)
    assert abs(xy(wy) - 3.0) < 0.05 and wy.support > 0
    assert planes[0].kind == "floor" and planes[0].hi[0] >= 3.4


def _half(d: np.ndarray) -> np.ndarray:
    """A depth map at half size as the sweep makes one (each pixel the 2 x 2 block it
    covers, so that K scaled by a half fits it): inverse depth averaged, which is exact on a
    plane; 0 where any of the four is."""
    h, w = d.shape[0] // 2, d.shape[1] // 2
    blocks = d[: 2 * h, : 2 * w].reshape(h, 2, w, 2)
    inv = np.where(blocks > 0, 1.0 / np.maximum(blocks, 1e-9), 0.0).mean((1, 3))
    return np.where((blocks > 0).all((1, 3)), 1.0 / np.maximum(inv, 1e-9), 0.0).astype(np.float32)


def test_fill_reads_blank_walls_from_the_planes(plain_room):
    cap = plain_room
    wall_id = [k for k, v in cap.classes.items() if v == "wall"][0]
    images, Ks, poses, sparse, depths, exact, walls = [], [], [], [], [], [], []
    for f in cap.frames:
        img = read_image(f.image).astype(np.float32) / 255.0
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        gray = img.mean(2)
        std = np.sqrt(np.maximum(uniform_filter(gray**2, 7) - uniform_filter(gray, 7) ** 2, 0))
        textured = std > 0.03  # what stereo reads: the plain walls are not among it
        images.append(img)
        Ks.append(f.intrinsics.K)
        poses.append(np.asarray(f.pose))
        sp = np.zeros_like(d)
        sp[::7, ::7] = np.where(textured[::7, ::7], d[::7, ::7], 0)  # SfM tracks
        sparse.append(sp)
        # the sweep's readings at half size, only where textured
        depths.append(_half(np.where(textured, d, 0)))
        exact.append(_half(d))
        walls.append(read_label(f.label)[::2, ::2] == wall_id)
    out, src, facts = fill(images, Ks, poses, sparse, depths, PlanesConfig(enabled=True))
    assert facts["coverage_after"] > facts["coverage_before"] + 0.3
    planes = np.concatenate([(s == 2).reshape(-1) for s in src])
    err = np.abs(np.concatenate([(o - e).reshape(-1) for o, e in zip(out, exact, strict=True)]))
    good = np.concatenate([(e > 0).reshape(-1) for e in exact])
    assert np.mean(err[planes & good] <= 0.03) > 0.95
    blank = np.concatenate([(w & (d == 0)).reshape(-1) for w, d in zip(walls, depths, strict=True)])
    assert np.mean(planes[blank]) > 0.6  # most of the blank walls get plane depth
    assert facts["coverage_by_kind"]["wall"] > 0.2 and facts["stereo_snapped"] > 0
    for o, s, d in zip(out, src, depths, strict=True):
        assert o.shape == d.shape and s.dtype == np.uint8 and np.isfinite(o).all()
        # kept stereo is untouched but where it agreed with a floor, wall or ceiling within
        # tol (snap), and took that plane's depth
        moved = (s == 1) & (o != d)
        assert np.all(np.abs(o[moved] - d[moved]) <= PlanesConfig().tol * o[moved] + 1e-6)
    # two views labelled side by side, one per thread: the same depth, pixel for pixel
    out2, src2, _ = fill(images, Ks, poses, sparse, depths, PlanesConfig(enabled=True), threads=2)
    for a, b, s, t in zip(out, out2, src, src2, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(s, t)
    # without the walls' feet the outermost planes the points show are furniture: the views
    # paste them on the plain walls at different depths and the check undoes the whole fill
    # (undo "all"), or those planes (undo "plane", the default), keeping the few the views
    # agree on (measured 8 % of the pixels, 89 % within 3 cm, against 36 % and 99 % above)
    every = PlanesConfig(wall_feet=False, undo="all")
    _, src3, off = fill(images, Ks, poses, sparse, depths, every)
    assert not off["ran"] and not any((s == 2).any() for s in src3)
    out4, src4, few = fill(images, Ks, poses, sparse, depths, PlanesConfig(wall_feet=False))
    assert few["ran"] and few["fills_dropped_by_check"] <= PlanesConfig().max_dropped
    assert {u["kind"] for u in few["planes_undone"]} >= {"wall"}
    assert 0 < few["coverage_planes"] < facts["coverage_planes"] / 2
    planes = np.concatenate([(s == 2).reshape(-1) for s in src4])
    err = np.abs(np.concatenate([(o - e).reshape(-1) for o, e in zip(out4, exact, strict=True)]))
    assert np.mean(err[planes & good] <= 0.03) > 0.8


def _shifted_views(room, n: int = 8):
    """(images, Ks, poses, sparse, depths, truth) of the room's first n views, the readings
    shifted 8 % in every other view (as a mirror in a glossy front or a drifting scale
    gives), stereo's readings where the photo has texture, at half size; truth: the exact
    depth at half size."""
    images, Ks, poses, sparse, depths, truth = [], [], [], [], [], []
    for i, f in enumerate(room.frames[:n]):
        img = read_image(f.image).astype(np.float32) / 255.0
        d = read_depth(f.depth, room.depth_scale, room.depth_invalid)
        truth.append(d[::2, ::2])
        d = d * (1.08 if i % 2 else 1.0)
        images.append(img)
        Ks.append(f.intrinsics.K)
        poses.append(np.asarray(f.pose))
        sp = np.zeros_like(d)
        sp[::7, ::7] = d[::7, ::7]
        sparse.append(sp)
        gray = img.mean(2)
        std = np.sqrt(np.maximum(uniform_filter(gray**2, 7) - uniform_filter(gray, 7) ** 2, 0))
        depths.append(np.where(std > 0.03, d, 0)[::2, ::2].astype(np.float32))
    return images, Ks, poses, sparse, depths, truth


def _fills_near(out, src, truth, rel: float) -> float:
    """Share of the plane-filled pixels within `rel` of the exact depth."""
    err = [np.abs(o[s == 2] / t[s == 2] - 1) for o, s, t in zip(out, src, truth, strict=True)]
    err = np.concatenate(err)
    return float((err < rel).mean())


def test_a_fill_the_views_disagree_on_is_undone_and_says_why(plain_room, monkeypatch):
    # the views' plane fills disagree, the multi-view check drops many of them, and over
    # max_dropped the maps pass through untouched (undo "all": the whole fill at once)
    images, Ks, poses, sparse, depths, _ = _shifted_views(plain_room)
    every = PlanesConfig(max_dropped=1.0, sample_every=0)  # all views, then the one check
    _, src, ran = fill(images, Ks, poses, sparse, depths, every)
    dropped = ran["fills_dropped_by_check"]
    assert ran["ran"] and any((s == 2).any() for s in src) and dropped > 0.05, ran
    assert ran["planes_undone"] == []  # no plane is over 100 %
    # eight views are too few to sample (SAMPLE_VIEWS): the whole check decides
    for k in (0, 3):
        cfg = PlanesConfig(max_dropped=dropped / 2, sample_every=k, undo="all")
        out, src, facts = fill(images, Ks, poses, sparse, depths, cfg)
        assert not facts["ran"] and facts["fills_dropped_by_check"] == dropped
        assert "sample" not in facts
        assert facts["reason"] == (
            f"no plane fill: the multi-view check dropped {100 * dropped:.0f} % of its fills, "
            f"over depth.planes.max_dropped {50 * dropped:.0f} % (the views disagree on the "
            "room's planes)"
        )
    # allowed a sample of three, one view in 3 (0, 3, 6) holds a shifted one: the sample
    # disagrees, and the fill stops before labelling the other five
    monkeypatch.setattr(planes_fill, "SAMPLE_VIEWS", 3)
    cfg = PlanesConfig(max_dropped=dropped / 2, sample_every=3, undo="all")
    out, src, facts = fill(images, Ks, poses, sparse, depths, cfg)
    assert not facts["ran"] and facts["sample"] == {"every": 3, "views": 3}
    assert facts["reason"].startswith("no plane fill: the multi-view check dropped")
    assert "of the fills of one view in 3 (3 views)" in facts["reason"]
    assert facts["coverage_after"] == facts["coverage_before"] and facts["coverage_planes"] == 0
    assert facts["cpu_seconds"] < ran["cpu_seconds"]
    for o, s, d in zip(out, src, depths, strict=True):
        np.testing.assert_array_equal(o, d)
        np.testing.assert_array_equal(s, (d > 0).astype(np.uint8))
    with pytest.raises(BlunfError, match="sample_every"):
        PlanesConfig(sample_every=-1)
    with pytest.raises(BlunfError, match="max_dropped"):
        PlanesConfig(max_dropped=1.5)


def test_the_planes_the_views_disagree_on_fill_nothing_and_the_others_stay(plain_room):
    # undo "plane" (the default): a plane whose fills the check drops over max_dropped
    # fills nothing, and what the other planes fill stays. The views shifted 8 % paste the
    # floor and walls at two depths; the planes they agree on fill within 2 % of the truth
    images, Ks, poses, sparse, depths, truth = _shifted_views(plain_room)
    inputs = (images, Ks, poses, sparse, depths)
    kept, ksrc, whole = fill(*inputs, PlanesConfig(max_dropped=1.0, sample_every=0))
    dropped = whole["fills_dropped_by_check"]
    # under max_dropped as a whole, every plane fills, those over it too
    under = PlanesConfig(max_dropped=min(1.0, dropped + 0.01), sample_every=0)
    _, _, all_in = fill(*inputs, under)
    assert all_in["ran"] and all_in["planes_undone"] == []
    assert all_in["coverage_planes"] == whole["coverage_planes"]
    out, src, facts = fill(*inputs, PlanesConfig(max_dropped=dropped / 2, sample_every=0))
    undone = facts["planes_undone"]
    assert facts["ran"] and facts["fills_dropped_by_check"] <= dropped / 2, facts
    assert undone and all(u["dropped"] > dropped / 2 and u["views"] == "all" for u in undone)
    assert {u["kind"] for u in undone} >= {"floor", "wall"}
    left = {p["offset"] for p in facts["planes"]} - {u["offset"] for u in undone}
    assert left  # some planes still fill
    assert 0 < facts["coverage_planes"] < whole["coverage_planes"]
    assert _fills_near(out, src, truth, 0.02) > 0.95 > _fills_near(kept, ksrc, truth, 0.02)
    # every plane over: nothing is left to fill, and the fill says so
    out, src, none = fill(*inputs, PlanesConfig(max_dropped=0.0, sample_every=0))
    assert not none["ran"] and none["coverage_planes"] == 0
    assert none["reason"] == (
        "no plane fill: the multi-view check dropped over depth.planes.max_dropped 0 % of each "
        "plane's fills (the views disagree on the room's planes)"
    )
    for o, s, d in zip(out, src, depths, strict=True):
        np.testing.assert_array_equal(o, d)
        np.testing.assert_array_equal(s, (d > 0).astype(np.uint8))
    with pytest.raises(BlunfError, match="depth.planes.undo"):
        PlanesConfig(undo="view")


def test_fill_rejects_mismatched_inputs():
    with pytest.raises(BlunfError, match="differ"):
        fill([np.zeros((8, 8, 3), np.float32)], [], [], [], [], PlanesConfig(enabled=True))


def _down_view(x: float, depth: float, size: int = 32) -> ViewData:
    """A blank view looking straight down from (x, 0, 1.5), reading `depth` everywhere
    (0: nothing)."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # x right, y down, z into
    pose[:3, 3] = [x, 0.0, 1.5]
    K = np.array([[size, 0, (size - 1) / 2], [0, size, (size - 1) / 2], [0, 0, 1.0]])
    rgb = np.full((size, size, 3), 0.5, np.float32)
    d = np.full((size, size), depth, np.float32)
    return ViewData(rgb, rgb.mean(2), K, pose, d, d, K)


def test_a_floor_that_other_views_see_furniture_in_front_of_is_not_filled():
    # the view reads nothing (a blank floor, or a blank sofa on it); a neighbour reads a
    # surface 0.5 m above the floor there (the sofa's top): the floor would be hidden
    floor = Plane(np.array([0.0, 0, 1]), 0.0, "floor", np.full(3, -5.0), np.full(3, 5.0), 1000)
    view = _down_view(0.0, 0.0)
    seg = np.arange(16).repeat(64).reshape(32, 32)  # 16 strips of 2 rows
    for nb_depth, hidden in ((1.0, True), (1.5, False)):  # the sofa's top; the floor itself
        nbrs = [_down_view(0.3, nb_depth)]
        cost = {
            w: data_costs(view, seg, [floor], nbrs, PlanesConfig(w_hidden=w), None)[0]
            for w in (0.0, PlanesConfig().w_hidden)
        }
        none = cost[0.0][:, 1]
        assert np.all(cost[0.0][:, 0] < none - 0.4)  # without the term: the floor wins
        # with it the floor loses where the neighbour saw the sofa (the strips it sees)
        seen = cost[PlanesConfig().w_hidden][:, 0] > none + 0.4
        assert seen.sum() >= (8 if hidden else 0) and (hidden or not seen.any())


def test_snap_moves_the_readings_that_agree_with_a_wall_onto_it_and_only_those():
    """A view square to a wall 5 m away, its stereo scattered 2 cm about it, a box 1 m in
    front of the wall in one corner, and the bottom rows on a table top: with snap the wall's
    agreeing readings take the wall's depth exactly; the box (off the wall by more than tol)
    and the top's readings (furniture: its plane is less sure) keep stereo's."""
    h, w = 40, 60
    K = np.array([[50.0, 0, 29.5], [0, 50.0, 19.5], [0, 0, 1]])
    pose = np.eye(4)  # looking along +z
    wall = Plane(np.array([0.0, 0.0, 1.0]), 5.0, "wall", np.zeros(3), np.zeros(3), 10**6)
    top = Plane(np.array([0.0, -1.0, 0.0]), -0.9, "top", np.zeros(3), np.zeros(3), 10**6)
    seg = np.zeros((h, w), np.int64)
    seg[30:] = 1  # the table's rows
    lab = Labelling(
        seg=seg,
        unary=np.array([[0.0, 1.0, 1.0], [1.0, 0.0, 1.0]]),  # each region's plane by far
        labels=np.array([0, 1]),
        edges=np.array([[0, 1]]),
        energy=0.0,
    )
    rng = np.random.default_rng(0)
    depth = (5.0 + rng.normal(0, 0.02, (h, w))).astype(np.float32)
    depth[5:15, 5:15] = 4.0  # the box
    uv = pixel_grid(w, h).reshape(-1, 2)
    t_top = plane_depth(rays(uv, K, pose), pose[:3, 3], [top])[0].reshape(h, w)
    depth[30:] = (t_top[30:] * 1.01).astype(np.float32)  # the table read 1 % long
    off = merge_view(lab, depth, K, pose, [wall, top], PlanesConfig(snap=False))
    on = merge_view(lab, depth, K, pose, [wall, top], PlanesConfig(snap=True))
    np.testing.assert_array_equal(off.kept, depth)
    agree = np.zeros((h, w), bool)
    agree[:30] = True
    agree[5:15, 5:15] = False
    np.testing.assert_allclose(on.kept[agree], 5.0, atol=1e-6)
    np.testing.assert_array_equal(on.kept[~agree], depth[~agree])  # the box, the table
    assert on.snapped == agree.sum() and off.snapped == 0

"""What goes with a surface hanging before a wall (segment.py's _by_hangers): a whiteboard on a
stand 0.3 m before the wall at y = 3 of test_semantics' room, as in the Replica office."""

from __future__ import annotations

import numpy as np
import trimesh

from stages.common.capture import UNKNOWN
from stages.common.classes import OBJECT, WALL
from stages.semantics import SemanticsConfig
from stages.semantics.segment import segment, triangles
from tests.stages.test_semantics import X, Y, Z, _quad, subdivided

YB = Y - 0.3  # the board's plane


def _board_room(extra: list[trimesh.Trimesh]) -> tuple[np.ndarray, np.ndarray]:
    """The floor, the wall at y = Y and a board 0.7-1.9 m up over x 1.0-2.8 at YB, its legs
    at both ends, with `extra` boxes; vertices and triangles subdivided to EDGE."""
    boxes = [
        trimesh.creation.box(bounds=[(1.0, YB - 0.03, 0.0), (1.05, YB + 0.03, 0.7)]),
        trimesh.creation.box(bounds=[(2.75, YB - 0.03, 0.0), (2.8, YB + 0.03, 0.7)]),
        *extra,
    ]
    parts = [(np.asarray(b.vertices), np.asarray(b.faces)) for b in boxes] + [
        _quad([(0, 0, 0), (X, 0, 0), (X, Y, 0), (0, Y, 0)], (0, 0, 1)),
        _quad([(0, Y, 0), (X, Y, 0), (X, Y, Z), (0, Y, Z)], (0, -1, 0)),
        _quad([(1.0, YB, 0.7), (2.8, YB, 0.7), (2.8, YB, 1.9), (1.0, YB, 1.9)], (0, -1, 0)),
    ]
    return subdivided(parts)


def test_the_stand_behind_a_board_hangs_with_it():
    # the stand's feet (8 cm high) run from the legs back to the wall: 0.3 m behind the
    # board, hidden by it, beyond hanger_slab of its plane. They go with the board (unknown),
    # not into an object the depth of the board's gap to the wall
    feet = [
        trimesh.creation.box(bounds=[(x, YB + 0.03, 0.0), (x + 0.05, Y - 0.01, 0.08)])
        for x in (1.0, 2.75)
    ]
    verts, tris = _board_room(feet)
    c, _, _ = triangles(verts, tris)
    behind = (c[:, 1] > YB + 0.12) & (c[:, 1] < Y - 0.04) & (c[:, 2] > 0.035)
    seg = segment(verts, tris, SemanticsConfig())
    assert behind.sum() > 20 and (seg.cls[behind] == UNKNOWN).all()
    assert seg.instance.max() == 0


def test_a_plant_beside_a_board_is_an_object_though_a_leaf_lies_in_its_plane():
    # a plant's pot 0.4 m beyond the board's end straddles its plane (10 cm behind it, 20 cm
    # before it); one leaf, 8 x 10 cm, lies in the plane, an inlier of the board's. The board
    # reaches where it covers the plane (10 cm stretches holding 0.01 m² of it), not the
    # leaf: the pot, standing on the floor beside the board, is an object, all of it
    pot = trimesh.creation.box(bounds=[(3.2, YB - 0.2, 0.0), (3.5, YB + 0.1, 0.8)])
    verts, tris = _board_room([pot])
    lv, lf = _quad([(3.3, YB, 1.0), (3.38, YB, 1.0), (3.38, YB, 1.1), (3.3, YB, 1.1)], (0, -1, 0))
    lv, lf = trimesh.remesh.subdivide_to_size(lv, lf, max_edge=0.02)
    verts, tris = np.concatenate([verts, lv]), np.concatenate([tris, lf + len(verts)])
    c, _, _ = triangles(verts, tris)
    in_pot = (c[:, 0] > 3.19) & (c[:, 0] < 3.51) & (c[:, 1] < Y - 0.05) & (c[:, 2] > 0.035)
    in_pot &= c[:, 2] < 0.81  # above the floor's 3 cm seam, which the floor takes
    seg = segment(verts, tris, SemanticsConfig())
    assert (seg.cls[in_pot] == OBJECT).all() and seg.instance.max() == 1


def test_blinds_close_before_a_wall_close_it_a_board_does_not():
    # blinds hang 6 cm before the wall at y = Y (0.3-2.3 m up, 2 m wide): within hanger_slab,
    # they close the wall there (wall class; nothing stands in the gap), while the wall
    # plane stays the one behind. A board 0.3 m before it hangs, unknown
    for gap, want in ((0.06, WALL), (0.3, UNKNOWN)):
        yb = Y - gap
        parts = [
            _quad([(0, 0, 0), (X, 0, 0), (X, Y, 0), (0, Y, 0)], (0, 0, 1)),
            _quad([(0, Y, 0), (X, Y, 0), (X, Y, Z), (0, Y, Z)], (0, -1, 0)),
            _quad([(1.0, yb, 0.3), (3.0, yb, 0.3), (3.0, yb, 2.3), (1.0, yb, 2.3)],
                  (0, -1, 0)),
        ]  # fmt: skip
        verts, tris = subdivided(parts)
        c, _, _ = triangles(verts, tris)
        hanging = np.abs(c[:, 1] - yb) < 1e-6
        seg = segment(verts, tris, SemanticsConfig())
        assert (seg.cls[hanging] == want).all(), gap
        walls = [-p["d"] * np.sign(p["normal"][1]) for p in seg.planes if p["kind"] == "wall"]
        assert np.allclose(walls, [Y], atol=0.01)

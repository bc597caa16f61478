"""Furniture as pieces: touching furniture of the procedural rooms' builders (exact heights) is
one DBSCAN cluster, split where its top steps into one instance per piece; the layout gives
each object its highest point and its top; components.json carries them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from stages.common.classes import OBJECT
from stages.common.components import with_heights
from stages.layout.openings import scene_of
from stages.layout.walls import object_heights
from stages.semantics import SemanticsConfig
from stages.semantics.config import ObjectsConfig
from stages.semantics.pieces import split_by_top
from stages.semantics.segment import segment, triangles
from stages.synth.furniture import box_mesh, build_chair, build_table

EDGE = 0.05  # triangles subdivided to this edge length (metres), as a fused surface's


def _moved(parts: list[trimesh.Trimesh], dx: float, dy: float, turn: bool = False) -> list:
    out = []
    for p in parts:
        v = np.asarray(p.vertices, np.float64).copy()
        if turn:  # half a turn about z: the back towards -y
            v[:, :2] *= -1
        out.append(trimesh.Trimesh(v + [dx, dy, 0.0], p.faces, process=False))
    return out


def _furniture() -> tuple[dict[str, list[trimesh.Trimesh]], float, float, float]:
    """Touching furniture on a 4.5 x 4 m floor: counters round the north-west corner (an L
    of two runs, 0.9 m, a microwave on one), a 2 m wardrobe against the north run's east
    end, a table against its front and a chair pushed against the table (its legs touch no
    other). Returns the parts by name, the table's top, the chair's seat and back tops."""
    rng = np.random.default_rng(0)
    table, (thx, thy), t_top = build_table(rng)
    chair, (chx, chy), c_top = build_chair(rng)
    seat = max(float(p.vertices[:, 2].max()) for p in chair[:1])
    items = {
        "north run": [box_mesh(0.6, 2.4, 3.4, 4.0, 0.0, 0.9)],
        "west run": [box_mesh(0.0, 0.6, 1.4, 4.0, 0.0, 0.9)],
        "microwave": [box_mesh(1.0, 1.5, 3.45, 3.95, 0.9, 1.2)],
        "wardrobe": [box_mesh(2.4, 3.2, 3.2, 4.0, 0.0, 2.0)],
        "table": _moved(table, 1.7, 3.4 - thy),
        "chair": _moved(chair, 1.7, 3.4 - 2 * thy - chy, turn=True),
    }
    return items, t_top, seat, c_top


def _mesh(items: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, triangles (subdivided to EDGE) and the item index of each triangle, with
    the floor and the north and west walls the furniture stands against (index -1)."""
    floor = box_mesh(-0.5, 4.0, 0.5, 4.5, -0.02, 0.0)
    quad = [[0, 1, 2], [0, 2, 3]]
    walls = [  # one face each, facing the room (as fused)
        trimesh.Trimesh([(4, 4, 0), (0, 4, 0), (0, 4, 2.5), (4, 4, 2.5)], quad),
        trimesh.Trimesh([(0, 4, 0), (0, 0.5, 0), (0, 0.5, 2.5), (0, 4, 2.5)], quad),
    ]
    parts = [(p, -1) for p in [floor, *walls]]
    parts += [(p, i) for i, ps in enumerate(items.values()) for p in ps]
    verts, tris, owner, n = [], [], [], 0
    for p, i in parts:
        edge = 4 * EDGE if i < 0 else EDGE  # the floor's plane needs no fine triangles
        v, f = trimesh.remesh.subdivide_to_size(p.vertices, p.faces, max_edge=edge)
        verts.append(v)
        tris.append(f + n)
        owner.append(np.full(len(f), i))
        n += len(v)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(owner)


def test_touching_furniture_is_one_piece_per_item_where_tops_step():
    items, _, _, _ = _furniture()
    verts, tris, owner = _mesh(items)
    c, _, area = triangles(verts, tris)
    whole = segment(verts, tris, SemanticsConfig(objects=ObjectsConfig(piece_step=0.0)))
    # without the split DBSCAN joins all but the chair: two instances
    assert whole.instance.max() == 2
    seg = segment(verts, tris, SemanticsConfig())
    names = list(items)
    boxes = [
        (np.min([p.vertices.min(0) for p in ps], 0), np.max([p.vertices.max(0) for p in ps], 0))
        for ps in items.values()
    ]
    got = {}
    for i, name in enumerate(names):
        # its faces a view could see: object triangles outside every other item's box (the
        # counter's end against the wardrobe is inside it: no fused surface holds it)
        inside = [((c >= lo - 0.01) & (c <= hi + 0.01)).all(1) for lo, hi in boxes]
        m = (owner == i) & (seg.cls == OBJECT) & ~np.any(inside[:i] + inside[i + 1 :], 0)
        ids = np.unique(seg.instance[m])
        share = np.bincount(seg.instance[m], weights=area[m]) / area[m].sum()
        got[name] = int(np.argmax(share))
        # nearly all of each item in one instance: the row of 5 cm cells where two items
        # meet goes with the taller one (the table's last row: 6 % of its faces)
        assert share.max() > 0.9, (name, dict(zip(ids, share[ids].round(3), strict=True)))
    # the microwave (0.5 m wide: a disk of 0.4 m fits) stands on the north run, not on the
    # floor: part of it, no piece of its own
    assert got["microwave"] == got["north run"]
    pieces = [got[n] for n in names if n != "microwave"]
    # one piece per straight counter run, the wardrobe, the table, the chair (its back, 4 cm
    # deep, joins its seat)
    assert len(set(pieces)) == 5 and seg.instance.max() == 5, got


def test_a_lone_piece_and_a_ragged_edge_stay_whole():
    # a 1 x 0.5 m box at 0.75 m: one piece; a 2 cm bevel of cells at 0.6 m along its edge
    # (the TSDF's rounded edge) joins it, being no wider than a disk of 0.25 m
    g = np.mgrid[0:1.0:0.02, 0:0.5:0.02].reshape(2, -1).T  # [N, 2]
    top = np.c_[g, np.full(len(g), 0.75)]
    bevel = np.c_[np.mgrid[0:1.0:0.02], np.full(50, 0.51), np.full(50, 0.6)]
    legs = np.array([[0.01, 0.01, 0.0], [0.99, 0.49, 0.0]])
    piece = split_by_top(np.concatenate([top, bevel, legs]), 0.05, 0.1, 0.25, 0.3)
    assert set(piece.tolist()) == {0}


def test_object_heights_are_its_highest_point_and_its_top():
    chair, (hx, hy), back = build_chair(np.random.default_rng(3))
    seat = float(chair[0].vertices[:, 2].max())
    mesh = trimesh.util.concatenate(chair)
    scene = scene_of(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    xy = np.mgrid[-hx + 0.01 : hx : 0.02, -hy + 0.01 : hy : 0.02].reshape(2, -1).T
    ((height, top),) = object_heights(scene, [xy], None)
    # the back covers 4 cm of the seat's 42-48 cm: the 98th percentile of the tops is the
    # back's, their median the seat's
    assert height == pytest.approx(back, abs=0.005)
    assert top == pytest.approx(seat, abs=0.005)
    assert seat < 0.5 < back


def test_components_carry_the_objects_heights():
    summary = {
        "components": [
            {"id": 1, "class": "floor", "instance": 0},
            {"id": 2, "class": "object", "instance": 3},
            {"id": 3, "class": "object", "instance": 4},
        ]
    }
    objs = [{"instance": 3, "height": 1.95, "top": 0.9}]
    out = with_heights(summary, objs)["components"]
    assert "height" not in out[0]
    assert (out[1]["height"], out[1]["top"]) == (1.95, 0.9)
    assert (out[2]["height"], out[2]["top"]) == (None, None)


def test_a_table_top_without_its_legs_is_an_object_a_wall_cabinet_is_not():
    # the fused surface of a table whose pedestal no view saw: its top alone, 0.72 m up; a
    # wall cabinet 1.5-2.1 m up; both float above the floor by more than object_max_gap
    items = {
        "table top": [box_mesh(1.0, 2.2, 1.0, 1.8, 0.70, 0.74)],
        "wall cabinet": [box_mesh(0.6, 1.8, 3.65, 4.0, 1.5, 2.1)],
    }
    verts, tris, owner = _mesh(items)
    seg = segment(verts, tris, SemanticsConfig())
    c, _, area = triangles(verts, tris)
    top = (owner == 0) & (c[:, 2] > 0.71)  # its upper faces and sides
    assert (seg.cls[top] == OBJECT).all() and seg.instance[top].min() == 1
    assert (seg.cls[owner == 1] != OBJECT).all() and seg.floating_clusters == 1
    # without the rule the table top floats too
    off = segment(verts, tris, SemanticsConfig(objects=ObjectsConfig(table_max_top=0.0)))
    assert (off.cls[owner >= 0] != OBJECT).all() and off.floating_clusters == 2


def test_a_chair_pushed_against_a_table_is_a_piece_of_its_own():
    # a chair as the 7-Scenes kitchen's: its seat 0.38 m wide at 0.45 m (8 cells of 5 cm),
    # 2 cm from the front panel of a 0.74 m table (DBSCAN joins them), its back 4 cm deep up
    # to 0.85 m on the far side. A disk of 0.4 m (9 cells across) does not fit in the seat:
    # it joined the table; the default width (0.3 m) keeps the seat, the back joining it
    s, seat = 0.38, 0.45
    y0 = 0.10  # the seat spans y 0.10-0.48: 2 cm before the table's front panel
    items = {
        "table": [
            box_mesh(1.0, 2.2, 0.5, 1.3, 0.70, 0.74),
            box_mesh(1.0, 2.2, 0.5, 0.52, 0.40, 0.70),  # its front panel, which the seat meets
        ]
        + [box_mesh(x, x + 0.05, y, y + 0.05, 0.0, 0.70) for x in (1.0, 2.15) for y in (0.5, 1.25)],
        "chair": [
            box_mesh(1.41, 1.41 + s, y0, y0 + s, seat - 0.04, seat),
            box_mesh(1.41, 1.41 + s, y0, y0 + 0.04, seat, 0.85),
        ]
        + [box_mesh(x, x + 0.03, y, y + 0.03, 0.0, seat - 0.04)
           for x in (1.41, 1.41 + s - 0.03) for y in (y0, y0 + s - 0.03)],
    }  # fmt: skip
    verts, tris, owner = _mesh(items)
    _, _, area = triangles(verts, tris)
    whole = segment(verts, tris, SemanticsConfig(objects=ObjectsConfig(piece_step=0.0)))
    assert whole.instance.max() == 1  # one cluster
    for objs, pieces in ((ObjectsConfig(), 2), (ObjectsConfig(piece_min_width=0.4), 1)):
        seg = segment(verts, tris, SemanticsConfig(objects=objs))
        width = objs.piece_min_width
        assert seg.instance.max() == pieces, width
        got = []
        for i in (0, 1):
            m = (owner == i) & (seg.cls == OBJECT)
            share = np.bincount(seg.instance[m], weights=area[m]) / area[m].sum()
            assert share.max() > 0.85, (width, i, share.round(3))
            got.append(int(np.argmax(share)))
        assert (got[0] != got[1]) == (pieces == 2)

"""What an edit gives besides its renders, on the analytic scene of tests/stages/edit_scene.py:
the edit metrics (worked out by hand), the edited mesh and the edited plan.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from stages.common.blueprint import Blueprint
from stages.edit.config import EditConfig, SelectConfig
from stages.edit.metrics import EditScore, changed, match_instances, pooled_iou
from stages.edit.ops import edit_mesh
from stages.edit.spec import Edit, EditSpec, Selector
from tests.stages.edit_scene import _edit, _plan, _select

torch.set_num_threads(1)


def test_metrics_by_hand():
    b = np.zeros((2, 3, 3))
    a = b.copy()
    a[0, 0] = 0.5  # changed
    a[0, 1] = 0.01  # below the 0.02 threshold
    a[1, 2] = 0.1  # changed, outside the selection
    ch = changed(b, a, 0.02)
    assert ch.tolist() == [[True, False, False], [False, False, True]]
    sel = np.array([[True, True, False], [False, False, False]])
    gt = np.array([[True, True, False], [False, False, False]])
    # intersection {(0,0)}, union {(0,0), (0,1), (1,2)}: 1/3
    assert pooled_iou([ch], [gt]) == pytest.approx(1 / 3)
    # outside the selection: 4 pixels x 3 channels, one pixel off by 0.1 on 3 channels:
    # MSE = 3 * 0.01 / 12 = 0.0025, PSNR = -10 log10(0.0025) = 26.0206. With the view's GT
    # instances (4 on the first two pixels, as gt) the matched instance is 4 and the IoU 1/3
    score = EditScore(0.02)
    score.add(b, a, sel, np.where(gt, 4, 0))
    res = score.result({})
    assert res["psnr_outside"] == pytest.approx(26.0206, abs=1e-3)
    assert res["changed_iou"] == pytest.approx(0.3333, abs=1e-4)
    assert res["gt_instances"] == [{"id": 4, "name": ""}]
    # the same view twice: the same pooled figures; a view without GT: no IoU, a note
    score.add(b, a, sel, np.where(gt, 4, 0))
    assert score.result({})["changed_iou"] == res["changed_iou"]
    assert score.result({})["changed_iou_views"] == [0.3333, 0.3333]
    # a third view where nothing changed over the same GT pixels: IoU 0 there, pooled
    # 2 / (3 + 3 + 2) = 0.25
    score.add(b, b, sel, np.where(gt, 4, 0))
    assert score.result({})["changed_iou_views"] == [0.3333, 0.3333, 0.0]
    assert score.result({})["changed_iou"] == 0.25
    score.add(b, a, sel, None)
    assert score.result({})["changed_iou"] is None and score.result({})["note"]
    # instance 3 is the most overlapped (2 px), instance 5 is half inside (1 of 2 px), 7 not
    inst = np.array([[3, 3, 5], [5, 7, 7]])
    m = np.array([[True, True, True], [False, False, False]])
    assert match_instances([m], [inst]) == [3, 5]
    assert match_instances([np.zeros_like(m)], [inst]) == []
    # instance 9 is wholly inside but 1 px against 40 px of the best (< 5 %): not matched
    big = np.zeros((5, 10), np.int32)
    big[:4] = 3
    big[4, 0] = 9
    assert match_instances([np.ones((5, 10), bool)], [big]) == [3]


def test_mesh_edits():
    # a grey floor quad at z = 0 over [0, 2]^2 and a red box standing off the floor inside A's
    # cells ([0.45, 0.75]^2 x [0.1, 0.5], like a seat), subdivided into small faces. With the
    # default floor_clear (0.02) A's extent spans z 0.02 .. 0.55 over A's cells: every box
    # face lies inside it, no floor face does (z = 0).
    floor = trimesh.Trimesh([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]], [[0, 1, 2], [0, 2, 3]])
    box = trimesh.creation.box(bounds=[[0.45, 0.45, 0.1], [0.75, 0.75, 0.5]])
    for _ in range(3):
        floor, box = floor.subdivide(), box.subdivide()
    nv = len(floor.vertices)
    rgba = np.r_[
        np.tile([128, 128, 128, 255], (nv, 1)), np.tile([255, 0, 0, 255], (len(box.vertices), 1))
    ]
    mesh = trimesh.Trimesh(
        np.r_[floor.vertices, box.vertices],
        np.r_[floor.faces, box.faces + nv],
        vertex_colors=rgba,
        process=False,
    )
    cfg = EditConfig(select=SelectConfig(pad=0.0))
    a = _select("click", (0.6, 0.6))
    out, stats = edit_mesh(mesh, [_edit("remove", a, cfg)])
    assert stats["faces_removed"] == len(box.faces)
    assert len(out.faces) == len(floor.faces) and len(out.vertices) == nv
    assert np.all(out.vertices[:, 2] == 0.0)
    # sketch A green (flat): the box's vertices only
    green = torch.tensor([0.0, 1.0, 0.0])
    out2, st2 = edit_mesh(mesh, [_edit("sketch", a, cfg, color=green)])
    assert len(out2.faces) == len(mesh.faces)
    col = np.asarray(out2.visual.vertex_colors)
    assert np.all(col[nv:, :3] == [0, 255, 0]) and np.all(col[:nv, :3] == 128)
    assert st2["vertices_recolored"] == len(box.vertices)


def test_edited_plan_relabels_removed_cells():
    from stages.edit.select import edited_plan

    bp = _plan()
    a = _select("click", (0.6, 0.6))
    floor = _select("pixel", (0, 0))  # the floor component: every cell but the two chairs'
    edits = [
        Edit(0, "remove", Selector("click", (0.6, 0.6))),
        Edit(1, "recolor", Selector("pixel", (0, 0))),
    ]
    # removing A makes its 16 cells floor; a recolour changes no label
    new, n = edited_plan(EditConfig(), bp, EditSpec(Path("e.yaml"), tuple(edits), (0,)), [a, floor])
    assert n == 16 and np.all(new.labels[a] == 0) and np.all(new.labels[~a] == bp.labels[~a])
    new, n = edited_plan(
        EditConfig(removed_label="unknown"),
        bp,
        EditSpec(Path("e.yaml"), tuple(edits), (0,)),
        [a, floor],
    )
    assert n == 16 and np.all(new.labels[a] == 255)
    # removing the floor itself leaves unknown cells, whatever removed_label says
    rm_floor = [Edit(0, "remove", Selector("pixel", (0, 0)))]
    new, n = edited_plan(EditConfig(), bp, EditSpec(Path("e.yaml"), tuple(rm_floor), (0,)), [floor])
    assert n == 400 - 32 and np.all(new.labels[floor] == 255)


def test_edited_plan_keeps_instances_but_the_removed_ones():
    from stages.edit.select import edited_plan

    bp = _plan()
    inst = np.zeros(bp.labels.shape, np.int32)
    inst[bp.labels != 0] = 7  # both chairs one instance here: only the clicked cells lose it
    bp = replace(bp, instances=inst)
    a = _select("click", (0.6, 0.6))
    edits = (Edit(0, "remove", Selector("click", (0.6, 0.6))),)
    new, _ = edited_plan(EditConfig(), bp, EditSpec(Path("e.yaml"), edits, (0,)), [a])
    assert new.instances is not None
    assert np.all(new.instances[a] == 0) and np.all(new.instances[~a] == inst[~a])
    assert (inst[~a] == 7).any()


def test_edited_plan_keeps_seen_and_inside_through_save(tmp_path):
    """An edit changes labels, not what the capture saw: seen and inside survive the edit
    and the saved file; a removed object's cells are floor inside the outline, unknown
    outside it."""
    from stages.edit.select import edited_plan

    bp = _plan()
    a = _select("click", (0.6, 0.6))
    seen = np.zeros(bp.labels.shape, np.uint8)
    seen[::2] = 1
    inside = np.ones(bp.labels.shape, np.uint8)
    rows = np.flatnonzero(a.any(axis=1))
    inside[rows[0]] = 0  # one row of the chair lies outside the outline
    bp = replace(bp, seen=seen, inside=inside)
    edits = (Edit(0, "remove", Selector("click", (0.6, 0.6))),)
    new, n = edited_plan(EditConfig(), bp, EditSpec(Path("e.yaml"), edits, (0,)), [a])
    new.save(tmp_path / "edited.npz")
    back = Blueprint.load(tmp_path / "edited.npz")
    assert np.array_equal(back.seen, seen) and np.array_equal(back.inside, inside)
    out = a & (inside == 0)
    assert out.any() and np.all(back.labels[out] == 255)
    assert np.all(back.labels[a & (inside == 1)] == 0) and n == int(a.sum())

"""The edited view (stages/edit/view.py): one picture whatever way it is asked for. An
untrained field and a fused mesh of boxes: pixels are compared, not judged."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from stages.common.camera import Intrinsics
from stages.common.components import component_map
from stages.common.errors import BlunfError
from stages.common.radiance.scene import build_model
from stages.edit.config import EditConfig, RenderConfig, SelectConfig
from stages.edit.render import look_at
from stages.edit.spec import Edit, Selector
from stages.edit.view import MASK_TINT, EditedView
from stages.nerf.config import NerfConfig
from tests.conftest import tune
from tests.stages.edit_scene import BOX_A, BOX_B, CFG, _plan

torch.set_num_threads(1)
INTR = Intrinsics(16.0, 16.0, 7.5, 5.5, 16, 12)
POSE = look_at(np.array([1.0, -0.8, 1.2]), np.array([1.0, 1.0, 0.2]))


def _mesh() -> trimesh.Trimesh:
    """The floor slab and the two boxes of edit_scene, dense enough for an extent's heights."""
    parts = [trimesh.creation.box(bounds=[[0, 0, -0.1], [2, 2, 0]])]
    for x0, x1, y0, y1 in (BOX_A, BOX_B):
        parts.append(trimesh.creation.box(bounds=[[x0, y0, 0], [x1, y1, 0.5]]))
    m = trimesh.util.concatenate(parts)
    for _ in range(4):
        m = m.subdivide()
    return m


@pytest.fixture(scope="module")
def view() -> EditedView:
    torch.manual_seed(0)
    ncfg = tune(NerfConfig(), field__hash_log2_size=10, field__hash_levels=2, field__width=16,
                sampling__samples_across=64)  # fmt: skip
    model = build_model(ncfg, torch.tensor([0.0, 0.0, -0.1]), torch.tensor([2.0, 2.0, 1.0]), [], [])
    bp = _plan()
    cfg = EditConfig(select=SelectConfig(floor_clear=0.0, pad=0.0), render=RenderConfig(chunk=50))
    return EditedView(cfg, model, _mesh(), bp, component_map(bp))


EDITS = (
    Edit(0, "recolor", Selector("click", (0.6, 0.6)), color=(40, 200, 40), strength=1.0),
    Edit(1, "mask", Selector("click", (1.4, 1.4))),
    Edit(2, "remove", Selector("click", (1.4, 1.4))),
)


@pytest.mark.parametrize("fast", [False, True])
def test_one_picture_however_it_is_asked_for(view, fast) -> None:
    before = view.before(POSE, INTR, EDITS, fast)
    assert before.masks.shape == (3, 12, 16) and before.renders == 1
    alone = view.render(POSE, INTR, EDITS, fast)  # the mask drawn from an unedited render
    reused = view.render(POSE, INTR, EDITS, fast, unedited=before)  # ... or the one given
    assert alone.renders == 2 and reused.renders == 1
    assert np.array_equal(alone.rgb, reused.rgb) and np.array_equal(alone.image, reused.image)
    # the mask edit's selection, the unedited scene's (the removed box keeps its mask),
    # blended half with magenta over the field edits' picture
    sel = before.masks[1]
    assert np.array_equal(alone.masks[0], sel)
    want = np.where(sel[..., None], 0.5 * alone.field_rgb + 0.5 * MASK_TINT, alone.field_rgb)
    assert np.array_equal(alone.rgb, want)
    # no edit: the unedited picture, untinted
    plain = view.render(POSE, INTR, (), fast)
    assert np.array_equal(plain.rgb, before.rgb) and plain.masks.shape == (0, 12, 16)
    assert (plain.volume_rendered is not None) == fast


def test_each_edit_is_resolved_once(view) -> None:
    a = view.resolve(EDITS[0])
    assert view.resolve(EDITS[0]) is a and a.edit.op == "recolor"
    assert [c["class"] for c in a.components] == ["chair"]
    assert view.resolve(EDITS[2]).edit.fill is not None  # the floor round the box: its colour


def test_no_field_no_render(view) -> None:
    blind = EditedView(CFG, None, _mesh(), view.bp, view.cmap)
    assert blind.verts.shape[1] == 3  # the mesh is there to show
    with pytest.raises(BlunfError, match="no trained NeRF"):
        blind.render(POSE, INTR, EDITS)

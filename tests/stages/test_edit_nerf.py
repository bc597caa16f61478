"""The edit stage end to end on a tiny procedural room: fused mesh, a briefly trained NeRF,
the exact plan. Checks the mechanics (files, plan and mesh edits, metrics computed, the
other chair of the same class untouched on the plan); the accuracy bars wait for a better
NeRF (see the report)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from stages.common.blueprint import Blueprint
from stages.common.capture import read_layout
from stages.common.io import read_json, read_label
from stages.edit import IMPLS, EditConfig, EditInputs, EditOutputs, spec_textures
from stages.edit.config import GifConfig, RenderConfig
from stages.fusion import IMPLS as FUSION
from stages.fusion import FusionConfig, FusionInputs
from stages.nerf import IMPLS as NERF
from stages.nerf import NerfConfig, NerfInputs
from stages.synth import make_room
from stages.synth.room import CHAIR, FLOOR
from tests.conftest import tune

# NeRF training (25-100 CPU-s, as the NeRF stage stands), fusion, ~20 renders of 96 x 72
pytestmark = pytest.mark.slow

torch.set_num_threads(1)

NERF_CFG = tune(
    NerfConfig(),
    threads=1,
    train__max_steps=200,
    train__time_budget=0.0,
    train__batch_rays=1024,
    train__eval_every=0,
)
# seed 3: chair_2 (instance 3) at x 1.83..2.34, y 1.84..2.34; sofa_1 (7) x 0.07..0.90,
# y 0.10..2.28; table_1 (1) x 2.32..3.42, y 1.83..3.29 (gt/instances.json). Frames 0 and 6
# see chair_2, the sofa or the table, and chair_1 (another chair).
SPEC = """\
edits:
  - {select: {click: [2.08, 2.09]}, op: remove}
  - {select: {click: [0.48, 1.19]}, op: recolor, color: [40, 200, 40], strength: 0.8}
  - {select: {click: [2.87, 2.56]}, op: retexture, texture: tex/checker.png}
  - {select: {click: [2.08, 2.09]}, op: mask}
views: [0, 6]
"""


@pytest.fixture(scope="module")
def edited(tmp_path_factory) -> tuple[Path, Path, EditOutputs, EditInputs]:
    tmp = tmp_path_factory.mktemp("edit_e2e")
    room = make_room(tmp / "room", views=8, seed=3, size=(96, 72))
    frames = tmp / "frames.json"
    read_layout(room).save(frames)
    (tmp / "fusion").mkdir()
    fused = FUSION["tsdf"](FusionConfig(voxel=0.03), FusionInputs(frames), tmp / "fusion")
    (tmp / "nerf").mkdir()
    nerf = NERF["grid"](NERF_CFG, NerfInputs(frames), tmp / "nerf")
    (tmp / "spec" / "tex").mkdir(parents=True)
    checker = np.kron([[1, 0], [0, 1]], np.ones((4, 4)))[..., None] * [255, 255, 0]
    Image.fromarray(checker.astype(np.uint8)).save(tmp / "spec" / "tex" / "checker.png")
    spec = tmp / "spec" / "edits.yaml"
    spec.write_text(SPEC)
    inputs = EditInputs(
        spec=spec,
        blueprint=room / "gt" / "blueprint.npz",
        model=nerf.model,
        mesh=fused.mesh,
        frames=frames,
        gt=room / "gt",
        textures=spec_textures(spec),
    )
    out = tmp / "edit"
    out.mkdir()
    cfg = EditConfig(gif=GifConfig(frames=3), render=RenderConfig(threads=1))
    return room, fused.mesh, IMPLS["nerf"](cfg, inputs, out), inputs


def test_outputs_written(edited):
    room, _, outs, _ = edited
    assert outs == EditOutputs.at(outs.stats.parent)
    for name in ("0000", "0006"):
        img = Image.open(outs.views / f"{name}.png")
        assert img.size == (2 * 96 + 4, 72)  # before | 4 px | after
        for i in range(4):
            assert Image.open(outs.masks / f"{name}_{i}.png").size == (96, 72)
    gif = Image.open(outs.gif)
    assert gif.n_frames == 3 and gif.size == (48, 36)  # gif_scale 0.5
    assert outs.blueprint_png.stat().st_size > 0


def test_plan_and_mesh_edits(edited):
    room, mesh_in, outs, _ = edited
    before = Blueprint.load(room / "gt" / "blueprint.npz")
    after = Blueprint.load(outs.blueprint)
    # chair_2's component became floor; every other cell is unchanged (the other chairs too)
    diff = after.labels != before.labels
    assert diff.any()
    assert np.all(before.labels[diff] == CHAIR) and np.all(after.labels[diff] == FLOOR)
    r, c, _ = before.grid.cell_of(np.array([[2.08, 2.09]]))
    assert after.labels[r[0], c[0]] == FLOOR
    assert (before.labels == CHAIR).sum() - diff.sum() == (after.labels == CHAIR).sum() > 0
    # the mesh lost chair_2's faces (and kept most of the rest), and the sofa changed colour
    m0 = trimesh.load(mesh_in, force="mesh", process=False)
    m1 = trimesh.load(outs.mesh, force="mesh", process=False)
    stats = read_json(outs.stats)
    removed = stats["mesh"]["faces_removed"]
    assert 0 < removed < 0.2 * len(m0.faces) and len(m1.faces) == len(m0.faces) - removed
    assert stats["mesh"]["vertices_recolored"] > 0
    chair2 = (
        (m1.vertices[:, 0] > 1.9)
        & (m1.vertices[:, 0] < 2.27)
        & (m1.vertices[:, 1] > 1.9)
        & (m1.vertices[:, 1] < 2.27)
        & (m1.vertices[:, 2] > 0.1)
    )
    assert not chair2.any()


def test_metrics_and_masks(edited):
    room, _, outs, _ = edited
    stats = read_json(outs.stats)
    ms = stats["metrics"]["edit"]
    assert [m["op"] for m in ms] == ["remove", "recolor", "retexture", "mask"]
    for m, rec in zip(ms, stats["edits"], strict=True):
        assert set(m) == {"index", "op", "changed_iou", "changed_iou_views", "psnr_outside"}
        assert 0.0 <= m["changed_iou"] <= 1.0 and m["psnr_outside"] > 0
        # one IoU per requested view (None where the view shows neither the object nor a
        # change: the sofa is out of view 6); the pooled one lies within them
        per_view = m["changed_iou_views"]
        seen = [v for v in per_view if v is not None]
        assert len(per_view) == len(stats["views"]) and seen
        assert min(seen) - 1e-4 <= m["changed_iou"] <= max(seen) + 1e-4
        assert rec["metrics"]["gt_instances"], rec
    # each selection matched its own object: chair_2 = 3, sofa_1 = 7, table_1 = 1
    got = [[g["name"] for g in rec["metrics"]["gt_instances"]] for rec in stats["edits"]]
    assert got[0] == ["chair_2"] and got[1] == ["sofa_1"] and got[2] == ["table_1"]
    # the mask of chair_2 in view 0 is mostly chair_2's GT pixels and covers most of them;
    # of chair_1 it may touch a pixel or two where the two chairs' outlines meet (measured:
    # 597 of chair_2's 611 pixels, 15 floor pixels, 1 of chair_1's 379)
    inst = read_label(room / "gt" / "instances" / "0000.png")
    mask = read_label(outs.masks / "0000_0.png") > 0
    assert (inst[mask] == 3).mean() > 0.8 and mask[inst == 3].mean() > 0.8
    assert (mask & (inst == 2)).sum() <= 0.01 * (inst == 2).sum()


def test_surface_render_path_changes_what_the_volume_render_changes(edited, tmp_path):
    """edit.render.path=surface (the fused mesh ray-cast, the field asked at the hit) on the same
    NeRF and spec: the same plan; in view 0, which the 8-view mesh covers, each edit changes
    the pixels the volume render changes, within a few points of its IoU against the ground
    truth (measured: remove 0.932 against 0.959, mask 0.949 against 0.992). In view 6 chair_2
    stands at the image's edge, half in front of the near views, and the fusion missed its
    near side: the rays pass on to the floor and the mask there is 0.62 against 0.98, the
    path's known limit (what the mesh lacks, it cannot outline)."""
    room, _, outs, inputs = edited
    out = tmp_path / "surface"
    out.mkdir()
    cfg = EditConfig(gif=GifConfig(frames=3), render=RenderConfig(path="surface", threads=1))
    fast = IMPLS["nerf"](cfg, inputs, out)
    a, b = read_json(outs.stats), read_json(fast.stats)
    assert (a["render"]["path"], b["render"]["path"]) == ("volume", "surface")
    bp_a, bp_b = Blueprint.load(outs.blueprint), Blueprint.load(fast.blueprint)
    assert np.array_equal(bp_a.labels, bp_b.labels)
    for va, vb in zip(a["metrics"]["edit"], b["metrics"]["edit"], strict=True):
        assert vb["changed_iou_views"][0] >= va["changed_iou_views"][0] - 0.05, (va, vb)
    m_vol = read_label(outs.masks / "0000_0.png") > 0
    m_fast = read_label(fast.masks / "0000_0.png") > 0
    assert (m_vol & m_fast).sum() > 0.85 * (m_vol | m_fast).sum()

"""Edits on an analytic field whose renders are worked out by hand: selections and extents
on the plan, then every edit op rendered. The scene, the camera and the plan are described in
tests/stages/edit_scene.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from stages.common.components import component_map
from stages.common.radiance.field import FieldFns, field_of
from stages.common.radiance.rays import camera_rays
from stages.common.radiance.render import RenderOptions
from stages.edit.config import EditConfig, SelectConfig
from stages.edit.metrics import PSNR_CAP, EditScore
from stages.edit.ops import edit_colors, fill_ground
from stages.edit.render import render_rays_edited
from stages.edit.select import _top, extent_of
from stages.edit.spec import Edit, Selector
from tests.stages.edit_scene import (
    BLUE,
    CFG,
    GREY,
    INTR,
    POSE,
    RED,
    _edit,
    _floor,
    _gt_instances,
    _plan,
    _render,
    _select,
    _vertices,
    color,
    density,
)

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def before() -> dict:
    return _render()


def test_unedited_render_matches_the_hand_geometry(before):
    rgb = before["rgb"]
    inst = _gt_instances()
    np.testing.assert_allclose(rgb[inst == 1], np.tile(RED, ((inst == 1).sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(rgb[inst == 2], np.tile(BLUE, ((inst == 2).sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(rgb[inst == 0], np.tile(GREY, ((inst == 0).sum(), 1)), atol=1e-6)


def test_selections_on_the_plan():
    a = np.zeros((20, 20), bool)
    a[12:16, 4:8] = True
    b = np.zeros((20, 20), bool)
    b[4:8, 12:16] = True
    # a click on A picks A's component only, not the other chair
    assert np.array_equal(_select("click", (0.6, 0.6)), a)
    # pixel [u, v] = column 13, row 5 lies in B
    assert np.array_equal(_select("pixel", (13, 5)), b)
    assert np.array_equal(_select("class", "chair"), a | b)
    # a square of centres 1.15 .. 1.65: columns 11..16, rows 3..8 (B and a ring of floor)
    sq = np.zeros((20, 20), bool)
    sq[3:9, 11:17] = True
    poly = ((1.1, 1.1), (1.7, 1.1), (1.7, 1.7), (1.1, 1.7))
    assert np.array_equal(_select("polygon", poly), sq)
    # a stroke along y = 1 of width 0.2: centres within 0.1 of it are rows 9 (y 1.05) and 10
    # (y 0.95); rows 8 and 11 are 0.15 away
    st = np.zeros((20, 20), bool)
    st[9:11, :] = True
    assert np.array_equal(_select("stroke", ((0.05, 1.0), (1.95, 1.0)), 0.2), st)


def test_extent_heights_padding_and_contains():
    bp = _plan()
    v, _ = _vertices()
    poly = ((1.1, 1.1), (1.7, 1.1), (1.7, 1.7), (1.1, 1.7))
    cfg = EditConfig(select=SelectConfig(pad=0.0))
    ext, info = extent_of(_select("polygon", poly), bp, component_map(bp), v, cfg)
    # B's cells: from floor_clear 0.02 to its top 0.5 (the ceiling at 2.5 lies 2 m above,
    # past the 0.3 m gap) + top_margin 0.05; the floor ring keeps the slab |z| <= 0.05
    assert np.all(ext.zlo[4:8, 12:16] == np.float32(0.02))
    assert np.all(ext.zhi[4:8, 12:16] == np.float32(0.55))
    ring = ext.footprint & ~np.pad(np.ones((4, 4), bool), ((4, 12), (12, 4)))
    assert ring.sum() == 36 - 16
    assert np.all(ext.zlo[ring] == np.float32(-0.05)) and np.all(ext.zhi[ring] == np.float32(0.05))
    assert sorted(i["class"] for i in info) == ["chair", "floor"]
    pts = np.array(
        [
            [1.4, 1.4, 0.3],  # inside B
            [1.4, 1.4, 0.01],  # below floor_clear over B: the floor under it is kept
            [1.4, 1.4, 0.6],  # above B's top + margin
            [1.4, 1.4, 2.5],  # the ceiling
            [1.15, 1.15, 0.0],  # the floor ring
            [1.15, 1.15, 0.3],  # above the floor ring's slab
            [0.6, 0.6, 0.3],  # inside A: not selected
        ]
    )
    assert ext.contains(pts).tolist() == [True, False, False, False, True, False, False]
    assert ext.contains(torch.from_numpy(pts).float()).tolist() == ext.contains(pts).tolist()
    # pad 0.1 m = one 0.1 m cell: A's 4 x 4 cells grow to 6 x 6, all with A's range
    cfg = EditConfig(select=SelectConfig(pad=0.1))
    big, _ = extent_of(_select("click", (0.6, 0.6)), bp, component_map(bp), v, cfg)
    assert big.footprint.sum() == 36 and big.footprint[11:17, 3:9].all()
    assert np.all(big.zhi[big.footprint] == np.float32(0.55))
    assert big.bbox() == pytest.approx((0.3, 0.3, 0.9, 0.9))


def test_top_skips_small_runs_and_what_is_above():
    cfg = EditConfig()
    # 2 noise vertices at 0.1, then 40 of a chair from 0.4 to 0.8, then 50 of a ceiling:
    # need = 5 % of 92 = 4.6, so the noise run is skipped and the chair's top is 0.8
    z = np.r_[[0.1, 0.1], np.linspace(0.4, 0.8, 40), np.full(50, 2.6), [0.0] * 30]
    assert _top(z, cfg) == pytest.approx(0.8)
    # only floor vertices (all within the floor band): the top is the band itself
    assert _top(np.array([0.0, 0.01, 0.04]), cfg) == pytest.approx(0.05)


def test_remove_reveals_the_floor_and_leaves_the_rest(before):
    a_cells = _select("click", (0.6, 0.6))
    e = _edit("remove", a_cells)
    after = _render([e], [e.extent])
    inst = _gt_instances()
    # A's pixels now see the floor under it; every other pixel is bit-identical, B included
    np.testing.assert_allclose(after["rgb"][inst == 1], np.tile(GREY, (16, 1)), atol=1e-6)
    assert np.array_equal(after["rgb"][inst != 1], before["rgb"][inst != 1])
    # the mask, on the unedited field: weight 1 exactly on A's pixels, 0 elsewhere
    m = _render((), [e.extent])["masks"][0]
    assert np.array_equal(m >= 0.5, inst == 1)
    # the metrics: changed pixels = A's pixels = A's GT mask, so IoU is exactly 1; nothing
    # changed outside the mask, so PSNR hits the cap
    score = EditScore(0.02)
    score.add(before["rgb"], after["rgb"], m >= 0.5, inst)
    res = score.result({1: "A", 2: "B"})
    assert res["gt_instances"] == [{"id": 1, "name": "A"}]
    assert res["changed_iou"] == 1.0 and res["psnr_outside"] == PSNR_CAP
    assert res["changed_pixels"] == res["selected_pixels"] == 16
    # removing both chairs by class: both show the floor
    both = _render([_edit("remove", _select("class", "chair"))])["rgb"]
    np.testing.assert_allclose(both, np.full((20, 20, 3), 0.5), atol=1e-6)


def test_remove_fills_ground_no_view_saw(before):
    # the floor slab has a hole under A (no view saw the ground there): removed without a
    # fill, A's pixels see through to nothing (black); with one, exactly they take the fill,
    # and a floor that is there (B's, with B removed) is rendered, never filled over
    def holed(x: torch.Tensor) -> torch.Tensor:
        under_a = (x[:, 0] >= 0.4) & (x[:, 0] < 0.8) & (x[:, 1] >= 0.4) & (x[:, 1] < 0.8)
        return torch.where(_floor(x) & under_a & (x[:, 2] < 0), 0.0, density(x))

    o, d, _ = camera_rays(POSE, INTR)
    inst = _gt_instances()
    green = torch.tensor([0.0, 1.0, 0.0])

    def render(edits) -> np.ndarray:
        opts = RenderOptions(near=19.0, far=20.2, step=0.01)
        out = render_rays_edited(o, d, field_of(holed, color), opts, edits)
        return out["rgb"].view(20, 20, 3).numpy()

    a = _edit("remove", _select("click", (0.6, 0.6)))
    b = _edit("remove", _select("pixel", (13, 5)), fill=green)
    plain = render([a, b])
    np.testing.assert_allclose(plain[inst == 1], 0.0, atol=1e-6)
    filled = render([replace(a, fill=green), b])
    np.testing.assert_allclose(filled[inst == 1], np.tile([0.0, 1.0, 0.0], (16, 1)), atol=1e-6)
    np.testing.assert_allclose(filled[inst == 2], np.tile(GREY, (16, 1)), atol=1e-6)
    assert np.array_equal(filled[inst == 0], before["rgb"][inst == 0])
    # the same through the view renderer (the NeRF path): over A's footprint only
    e = replace(a, fill=green)
    rgb, acc = fill_ground([e], o, d, torch.zeros(400, 3), torch.zeros(400))
    assert np.array_equal((acc.view(20, 20) > 0).numpy(), inst == 1)
    half = fill_ground([e], o, d, torch.zeros(400, 3), torch.full((400,), 0.5))[0]
    np.testing.assert_allclose(half.view(20, 20, 3).numpy()[inst == 1], [[0, 0.5, 0]] * 16)


def test_fill_is_the_floor_colour_round_the_footprint():
    # A removed: its fill is the median colour of the floor vertices within 0.2 m of its
    # footprint (green here), not of the floor further out (red), nor of the box (blue);
    # the field is asked only when the mesh has no colours; no fill for a recolour, for a
    # removal of floor, or without floor round the footprint
    from stages.edit.view import ground_fill

    bp = _plan()
    cells = _select("click", (0.6, 0.6))
    ext, comps = extent_of(cells, bp, component_map(bp), _vertices()[0], CFG)
    g = np.arange(0.025, 2.0, 0.05)
    xx, yy = np.meshgrid(g, g)
    floor = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
    box = np.array([[0.6, 0.6, 0.3], [0.5, 0.7, 0.5]])
    verts = np.concatenate([floor, box])
    d = np.maximum(np.abs(floor[:, 0] - 0.6), np.abs(floor[:, 1] - 0.6))  # square distance
    cols = np.where((d > 0.2) & (d < 0.35), 1, 0)[:, None] * [0.0, 1.0, 0.0]
    cols = np.where((d >= 0.45)[:, None], [1.0, 0.0, 0.0], cols)
    cols = np.concatenate([cols, [[0.0, 0.0, 1.0]] * 2])
    ring = (d > 0.2) & (d < 0.4)  # the band's vertices: most green, the outer row black
    assert ring.sum() > 40

    class NoField:
        def fns(self, semantics: bool = True) -> FieldFns:
            raise AssertionError("the mesh has colours: the field is not asked")

    e = Edit(0, "remove", Selector("click", (0.6, 0.6)))
    fill = ground_fill(CFG, e, ext, comps, verts, cols, NoField())
    assert fill is not None and torch.equal(fill, torch.tensor([0.0, 1.0, 0.0]))
    grey = ground_fill(CFG, e, ext, comps, verts, None, _FieldOf(density, color))
    assert grey is not None and torch.allclose(grey, torch.tensor(GREY))
    assert ground_fill(CFG, replace(e, op="recolor"), ext, comps, verts, cols, NoField()) is None
    floor_comp = [{**comps[0], "class": "floor"}]
    assert ground_fill(CFG, e, ext, floor_comp, verts, cols, NoField()) is None
    assert ground_fill(CFG, e, ext, comps, box, cols[-2:], NoField()) is None


class _FieldOf:
    """A model-like object over the analytic field (what `ground_fill` asks: its functions)."""

    def __init__(self, density_fn, color_fn) -> None:
        self.density, self.color = density_fn, color_fn

    def fns(self, semantics: bool = True) -> FieldFns:
        return field_of(self.density, self.color)


def test_recolor_keeps_shading_and_touches_only_the_selection(before):
    # B is flat blue, its vertices too: shading = lum(sample) / median lum = 1, so the new
    # colour is 0.5 blue + 0.5 green = (0, 0.5, 0.5) on B's pixels
    e = _edit(
        "recolor", _select("pixel", (13, 5)), color=torch.tensor([0.0, 1.0, 0.0]), strength=0.5
    )
    assert e.ref_lum == pytest.approx(0.0722)
    after = _render([e])["rgb"]
    inst = _gt_instances()
    np.testing.assert_allclose(after[inst == 2], np.tile((0.0, 0.5, 0.5), (16, 1)), atol=1e-5)
    assert np.array_equal(after[inst != 2], before["rgb"][inst != 2])
    # a sample half as bright as the reference gets half the colour: shading is kept
    x = torch.tensor([[1.4, 1.4, 0.3]])
    dark = edit_colors([e], x, torch.tensor([[0.0, 0.0, 0.5]]))
    torch.testing.assert_close(dark, torch.tensor([[0.0, 0.25, 0.25]]), atol=1e-6, rtol=0)


def test_retexture_maps_the_image_over_the_bounding_box(before):
    # a 2 x 2 texture over B's box [1.2, 1.6]^2, row 0 = north: top-left red, top-right green,
    # bottom-left white, bottom-right black. B's top is seen at x = 1.244, 1.341 (west half,
    # columns u 12, 13), 1.439, 1.536 (east, u 14, 15); y = 1.536, 1.439 (north, v 4, 5),
    # 1.341, 1.244 (south, v 6, 7). Shading 1 (flat blue), strength 1: the texels exactly.
    tex = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]], [[1.0, 1.0, 1.0], [0, 0, 0]]])
    after = _render([_edit("retexture", _select("pixel", (13, 5)), texture=tex)])["rgb"]
    np.testing.assert_allclose(after[4:6, 12:14], np.broadcast_to(RED, (2, 2, 3)), atol=1e-5)
    np.testing.assert_allclose(after[4:6, 14:16], np.broadcast_to((0, 1, 0), (2, 2, 3)), atol=1e-5)
    np.testing.assert_allclose(after[6:8, 12:14], np.ones((2, 2, 3)), atol=1e-5)
    np.testing.assert_allclose(after[6:8, 14:16], np.zeros((2, 2, 3)), atol=1e-5)
    inst = _gt_instances()
    assert np.array_equal(after[inst != 2], before["rgb"][inst != 2])


def test_sketch_paints_the_stroke_on_the_floor(before):
    # the stroke's cells are rows 9 and 10 of the plan: floor, so its extent is the floor slab;
    # the floor seen by pixel rows v 9 (y 1.05) and 10 (y 0.95) lies in them, all columns
    e = _edit(
        "sketch",
        _select("stroke", ((0.05, 1.0), (1.95, 1.0)), 0.2),
        color=torch.tensor([1.0, 1.0, 0.0]),
    )
    after = _render([e])["rgb"]
    np.testing.assert_allclose(after[9:11], np.broadcast_to((1, 1, 0), (2, 20, 3)), atol=1e-6)
    rest = np.ones(20, bool)
    rest[9:11] = False
    assert np.array_equal(after[rest], before["rgb"][rest])


def test_edits_compose_and_mask_changes_nothing(before):
    a = _edit("remove", _select("click", (0.6, 0.6)))
    b = _edit(
        "recolor", _select("pixel", (13, 5)), color=torch.tensor([0.0, 1.0, 0.0]), strength=1.0
    )
    m = _edit("mask", _select("pixel", (13, 5)))
    after = _render([a, b, m])["rgb"]
    inst = _gt_instances()
    np.testing.assert_allclose(after[inst == 1], np.tile(GREY, (16, 1)), atol=1e-6)
    np.testing.assert_allclose(after[inst == 2], np.tile((0, 1, 0), (16, 1)), atol=1e-5)
    assert np.array_equal(after[inst == 0], before["rgb"][inst == 0])
    assert np.array_equal(_render([m])["rgb"], before["rgb"])


def test_edits_when_colour_is_read_at_the_expected_depth(before):
    # surface colouring reads the (edited) colour once per ray at its expected depth: the
    # box top (the first opaque sample, inside the box) or, A removed, the floor slab
    a = _edit("remove", _select("click", (0.6, 0.6)))
    green = torch.tensor([0.0, 1.0, 0.0])
    b = _edit("recolor", _select("pixel", (13, 5)), color=green, strength=0.5)
    plain = _render(surface=True)["rgb"]
    np.testing.assert_allclose(plain, before["rgb"], atol=1e-6)
    after = _render([a, b], surface=True)["rgb"]
    inst = _gt_instances()
    np.testing.assert_allclose(after[inst == 1], np.tile(GREY, (16, 1)), atol=1e-6)
    np.testing.assert_allclose(after[inst == 2], np.tile((0.0, 0.5, 0.5), (16, 1)), atol=1e-5)
    assert np.array_equal(after[inst == 0], plain[inst == 0])

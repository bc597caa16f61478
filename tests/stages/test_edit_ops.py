"""Edits on an analytic field whose renders are worked out by hand.

The scene: a grey floor slab z in [-0.1, 0) over [0, 2]^2, a red box A over [0.4, 0.8]^2 and
a blue box B over [1.2, 1.6]^2, both z in [0, 0.5] and both of class chair. Densities are
1e4 / m (opaque within one 1 cm step), 0 elsewhere.

The camera looks straight down from (1, 1, 20) with f = 200 px on a 20 x 20 image (cx = cy =
9.5): pixel (u, v) sees the floor at x = 1 + (u - 9.5) 0.1, y = 1 - (v - 9.5) 0.1, and the
box tops (z = 0.5, 19.5 m away) at x = 1 + (u - 9.5) 0.0975, y = 1 - (v - 9.5) 0.0975.
So A covers columns u 4..7 (x 0.464 .. 0.756; u = 3 gives 0.366, u = 8 0.854) and rows
v 12..15; B covers u 12..15 and v 4..7. The rays are so steep that none clips a box's side
(u = 3 goes from x 0.366 at the top's height to 0.35 at the floor, never reaching 0.4).

The plan: 0.1 m cells from the origin, 20 x 20, floor (0) everywhere but chair (4) on A's
cells (columns 4..7, rows 12..15: row = 19 - floor(y / 0.1)) and B's (columns 12..15,
rows 4..7).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from stages.common.blueprint import Blueprint, Grid
from stages.common.camera import Intrinsics
from stages.common.components import component_map
from stages.common.errors import BlunfError
from stages.common.radiance.field import FieldFns, field_of
from stages.common.radiance.rays import camera_rays
from stages.common.radiance.render import RenderOptions, render_view
from stages.edit.config import EditConfig
from stages.edit.metrics import PSNR_CAP, EditScore, changed, match_instances, pooled_iou
from stages.edit.ops import (
    FieldEdit,
    edit_colors,
    edit_mesh,
    fill_ground,
    reference_luminance,
)
from stages.edit.render import look_at, orbit_poses, render_rays_edited, render_view_edited
from stages.edit.select import _top, extent_of, select_cells
from stages.edit.spec import Edit, EditSpec, Selector
from stages.nerf.config import NerfConfig
from stages.nerf.scene import build_model
from tests.conftest import tune

torch.set_num_threads(1)

GREY = (0.5, 0.5, 0.5)
RED = (1.0, 0.0, 0.0)
BLUE = (0.0, 0.0, 1.0)
BOX_A = (0.4, 0.8, 0.4, 0.8)  # x0, x1, y0, y1
BOX_B = (1.2, 1.6, 1.2, 1.6)
SIGMA = 1e4
# floor_clear 0: the boxes stand on the floor with their bottom at z = 0, the floor slab is
# z < 0, so an extent from z = 0 up holds all of a box and none of the floor. pad 0: the
# footprints are exactly the boxes' cells.
CFG = EditConfig(floor_clear=0.0, pad=0.0)


def _in_box(x: torch.Tensor, b: tuple[float, float, float, float]) -> torch.Tensor:
    return (
        (x[:, 0] >= b[0])
        & (x[:, 0] < b[1])
        & (x[:, 1] >= b[2])
        & (x[:, 1] < b[3])
        & (x[:, 2] >= 0.0)
        & (x[:, 2] <= 0.5)
    )


def _floor(x: torch.Tensor) -> torch.Tensor:
    inside = (x[:, :2] >= 0).all(dim=1) & (x[:, :2] < 2).all(dim=1)
    return inside & (x[:, 2] >= -0.1) & (x[:, 2] < 0.0)


def density(x: torch.Tensor) -> torch.Tensor:
    solid = _floor(x) | _in_box(x, BOX_A) | _in_box(x, BOX_B)
    return torch.where(solid, SIGMA, 0.0)


def color(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    c = torch.tensor(GREY).expand(len(x), 3).clone()
    c[_in_box(x, BOX_A)] = torch.tensor(RED)
    c[_in_box(x, BOX_B)] = torch.tensor(BLUE)
    return c


INTR = Intrinsics(200.0, 200.0, 9.5, 9.5, 20, 20)
POSE = look_at(np.array([1.0, 1.0, 20.0]), np.array([1.0, 1.0, 0.0]))


def _gt_instances() -> np.ndarray:
    """Instance per pixel (1 = A, 2 = B, 0 = floor), from the geometry worked out above."""
    inst = np.zeros((20, 20), np.int32)
    inst[12:16, 4:8] = 1
    inst[4:8, 12:16] = 2
    return inst


def _plan() -> Blueprint:
    lab = np.zeros((20, 20), np.uint8)
    lab[12:16, 4:8] = 4
    lab[4:8, 12:16] = 4
    return Blueprint(lab, Grid((0.0, 0.0), 0.1, (20, 20)), {0: "floor", 4: "chair"})


def _vertices() -> tuple[np.ndarray, np.ndarray]:
    """Points of the surfaces a fusion would see, with colours: the floor at the centres of
    the floor cells (z = 0), the boxes' tops and sides every 5 cm, and a ceiling at z = 2.5
    over everything (the height measurement must stop below it)."""
    pts, cols = [], []
    g = np.arange(0.025, 2.0, 0.05)
    xx, yy = np.meshgrid(g, g)
    xy = np.stack([xx, yy], -1).reshape(-1, 2)
    floor = _plan().sample(xy) == 0
    pts.append(np.c_[xy[floor], np.zeros(floor.sum())])
    cols.append(np.tile(GREY, (floor.sum(), 1)))
    pts.append(np.c_[xy, np.full(len(xy), 2.5)])
    cols.append(np.tile((1.0, 1.0, 1.0), (len(xy), 1)))
    for (x0, x1, y0, y1), c in ((BOX_A, RED), (BOX_B, BLUE)):
        s = np.arange(0.0, 0.41, 0.05)
        tx, ty = np.meshgrid(x0 + s, y0 + s)
        top = np.c_[tx.ravel(), ty.ravel(), np.full(tx.size, 0.5)]
        zz = np.arange(0.05, 0.5, 0.05)
        side = np.array(
            [(x0, y0 + a, z) for a in s for z in zz]
            + [(x1, y0 + a, z) for a in s for z in zz]
            + [(x0 + a, y0, z) for a in s for z in zz]
            + [(x0 + a, y1, z) for a in s for z in zz]
        )
        pts += [top, side]
        cols += [np.tile(c, (len(top), 1)), np.tile(c, (len(side), 1))]
    return np.concatenate(pts), np.concatenate(cols)


def _select(kind: str, value, width: float = 0.0) -> np.ndarray:
    bp = _plan()
    return select_cells(Selector(kind, value, width, f"test.{kind}"), bp, component_map(bp))


def _edit(op: str, cells: np.ndarray, cfg: EditConfig = CFG, **kw) -> FieldEdit:
    bp = _plan()
    v, c = _vertices()
    ext, _ = extent_of(cells, bp, component_map(bp), v, cfg)
    return FieldEdit(op, ext, ref_lum=reference_luminance(ext, v, c), **kw)


def _render(edits=(), masks=(), surface: bool = False) -> dict:
    o, d, _ = camera_rays(POSE, INTR)
    opts = RenderOptions(near=19.0, far=20.2, step=0.01, surface_color=surface)
    out = render_rays_edited(o, d, field_of(density, color), opts, edits, masks)
    return {
        "rgb": out["rgb"].view(20, 20, 3).numpy(),
        "masks": out["masks"].view(-1, 20, 20).numpy(),
    }


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
    ext, info = extent_of(_select("polygon", poly), bp, component_map(bp), v, EditConfig(pad=0.0))
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
    big, _ = extent_of(_select("click", (0.6, 0.6)), bp, component_map(bp), v, EditConfig(pad=0.1))
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
    from stages.edit.nerf import _fill

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
    fill = _fill(CFG, e, ext, comps, verts, cols, NoField())
    assert fill is not None and torch.equal(fill, torch.tensor([0.0, 1.0, 0.0]))
    grey = _fill(CFG, e, ext, comps, verts, None, _FieldOf(density, color))
    assert grey is not None and torch.allclose(grey, torch.tensor(GREY))
    assert _fill(CFG, replace(e, op="recolor"), ext, comps, verts, cols, NoField()) is None
    floor_comp = [{**comps[0], "class": "floor"}]
    assert _fill(CFG, e, ext, floor_comp, verts, cols, NoField()) is None
    assert _fill(CFG, e, ext, comps, box, cols[-2:], NoField()) is None


class _FieldOf:
    """A model-like object over the analytic field (what `_fill` asks of it: its functions)."""

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
    cfg = EditConfig(pad=0.0)
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


@pytest.mark.parametrize("surface", [False, True])
def test_render_view_edited_without_edits_is_render_view(surface):
    # an untrained model: the same box, near plane, occupancy, step, pruning and colouring
    # mode (composited, or read at the expected depth) as render_view (the shared
    # renderer's), so the same pixels bit for bit
    torch.manual_seed(0)
    cfg = tune(
        NerfConfig(),
        field__hash_log2_size=10,
        field__hash_levels=2,
        field__width=16,
        sampling__samples_across=64,
    )
    model = build_model(cfg, torch.tensor([0.0, 0.0, 0.0]), torch.tensor([2.0, 2.0, 1.0]), [], [])
    model.surface.fill_(surface)
    intr = Intrinsics(8.0, 8.0, 3.5, 2.5, 8, 6)
    pose = look_at(np.array([1.0, -0.5, 0.8]), np.array([1.0, 1.0, 0.2]))
    ref = render_view(model, pose, intr, chunk=17)
    got = render_view_edited(model, pose, intr, (), chunk=17)
    for k in ("rgb", "depth", "acc"):
        assert np.array_equal(got[k], ref[k]), k


@pytest.mark.parametrize("color", [False, True])
def test_render_view_of_some_pixels_is_the_full_render_there(color):
    # the photos-only path renders only the pixels stereo left without depth: the same
    # values as the full view where asked, 0 (no opacity) elsewhere
    torch.manual_seed(0)
    cfg = tune(
        NerfConfig(),
        field__hash_log2_size=10,
        field__hash_levels=2,
        field__width=16,
        sampling__samples_across=64,
    )
    model = build_model(cfg, torch.tensor([0.0, 0.0, 0.0]), torch.tensor([2.0, 2.0, 1.0]), [], [])
    intr = Intrinsics(8.0, 8.0, 3.5, 2.5, 8, 6)
    pose = look_at(np.array([1.0, -0.5, 0.8]), np.array([1.0, 1.0, 0.2]))
    ref = render_view(model, pose, intr, chunk=7, color=color)
    assert ref["acc"].min() > 0  # every pixel has something to compare
    mask = np.zeros((6, 8), bool)
    mask[1:4, 2:7] = True
    mask[5, 0] = True
    got = render_view(model, pose, intr, chunk=7, color=color, pixels=mask)
    for k in ("rgb", "depth", "acc"):
        assert got[k].shape == ref[k].shape, k
        np.testing.assert_allclose(got[k][mask], ref[k][mask], rtol=1e-6, atol=1e-7)
        assert not got[k][~mask].any(), k
    nothing = render_view(model, pose, intr, color=color, pixels=np.zeros((6, 8), bool))
    assert not nothing["depth"].any() and nothing["depth"].shape == (6, 8)
    with pytest.raises(BlunfError, match="pixel mask"):
        render_view(model, pose, intr, pixels=np.ones((8, 6), bool))


def test_orbit_cameras_look_at_the_centre():
    c = (1.0, 2.0, 0.5)
    poses = orbit_poses(c, 2.0, 1.5, 4)
    # frame k sits at angle k * 90 degrees, at height 1.5, 2 m from the centre horizontally
    np.testing.assert_allclose(poses[1][:3, 3], [1.0, 4.0, 1.5], atol=1e-12)
    for p in poses:
        # the centre projects to the principal point: it is on the optical axis (z column)
        d = np.asarray(c) - p[:3, 3]
        np.testing.assert_allclose(p[:3, 2], d / np.linalg.norm(d), atol=1e-12)
        # image x is horizontal, image y points down (its world z is negative)
        assert abs(p[2, 0]) < 1e-12 and p[2, 1] < 0
        np.testing.assert_allclose(p[:3, :3].T @ p[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(p[:3, :3]) == pytest.approx(1.0)


def test_edited_plan_relabels_removed_cells():
    from stages.edit.nerf import _edited_plan

    bp = _plan()
    a = _select("click", (0.6, 0.6))
    floor = _select("pixel", (0, 0))  # the floor component: every cell but the two chairs'
    edits = [
        Edit(0, "remove", Selector("click", (0.6, 0.6))),
        Edit(1, "recolor", Selector("pixel", (0, 0))),
    ]
    # removing A makes its 16 cells floor; a recolour changes no label
    new, n = _edited_plan(
        EditConfig(), bp, EditSpec(Path("e.yaml"), tuple(edits), (0,)), [a, floor]
    )
    assert n == 16 and np.all(new.labels[a] == 0) and np.all(new.labels[~a] == bp.labels[~a])
    new, n = _edited_plan(
        EditConfig(removed_label="unknown"),
        bp,
        EditSpec(Path("e.yaml"), tuple(edits), (0,)),
        [a, floor],
    )
    assert n == 16 and np.all(new.labels[a] == 255)
    # removing the floor itself leaves unknown cells, whatever removed_label says
    rm_floor = [Edit(0, "remove", Selector("pixel", (0, 0)))]
    new, n = _edited_plan(
        EditConfig(), bp, EditSpec(Path("e.yaml"), tuple(rm_floor), (0,)), [floor]
    )
    assert n == 400 - 32 and np.all(new.labels[floor] == 255)


def test_edited_plan_keeps_instances_but_the_removed_ones():
    from stages.edit.nerf import _edited_plan

    bp = _plan()
    inst = np.zeros(bp.labels.shape, np.int32)
    inst[bp.labels != 0] = 7  # both chairs one instance here: only the clicked cells lose it
    bp = replace(bp, instances=inst)
    a = _select("click", (0.6, 0.6))
    edits = (Edit(0, "remove", Selector("click", (0.6, 0.6))),)
    new, _ = _edited_plan(EditConfig(), bp, EditSpec(Path("e.yaml"), edits, (0,)), [a])
    assert new.instances is not None
    assert np.all(new.instances[a] == 0) and np.all(new.instances[~a] == inst[~a])
    assert (inst[~a] == 7).any()

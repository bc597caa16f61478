"""The fast render path (mesh ray cast, a band of field samples round the hit) against the
volume render, on the analytic edit scene of tests/stages/edit_scene.py: a grey floor slab,
a red box A and a blue box B, seen straight down, with the fused surface a real mesh of
those solids. Each render is a few thousand field queries: milliseconds."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch
import trimesh

from stages.common.radiance.config import SamplingConfig
from stages.common.radiance.field import field_of
from stages.edit.render import render_view_edited
from stages.edit.surface import SurfaceOptions, SurfaceRenderer, kept_faces
from tests.stages.edit_scene import (
    BOX_A,
    BOX_B,
    GREY,
    INTR,
    POSE,
    RED,
    _edit,
    _gt_instances,
    _select,
    color,
    density,
)

torch.set_num_threads(1)


@dataclass
class AnalyticField:
    """What the renderers read of a trained field (box, sampling, step, colouring, the field
    as functions), for the analytic scene: step 1 cm, no occupancy grid."""

    surface: bool
    lo: torch.Tensor = torch.tensor([0.0, 0.0, -0.1])
    hi: torch.Tensor = torch.tensor([2.0, 2.0, 0.6])
    sampling: SamplingConfig = SamplingConfig(near=0.05, prune_eps=1e-4)
    step: float = 0.01
    occupancy: None = None

    @property
    def surface_color(self) -> bool:
        return self.surface

    def fns(self, semantics: bool = True):
        return field_of(density, color)

    def color(self, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        return color(x, d)


# the fused surface lies 1 mm inside each solid: the analytic colour flips from the solid's
# to the air's exactly at its boundary, where a ray's hit lands on either side by rounding
INSET = 0.001


def _box(lo, hi) -> trimesh.Trimesh:
    return trimesh.creation.box(bounds=[np.add(lo, INSET), np.subtract(hi, INSET)])


def _mesh() -> tuple[np.ndarray, np.ndarray]:
    """The scene's solids as triangles: the floor slab and the two boxes."""
    parts = [_box([0.0, 0.0, -0.1], [2.0, 2.0, 0.0])]
    for x0, x1, y0, y1 in (BOX_A, BOX_B):
        parts.append(_box([x0, y0, 0.0], [x1, y1, 0.5]))
    m = trimesh.util.concatenate(parts)
    return np.asarray(m.vertices), np.asarray(m.faces)


# the colour read at the mesh's hit (the default), and a band of field samples round it
BANDS = [0.0, 0.05]


def _both(surface: bool, edits=(), masks=(), band: float = 0.0):
    opts = SurfaceOptions(band=band)
    field = AnalyticField(surface)
    v, f = _mesh()
    sr = SurfaceRenderer(field, v, f, opts)
    fast = sr.render_view(POSE, INTR, edits, masks)
    vol = render_view_edited(field, POSE, INTR, edits, masks=masks)
    return fast, vol, sr


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


@pytest.mark.parametrize("band", BANDS)
@pytest.mark.parametrize("surface", [False, True])
def test_fast_render_is_the_volume_render(surface, band) -> None:
    # every ray hits the mesh where the field's surface is: the band holds all of the
    # ray's opacity, nothing is volume rendered, the colours agree (measured: identical
    # up to float rounding, > 60 dB)
    fast, vol, sr = _both(surface, band=band)
    assert not fast["fallback"].any()
    assert _psnr(fast["rgb"], vol["rgb"]) > 50.0
    inst = _gt_instances()
    assert np.allclose(fast["rgb"][inst == 1], RED, atol=1e-3)
    assert np.allclose(fast["rgb"][inst == 0], GREY, atol=1e-3)
    assert np.allclose(fast["depth"], vol["depth"], atol=0.01)


@pytest.mark.parametrize("band", BANDS)
@pytest.mark.parametrize("surface", [False, True])
def test_removal_shows_what_is_behind(surface, band) -> None:
    remove_a = _edit("remove", _select("click", (0.6, 0.6)))
    fast, vol, sr = _both(surface, [remove_a], band=band)
    inst = _gt_instances()
    # A's pixels show the floor under it, B and the floor are untouched: as the volume render
    assert np.allclose(fast["rgb"][inst == 1], GREY, atol=1e-3)
    assert np.allclose(fast["rgb"][inst == 2], (0.0, 0.0, 1.0), atol=1e-3)
    assert _psnr(fast["rgb"], vol["rgb"]) > 50.0
    # ... through the mesh without A's faces (the rays went on to the floor's surface), not by
    # falling back on the volume render
    assert not fast["fallback"].any()
    v, f = _mesh()
    kept = kept_faces(v, f, [remove_a])
    top = v[kept].mean(axis=1)  # centroids of the faces kept
    on_a = (top[:, 0] > BOX_A[0]) & (top[:, 0] < BOX_A[1]) & (top[:, 1] > BOX_A[2])
    assert len(kept) < len(f) and not (on_a & (top[:, 1] < BOX_A[3]) & (top[:, 2] > 0.25)).any()
    # the fast depth is the floor's under A (19.5 m above it was A's top)
    assert np.allclose(fast["depth"][inst == 1], 20.0, atol=0.01)


@pytest.mark.parametrize("band", BANDS)
@pytest.mark.parametrize("surface", [False, True])
def test_recolour_changes_only_the_objects_pixels(surface, band) -> None:
    green = torch.tensor([0.0, 1.0, 0.0])
    before, _, _ = _both(surface, band=band)
    edit = _edit("recolor", _select("click", (1.4, 1.4)), color=green, strength=1.0)
    fast, vol, _ = _both(surface, [edit], band=band)
    changed = np.abs(fast["rgb"] - before["rgb"]).max(axis=2) > 0.05
    assert np.array_equal(changed, _gt_instances() == 2)  # B's pixels, and only those
    assert _psnr(fast["rgb"], vol["rgb"]) > 50.0


@pytest.mark.parametrize("band", BANDS)
def test_masks_and_a_misplaced_surface(band) -> None:
    # a mask is the unedited surface inside the extent (the volume render: the weight there)
    ext = _edit("mask", _select("click", (0.6, 0.6))).extent
    fast, vol, _ = _both(False, masks=[ext], band=band)
    assert np.array_equal(fast["masks"][0] >= 0.5, vol["masks"][0] >= 0.5)
    assert np.array_equal(fast["masks"][0] >= 0.5, _gt_instances() == 1)
    if band == 0:
        return
    # with a band: where the mesh's surface is not where the field's is (A's box fused 0.2 m
    # too high: the band round its top holds no density) the rays are volume rendered, and
    # show A as the volume render does
    x0, x1, y0, y1 = BOX_A
    parts = [
        _box([0.0, 0.0, -0.1], [2.0, 2.0, 0.0]),
        _box([x0, y0, 0.2], [x1, y1, 0.7]),  # A, too high
        _box([BOX_B[0], BOX_B[2], 0.0], [BOX_B[1], BOX_B[3], 0.5]),
    ]
    m = trimesh.util.concatenate(parts)
    field = AnalyticField(False)
    sr = SurfaceRenderer(field, np.asarray(m.vertices), np.asarray(m.faces), SurfaceOptions(band))
    out = sr.render_view(POSE, INTR)
    vol = render_view_edited(field, POSE, INTR)
    assert np.array_equal(out["fallback"], _gt_instances() == 1)
    assert np.allclose(out["rgb"][_gt_instances() == 1], RED, atol=1e-3)
    assert _psnr(out["rgb"], vol["rgb"]) > 50.0

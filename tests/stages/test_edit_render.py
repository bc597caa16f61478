"""The edit stage's view renderer against the shared one (render_view) on an untrained
model, and the orbit cameras it renders edited scenes from.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.common.camera import Intrinsics
from stages.common.errors import BlunfError
from stages.common.radiance.render import render_view
from stages.common.radiance.scene import build_model
from stages.edit.render import look_at, orbit_poses, render_view_edited
from stages.nerf.config import NerfConfig
from tests.conftest import tune

torch.set_num_threads(1)


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


def test_views_side_by_side_are_the_views_one_by_one():
    # two torch threads: the views render one per thread side by side, in order, the same
    # pixels as one by one; the caller's thread count is back afterwards
    from stages.common.threads import side_by_side

    torch.manual_seed(0)
    cfg = tune(NerfConfig(), field__hash_log2_size=10, field__hash_levels=2, field__width=16)
    model = build_model(cfg, torch.tensor([0.0, 0.0, 0.0]), torch.tensor([2.0, 2.0, 1.0]), [], [])
    intr = Intrinsics(8.0, 8.0, 3.5, 2.5, 8, 6)
    poses = [look_at(np.array([1.0, -0.5, z]), np.array([1.0, 1.0, 0.2])) for z in (0.5, 0.8, 1.1)]
    ref = [render_view(model, p, intr, chunk=17) for p in poses]
    threads = []

    def draw(p):
        threads.append(torch.get_num_threads())
        return render_view(model, p, intr, chunk=17)

    torch.set_num_threads(2)
    try:
        got = list(side_by_side(draw, poses))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
    assert threads == [1, 1, 1]  # each view on one thread
    for a, b in zip(ref, got, strict=True):
        for k in ("rgb", "depth", "acc"):
            assert np.array_equal(a[k], b[k]), k
    # one torch thread: one by one, on the caller's thread
    assert [v["acc"].sum() for v in side_by_side(draw, poses)] == [v["acc"].sum() for v in ref]
    assert threads[3:] == [1, 1, 1]

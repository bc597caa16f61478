"""NeRF training (stages/nerf: train.py, losses.py, views.py, scene.py) on small rooms and
tiny fields: seeded runs, the silhouette terms, the losses at extreme densities, the
learning-rate schedule."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor

from stages.common.capture import read_layout
from stages.common.radiance.field import EXP_CLAMP, RadianceField, load_field, save_field
from stages.common.radiance.losses import depth_pixels, edge_loss, geometry_loss, surface_loss
from stages.common.radiance.occupancy import OccupancyGrid
from stages.common.radiance.render import FieldRender, render_field
from stages.common.radiance.scene import build_model, scene_box
from stages.common.radiance.train import _batch, train
from stages.common.radiance.views import (
    Rays,
    depth_points,
    gather_rays,
    load_views,
    nearer_neighbour,
    seed_points,
    split,
)
from stages.common.threads import torch_threads
from stages.nerf import NerfConfig
from stages.synth import make_room
from tests.conftest import tune
from tests.stages.test_nerf import FAST

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def room8(tmp_path_factory) -> Path:
    """8 views at 96 x 72: view 4 is held out (holdout_every = 8)."""
    return make_room(tmp_path_factory.mktemp("room8") / "capture", views=8, seed=3, size=(96, 72))


# ---- seeds ---------------------------------------------------------------------------------


def _training_inputs(room: Path, cfg: NerfConfig):
    """What train() takes for `room`'s training views: (views, depth points, box lo, hi, rays)."""
    cap = read_layout(room)
    views = load_views(cap, cfg.semantics)
    tr, _ = split(len(cap.frames), cfg.train.holdout_every)
    pts = depth_points(cap, views, tr, cfg.box.depth_stride)
    lo, hi = scene_box(cap.poses()[:, :3, 3], pts, cfg)
    return views, pts, lo, hi, gather_rays(cap, views, tr)


@pytest.mark.parametrize("dense", [True, False])
def test_same_seed_same_weights(room8, dense):
    # the whole training (init, batches, jitter, occupancy updates) is seeded: two runs give
    # bit-identical weights and occupancy grids; another seed gives other weights. The sparse
    # setting (dense=False) also exercises the occupancy updates (the dense grid is frozen).
    cfg = tune(
        FAST,
        train__max_steps=6,
        train__batch_rays=64,
        losses__surface_rays=128,
        losses__geo_rays=128,
        occupancy__every=3,
        occupancy__cells=4096,
        occupancy__res=32,
    )
    views, pts, lo, hi, rays = _training_inputs(room8, cfg)

    def run(seed: int) -> dict:
        c = replace(cfg, seed=seed)
        torch.manual_seed(seed)
        model = build_model(c, lo, hi, views.class_ids, [pts], dense=dense)
        train(c, model, rays, None, dense=dense)
        return model.state_dict()

    a, b, other = run(0), run(0), run(1)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert not torch.equal(other["encoding.table"], a["encoding.table"])
    assert not torch.equal(other["trunk.0.weight"], a["trunk.0.weight"])


def test_weights_do_not_depend_on_the_callers_thread_count(room8):
    # The runner gives a stage the free cores' count; training computes with train.threads
    # (1) whatever that is, so a loaded and an idle machine train the same weights. With
    # threads=0 (the caller's count) 2 threads and 1 differ: the batch is large enough for
    # torch to split the weight gradients' sums and the element-wise kernels between threads.
    cfg = tune(FAST, train__max_steps=2, train__batch_rays=2048, losses__surface_rays=2048,
               losses__geo_rays=2048)  # fmt: skip
    views, pts, lo, hi, rays = _training_inputs(room8, cfg)

    def run(caller: int, threads: int) -> dict:
        c = tune(cfg, train__threads=threads)
        torch.manual_seed(0)
        model = build_model(c, lo, hi, views.class_ids, [pts], dense=True)
        with torch_threads(caller):
            train(c, model, rays, None, dense=True)
            assert torch.get_num_threads() == caller  # put back after training
        return model.state_dict()

    one, two = run(1, 1), run(2, 1)
    for key in one:
        assert torch.equal(one[key], two[key]), key
    free1, free2 = run(1, 0), run(2, 0)
    assert any(not torch.equal(free1[k], free2[k]) for k in free1), "2 threads split nothing"


# ---- silhouettes ---------------------------------------------------------------------------


def test_nearer_neighbour_marks_the_pixels_beside_a_silhouette():
    # a box at 1 m over a wall at 3 m: the wall pixels within 2 px of the box get 1 m, nothing
    # else does (not the box, not the wall further out, not a missing reading)
    d = np.full((20, 30), 3.0, np.float32)
    d[5:10, 8:14] = 1.0
    d[15, 20] = 0.0  # a missing reading: never nearer, and gets nothing itself
    d[15, 22] = 0.0
    near = nearer_neighbour(d, 2, 0.1)
    ring = np.zeros(d.shape, bool)
    ring[3:12, 6:16] = True
    ring[5:10, 8:14] = False
    assert np.all(near[ring] == 1.0) and np.all(near[~ring] == 0.0)
    # a receding floor (10 % deeper per row): 20 % over 2 px, only 0.02-0.1 m at this range,
    # under the gap: not a silhouette; with a smaller gap it is one, at the nearer row's depth
    floor = np.repeat((0.1 * 1.1 ** np.arange(12, dtype=np.float32))[:, None], 5, axis=1)
    assert not nearer_neighbour(floor, 2, 0.1).any()
    got = nearer_neighbour(floor, 2, 0.001)
    np.testing.assert_allclose(got[2:], floor[:-2], rtol=1e-6)
    assert not nearer_neighbour(np.zeros((4, 4), np.float32), 2, 0.1).any()


def test_gather_rays_edge_distances(room8):
    # with a radius, t_edge is the nearer neighbour's z-depth along the pixel's own ray
    cap = read_layout(room8)
    views = load_views(cap, False)
    plain = gather_rays(cap, views, [0, 1])
    assert plain.t_edge is None and len(plain.edges) == 0
    rays = gather_rays(cap, views, [0, 1], 2, 0.1)
    assert rays.t_edge is not None and 0 < len(rays.edges) < 0.5 * len(rays.rgb)
    h, w = 72, 96
    z = views.depth[0].numpy().reshape(h, w)
    near = nearer_neighbour(z, 2, 0.1).reshape(-1)
    n0 = h * w
    te = rays.t_edge[:n0].numpy()
    zs = (plain.t_depth[:n0] / views.depth[0].clamp(min=1e-9)).numpy()  # ray distance per z
    np.testing.assert_allclose(te, near * zs, rtol=1e-5)
    assert torch.all(rays.t_edge[rays.edges] < rays.t_depth[rays.edges] - 0.1)


def _weight_in_front(model: RadianceField, rays: Rays, idx: Tensor, gap: float) -> float:
    """Mean rendered weight of rays idx in front of (their reading - gap / 2)."""
    with torch.no_grad():
        out = render_field(model, rays.origins[idx], rays.dirs[idx], model.fns(semantics=False),
                           FieldRender(return_samples=True))  # fmt: skip
    front = out["t"] < rays.t_depth[idx][out["ray"]] - 0.5 * gap
    w = torch.zeros(len(idx)).index_add(0, out["ray"][front], out["weights"][front])
    return float(w.mean())


def test_edges_clear_the_halo_beside_silhouettes(room8):
    # Beside an object, rays pass it and hit what is behind. Trained without the silhouette
    # terms, the field's blur puts weight on those rays at the object's depth; with them (a
    # free point each where the ray passes the nearer reading, and half the marched rays
    # drawn there) the rendered weight in front of those readings drops by a third or more
    # (0.69 -> 0.44 when written).
    cap = read_layout(room8)
    views = load_views(cap, False)
    tr, _ = split(len(cap.frames), FAST.train.holdout_every)
    pts = depth_points(cap, views, tr, FAST.box.depth_stride)
    lo, hi = scene_box(cap.poses()[:, :3, 3], pts, FAST)
    rays = gather_rays(cap, views, tr, 2, 0.1)
    probe = rays.edges[torch.randperm(len(rays.edges), generator=torch.Generator().manual_seed(1))]
    probe = probe[:2000]

    def halo(edge_rays: int, edge_batch: float) -> float:
        cfg = tune(
            FAST,
            train__max_steps=120,
            semantics=False,
            losses__edge_rays=edge_rays,
            train__edge_batch=edge_batch,
        )
        torch.manual_seed(0)
        model = build_model(cfg, lo, hi, [], seed_points(cap, views, tr), dense=True)
        train(cfg, model, rays, None, dense=True)
        return _weight_in_front(model, rays, probe, cfg.losses.edge_gap)

    without, with_edges = halo(0, 0.0), halo(512, 0.5)
    assert with_edges < 0.75 * without, (without, with_edges)


def test_batch_draws_half_its_rays_beside_silhouettes():
    z = torch.zeros(1000, 3)
    t_edge = torch.zeros(1000)
    t_edge[100:110] = 1.0
    rays = Rays(z, z, z, torch.ones(1000), None, t_edge)
    gen = torch.Generator().manual_seed(0)
    idx = _batch(tune(FAST, train__batch_rays=200, train__edge_batch=0.5).train, rays, gen)
    assert len(idx) == 200 and bool(((idx[100:] >= 100) & (idx[100:] < 110)).all())
    assert int(((idx[:100] >= 100) & (idx[:100] < 110)).sum()) < 10  # the rest: any pixel
    plain = Rays(z, z, z, torch.ones(1000), None)  # no silhouettes known: all from anywhere
    assert len(_batch(tune(FAST, train__batch_rays=200).train, plain, gen)) == 200


def test_edge_loss_draws_at_the_nearer_depth():
    # each free point lies within a step of t_edge and at least edge_gap / 2 before the reading
    model, rays = _tiny_model(0.0, True)
    t_edge = torch.zeros(64)
    t_edge[1::2] = 0.3
    t_edge[3] = 0.49  # too close to its reading (0.5): drawn at 0.5 - gap / 2 at the latest
    rays = Rays(rays.origins, rays.dirs, rays.rgb, rays.t_depth, None, t_edge)
    seen: list[Tensor] = []
    real = model.sigma

    def sigma(x: Tensor) -> Tensor:
        seen.append(x.detach().clone())
        return real(x)

    model.sigma = sigma  # type: ignore[method-assign]
    cfg = tune(FAST, losses__edge_rays=1000, losses__edge_gap=0.1)
    loss = edge_loss(cfg.losses, model, rays, torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and loss.requires_grad
    t = seen[0].norm(dim=1)  # rays start at the origin with unit directions
    assert len(t) == 32 and len(seen) == 1  # as many draws as edge rays (< edge_rays)
    at_edge = (t - 0.3).abs() <= model.step + 1e-6
    capped = (t - 0.45).abs() < 1e-6  # ray 3's: its t_edge is within the gap of its reading
    assert torch.all(at_edge | capped) and at_edge.sum() > 16


# ---- losses at extreme densities -----------------------------------------------------------


def _tiny_cfg(color_grid: bool) -> NerfConfig:
    """A small hash field: 2 levels of 2^10 entries, 4 to 8 cells across, 16 wide."""
    return tune(
        FAST,
        field__hash_levels=2,
        field__hash_log2_size=10,
        field__hash_base_res=4,
        field__hash_max_res=8,
        field__width=16,
        field__geo_features=3,
        field__color_grid=color_grid,
        losses__geo_rays=64,
        losses__surface_rays=64,
    )


def _tiny_model(bias: float, color_grid: bool) -> tuple[RadianceField, Rays]:
    """The `_tiny_cfg` field in [-1, 1]^3 whose density is exp(min(raw, 15)) with raw ~ bias,
    and 64 rays from the origin with depth readings at 0.5 m (every 4th ray has none)."""
    cfg = _tiny_cfg(color_grid)
    lo, hi = -torch.ones(3), torch.ones(3)
    torch.manual_seed(0)
    model = RadianceField(cfg.field, cfg.sampling, lo, hi, [], OccupancyGrid.for_box(lo, hi, 4))
    with torch.no_grad():
        model.trunk[-1].bias[0] = bias
    dirs = torch.nn.functional.normalize(torch.randn(64, 3), dim=1)
    t = torch.full((64,), 0.5)
    t[::4] = 0.0
    rays = Rays(torch.zeros(64, 3), dirs, torch.rand(64, 3), t, None)
    return model, rays


def test_depth_losses_draw_only_pixels_with_depth():
    # SfM tracks: few pixels have a reading; every draw of the depth losses is one of them
    # (drawn from all pixels, most draws would be thrown away), at most as many as there are
    z = torch.zeros(1000, 3)
    few = torch.zeros(1000)
    few[[5, 500, 999]] = torch.tensor([1.0, 2.0, 3.0])
    idx, td = depth_pixels(Rays(z, z, z, few, None), 256, torch.Generator().manual_seed(0))
    assert len(idx) == 3 and set(idx.tolist()) <= {5, 500, 999}
    assert torch.equal(td, few[idx])
    more = few.clone()
    more[10:410] = 4.0
    idx, td = depth_pixels(Rays(z, z, z, more, None), 256, torch.Generator().manual_seed(0))
    assert len(idx) == 256 and (td > 0).all() and torch.equal(td, more[idx])
    assert len(set(idx.tolist())) > 150  # spread over the pool, not one pixel repeated
    empty = Rays(z, z, z, torch.zeros(1000), None)
    assert len(depth_pixels(empty, 256, torch.Generator())[0]) == 0


@pytest.mark.parametrize(("color_grid", "dense"), [(True, True), (False, True), (True, False)])
@pytest.mark.parametrize("bias", [-30.0, 30.0])
def test_losses_stay_finite_at_extreme_densities(bias, color_grid, dense):
    # dense = False: the free-space point is drawn anywhere in front of the reading
    model, rays = _tiny_model(bias, color_grid)
    gen = torch.Generator().manual_seed(0)
    lc = _tiny_cfg(color_grid).losses
    geo = geometry_loss(lc, model, rays, gen, dense)
    surf = surface_loss(lc, model, rays, gen)
    (geo + surf).backward()
    assert torch.isfinite(geo) and torch.isfinite(surf)
    for name, p in model.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    s = model.step  # diagonal 2 sqrt(3) / 256 samples across
    if bias > 0:
        # raw ~ 30 everywhere (the trunk's other terms are ~1): the density is clamped at
        # e^15, so one step's optical depth is e^15 s at the free-space points (their loss
        # is that optical depth) and the opaque points' -log(1 - e^(-e^15 s)) is 0
        torch.testing.assert_close(geo, torch.tensor(math.exp(EXP_CLAMP) * s), rtol=1e-4, atol=0)
        # and the gradient lowers the density (the truncated exp passes it on when clamped)
        assert model.trunk[-1].bias.grad[0] > 0
    else:
        # density ~ e^-30: nothing in front (loss ~ 0); behind the reading the term is
        # -log(1 - e^-sd) ~ -log(sd) = -(raw + log s) ~ 30 + 4.3: large but finite, and its
        # gradient on the raw density is -1 (a region the field emptied can come back)
        assert 25.0 < float(geo.detach()) < 45.0
        assert model.trunk[-1].bias.grad[0] < -0.5
    # the colour loss is an MSE of colours in [0, 1] against targets in [0, 1]
    assert 0.0 <= float(surf.detach()) <= 1.0
    color_params = model.color_encoding if color_grid else model.trunk
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in color_params.parameters())


@pytest.mark.parametrize("bias", [-30.0, 30.0])
def test_training_steps_stay_finite_at_extreme_densities(bias):
    # a few full steps (marching + both losses + Adam) from a field that is empty or solid
    model, rays = _tiny_model(bias, True)
    cfg = tune(_tiny_cfg(True), train__max_steps=3, train__batch_rays=32, losses__trunc_steps=4)
    stats = train(cfg, model, rays, None, dense=True)
    assert stats["steps"] == 3 and math.isfinite(stats["final_loss"])
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), name


@pytest.mark.parametrize(
    ("surface_color", "dense", "expect"),
    [(True, True, True), (True, False, False), (False, True, False)],
)
def test_surface_color_is_set_by_dense_training(tmp_path, surface_color, dense, expect):
    # rendering colours rays at their expected depth only for a field trained on dense depth
    # with surface_color on; the flag is saved with the model
    model, rays = _tiny_model(-3.0, True)
    cfg = tune(
        _tiny_cfg(True),
        train__max_steps=1,
        train__batch_rays=16,
        train__surface_color=surface_color,
    )
    train(cfg, model, rays, None, dense=dense)
    assert model.surface_color is expect
    save_field(model, tmp_path / "model.pt")
    assert load_field(tmp_path / "model.pt").surface_color is expect


# ---- the occupancy grid ------------------------------------------------------------------


def test_dense_grid_is_the_seeded_cells():
    # box [-1, 1]^3 at occ_res 10: cells of 0.2 m. The point (0.1, 0.1, 0.1) is in cell
    # floor(1.1 / 0.2) = 5 along each axis; dilated by 1 that is cells 4-6: 27 cells, and
    # nothing else. Training on dense depth leaves the grid as it is (occ_seeded_only).
    model, rays = _tiny_model(-3.0, True)
    cfg = tune(
        _tiny_cfg(True),
        occupancy__res=10,
        occupancy__dilate=1,
        occupancy__every=1,
        train__max_steps=2,
        train__batch_rays=16,
    )
    lo, hi = -torch.ones(3), torch.ones(3)
    pts = np.array([[0.1, 0.1, 0.1]])
    model = build_model(cfg, lo, hi, [], [pts], dense=True)
    occ = model.occupancy.binary
    assert occ.shape == (10, 10, 10) and int(occ.sum()) == 27 and bool(occ[4:7, 4:7, 4:7].all())
    before = occ.clone()
    train(cfg, model, rays, None, dense=True)
    assert torch.equal(model.occupancy.binary, before)
    # without any depth point every cell starts occupied
    assert bool(build_model(cfg, lo, hi, [], [], dense=True).occupancy.binary.all())


# ---- learning-rate schedule ----------------------------------------------------------------


def test_learning_rate_decays_over_the_steps(monkeypatch):
    # lr 1e-2 decayed to lr_final = 0.1 of it over max_steps = 4: step k (from 0) runs at
    # 1e-2 * 0.1^(k / 4) = 1e-2, 5.623e-3, 3.162e-3, 1.778e-3, for every parameter group
    # (the MLPs and the hash tables)
    used: list[list[float]] = []

    class Recording(torch.optim.Adam):
        def step(self, closure=None):  # type: ignore[override]
            used.append([g["lr"] for g in self.param_groups])
            return super().step(closure)

    monkeypatch.setattr(torch.optim, "Adam", Recording)
    model, rays = _tiny_model(-3.0, True)
    cfg = tune(
        _tiny_cfg(True),
        train__max_steps=4,
        train__batch_rays=16,
        train__lr=1e-2,
        train__lr_final=0.1,
    )
    train(cfg, model, rays, None)
    expect = [1e-2 * 0.1 ** (k / 4) for k in range(4)]
    assert len(used) == 4 and all(len(g) == 2 for g in used)
    for lrs, e in zip(used, expect, strict=True):
        assert lrs == pytest.approx([e, e], rel=1e-9)

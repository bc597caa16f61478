"""The volume renderer on analytic fields whose renders are worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import torch

from stages.common.camera import Intrinsics
from stages.common.radiance.field import field_of
from stages.common.radiance.occupancy import OccupancyGrid
from stages.common.radiance.rays import camera_rays, ray_box
from stages.common.radiance.render import RenderOptions, render_rays

torch.set_num_threads(1)

RED = torch.tensor([1.0, 0.0, 0.0])


def _rays(n: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """n rays from x = 0 along +x (unit directions), at different y."""
    o = torch.zeros(n, 3)
    o[:, 1] = torch.arange(n, dtype=torch.float32) * 0.1
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3).clone()
    return o, d


def _slab(sigma: float, x0: float, x1: float):
    """Constant density sigma where x0 <= x < x1, zero elsewhere; red everywhere."""

    def density(x: torch.Tensor) -> torch.Tensor:
        inside = (x[:, 0] >= x0) & (x[:, 0] < x1)
        return torch.where(inside, sigma, 0.0)

    return density, lambda x, d: RED.expand(len(x), 3)


def test_constant_slab_transmittance_and_opacity():
    # sigma = 2 / m over [1, 1.5): optical depth 2 * 0.5 = 1, so acc = 1 - e^-1 = 0.63212.
    # The slab boundaries fall on step boundaries (step 0.01), so the sum is exact.
    density, color = _slab(2.0, 1.0, 1.5)
    o, d = _rays()
    out = render_rays(
        o, d, field_of(density, color), RenderOptions(near=0.0, far=3.0, step=0.01, prune_eps=0.0)
    )
    expect = 1.0 - math.exp(-1.0)
    torch.testing.assert_close(out["acc"], torch.full((4,), expect), atol=1e-4, rtol=0)
    torch.testing.assert_close(out["rgb"][:, 0], torch.full((4,), expect), atol=1e-4, rtol=0)
    assert torch.all(out["rgb"][:, 1:] == 0)
    # expected depth of a constant slab [a, b) with optical depth tau: the density of weight
    # along t is sigma e^{-sigma (t - a)}, normalised: mean = a + 1/sigma - L e^{-tau}/(1-e^{-tau})
    # = 1 + 0.5 - 0.5 * e^-1 / (1 - e^-1) = 1.20902 (midpoint samples: within ~1e-4)
    mean = 1.0 + 0.5 - 0.5 * math.exp(-1.0) / (1.0 - math.exp(-1.0))
    torch.testing.assert_close(out["depth"], torch.full((4,), mean), atol=5e-4, rtol=0)


def test_step_density_puts_depth_at_the_step():
    # A huge density from x = 2 on: all the weight is in the first sample past the step,
    # at its middle (2.005), so the expected depth is 2.005 and acc is 1.
    density, color = _slab(1e5, 2.0, 10.0)
    o, d = _rays()
    out = render_rays(o, d, field_of(density, color), RenderOptions(near=0.0, far=5.0, step=0.01))
    torch.testing.assert_close(out["depth"], torch.full((4,), 2.005), atol=1e-4, rtol=0)
    torch.testing.assert_close(out["acc"], torch.ones(4), atol=1e-6, rtol=0)


def test_early_stop_changes_nothing_visible():
    # Pruning samples after transmittance 1e-4 changes the render by at most ~1e-4.
    density, color = _slab(3.0, 1.0, 6.0)
    o, d = _rays()
    full = render_rays(
        o, d, field_of(density, color), RenderOptions(near=0.0, far=8.0, step=0.01, prune_eps=0.0)
    )
    fast = render_rays(
        o, d, field_of(density, color), RenderOptions(near=0.0, far=8.0, step=0.01, prune_eps=1e-4)
    )
    with torch.no_grad():  # the block-wise marcher used for rendering views
        blocks = render_rays(
            o,
            d,
            field_of(density, color),
            RenderOptions(near=0.0, far=8.0, step=0.01, prune_eps=1e-4),
        )
    for k in ("rgb", "acc", "depth"):
        torch.testing.assert_close(fast[k], full[k], atol=2e-3, rtol=0)
        torch.testing.assert_close(blocks[k], full[k], atol=2e-3, rtol=0)


def test_empty_field_gives_background():
    o, d = _rays()
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = render_rays(
        o,
        d,
        field_of(lambda x: torch.zeros(len(x)), lambda x, v: RED.expand(len(x), 3)),
        RenderOptions(near=0.1, far=2.0, step=0.01, background=bg),
    )
    torch.testing.assert_close(out["rgb"], bg.expand(4, 3))
    assert torch.all(out["acc"] == 0)
    assert torch.all(torch.isfinite(out["depth"]))
    # no weight anywhere: depth reports the far end
    torch.testing.assert_close(out["depth"], torch.full((4,), 2.0))


class _Empty:
    """An occupancy grid with every cell empty."""

    def query(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(len(x), dtype=torch.bool)

    def query_coarse(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(len(x), dtype=torch.bool)

    def coarse_size(self) -> float:
        return 0.04


def _finite(out: dict) -> None:
    for k in ("rgb", "depth", "acc"):
        assert torch.all(torch.isfinite(out[k])), k
    assert torch.all((out["acc"] >= 0) & (out["acc"] <= 1 + 1e-6))


def test_degenerate_inputs_stay_finite():
    o, d = _rays()
    density, color = _slab(2.0, 1.0, 1.5)
    # every sample skipped by the occupancy grid
    out = render_rays(
        o,
        d,
        field_of(density, color),
        RenderOptions(near=0.0, far=3.0, step=0.01, occupancy=_Empty()),
    )
    _finite(out)
    assert torch.all(out["acc"] == 0)
    with torch.no_grad():
        out = render_rays(
            o,
            d,
            field_of(density, color),
            RenderOptions(near=0.0, far=3.0, step=0.01, occupancy=_Empty()),
        )
    _finite(out)
    # huge density (clamped exponentials), zero density, near == far, far < near
    for dens in (lambda x: torch.full((len(x),), 3e38), lambda x: torch.zeros(len(x))):
        _finite(
            render_rays(o, d, field_of(dens, color), RenderOptions(near=0.0, far=3.0, step=0.01))
        )
        with torch.no_grad():
            _finite(
                render_rays(
                    o, d, field_of(dens, color), RenderOptions(near=0.0, far=3.0, step=0.01)
                )
            )
    _finite(
        render_rays(o, d, field_of(density, color), RenderOptions(near=1.0, far=1.0, step=0.01))
    )
    out = render_rays(o, d, field_of(density, color), RenderOptions(near=2.0, far=1.0, step=0.01))
    _finite(out)
    assert torch.all(out["acc"] == 0)
    # rays parallel to the slab faces (along y inside and outside the slab)
    o2 = torch.tensor([[1.2, 0.0, 0.0], [0.5, 0.0, 0.0]])
    d2 = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    out = render_rays(o2, d2, field_of(density, color), RenderOptions(near=0.0, far=2.0, step=0.01))
    _finite(out)
    # inside the slab: optical depth 2 * 2 = 4 -> acc = 1 - e^-4; outside: nothing
    torch.testing.assert_close(
        out["acc"], torch.tensor([1 - math.exp(-4.0), 0.0]), atol=1e-4, rtol=0
    )
    # gradients stay finite through a huge density
    raw = torch.tensor(50.0, requires_grad=True)
    out = render_rays(
        o,
        d,
        field_of(lambda x: torch.exp(raw.clamp(max=15)).expand(len(x)), color),
        RenderOptions(near=0.0, far=3.0, step=0.01),
    )
    (out["rgb"].sum() + out["depth"].sum()).backward()
    assert raw.grad is not None and torch.isfinite(raw.grad)


def test_occupancy_skipping_matches_full_marching():
    # a grid occupied only around the slab renders what the full march renders
    density, color = _slab(2.0, 1.0, 1.5)
    occ = OccupancyGrid(
        torch.tensor([-0.5, -0.5, -0.5]), torch.tensor([3.5, 0.5, 0.5]), (40, 10, 10)
    )
    pts = torch.stack(
        torch.meshgrid(
            torch.linspace(1.0, 1.49, 50),
            torch.linspace(-0.45, 0.45, 10),
            torch.linspace(-0.45, 0.45, 10),
            indexing="ij",
        ),
        -1,
    ).reshape(-1, 3)
    occ.seed(pts, 1.0, 0)
    o, d = _rays()
    ref = render_rays(
        o, d, field_of(density, color), RenderOptions(near=0.0, far=3.0, step=0.01, prune_eps=0.0)
    )
    got = render_rays(
        o, d, field_of(density, color), RenderOptions(near=0.0, far=3.0, step=0.01, occupancy=occ)
    )
    for k in ("rgb", "acc", "depth"):
        torch.testing.assert_close(got[k], ref[k], atol=1e-4, rtol=0)


def test_seeding_several_sets_and_refreshing_the_occupancy():
    lo, hi = torch.zeros(3), torch.ones(3)
    a, b = torch.tensor([[0.05, 0.05, 0.05]]), torch.tensor([[0.95, 0.95, 0.95]])
    one, apart = OccupancyGrid(lo, hi, (10, 10, 10)), OccupancyGrid(lo, hi, (10, 10, 10))
    one.seed([a, b], 5.0, 1)  # the sets' cells dilated once: as if seeded one at a time
    apart.seed(a, 5.0, 1)
    apart.seed(b, 5.0, 1)
    assert torch.equal(one.binary, apart.binary) and int(one.binary.sum()) == 2 * 8
    assert torch.equal(one.keep, one.binary) and torch.equal(one.ema, apart.ema)
    # cells the updates added: the refresh drops those where the field is now empty and
    # keeps those where it is dense; seeded cells stay, free cells stay free
    one.binary[5, 5, 5] = one.binary[5, 5, 6] = True

    def density(x: torch.Tensor) -> torch.Tensor:  # dense only in cell (5, 5, 6)
        return torch.where((x[:, 2] >= 0.6) & (x[:, 2] < 0.7), 10.0, 0.0)

    assert one.refresh(density, 1.0) == 2 * 8 + 1
    assert one.binary[5, 5, 6] and not one.binary[5, 5, 5] and one.binary[0, 0, 0]
    assert not one.binary[3, 3, 3] and bool(one.coarse.any())


def test_edit_hook_reveals_what_is_behind():
    # A wall at x in [2, 2.2) and a far wall at x >= 4. Zeroing the density inside the box
    # x in [1.5, 3] (an edit wrapping density_fn) removes the near wall: the depth goes from
    # 2.005 (first sample past 2) to 4.005.
    def scene(x: torch.Tensor) -> torch.Tensor:
        near_wall = (x[:, 0] >= 2.0) & (x[:, 0] < 2.2)
        return torch.where(near_wall | (x[:, 0] >= 4.0), 1e4, 0.0)

    def removed(x: torch.Tensor) -> torch.Tensor:
        inside = (x[:, 0] >= 1.5) & (x[:, 0] <= 3.0)
        return torch.where(inside, 0.0, scene(x))

    o, d = _rays()
    color = lambda x, v: RED.expand(len(x), 3)  # noqa: E731
    before = render_rays(o, d, field_of(scene, color), RenderOptions(near=0.0, far=6.0, step=0.01))
    after = render_rays(o, d, field_of(removed, color), RenderOptions(near=0.0, far=6.0, step=0.01))
    torch.testing.assert_close(before["depth"], torch.full((4,), 2.005), atol=1e-4, rtol=0)
    torch.testing.assert_close(after["depth"], torch.full((4,), 4.005), atol=1e-4, rtol=0)


def test_ray_box_and_camera_rays():
    lo, hi = torch.zeros(3), torch.ones(3)
    o = torch.tensor([[-1.0, 0.5, 0.5], [0.5, 0.5, 0.5], [-1.0, 2.0, 0.5]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t_in, t_out = ray_box(o, d, lo, hi)
    # enters at x = 0 (t = 1), leaves at x = 1 (t = 2); from inside, leaves the floor at 0.5;
    # the third ray passes above the box: it misses (t_out < t_in)
    torch.testing.assert_close(t_in[:2], torch.tensor([1.0, -0.5]))
    torch.testing.assert_close(t_out[:2], torch.tensor([2.0, 0.5]))
    assert t_out[2] < t_in[2]
    # a camera at the origin looking along world +y: the centre pixel's ray is +y and its
    # z_scale is 1; a corner pixel's z_scale is 1/|(u-cx)/fx, (v-cy)/fy, 1|
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # columns: x right, y down, z forward
    intr = Intrinsics(10.0, 10.0, 2.0, 1.0, 5, 3)
    o, d, zs = camera_rays(pose, intr)
    torch.testing.assert_close(d[1 * 5 + 2], torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(zs[0], torch.tensor(1 / math.sqrt(0.2**2 + 0.1**2 + 1)))
    assert torch.all(o == 0)


def _depth_colour(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """A colour that varies non-linearly with depth along +x: ((x/3)^2, 0.25, 0.5 + 0.5 sin 4x).

    Non-linear on purpose: for a colour linear in x, compositing the samples' colours equals
    the colour at the expected depth, and the two render modes could not be told apart."""
    return torch.stack(
        [(x[:, 0] / 3.0) ** 2, torch.full((len(x),), 0.25), 0.5 + 0.5 * torch.sin(4.0 * x[:, 0])],
        dim=-1,
    )


def _at(t: float) -> torch.Tensor:
    return _depth_colour(torch.tensor([[t, 0.0, 0.0]]), torch.zeros(1, 3))[0]


def test_surface_color_is_the_colour_at_the_expected_depth():
    # The slab of the first test: sigma = 2 / m over [1, 1.5), acc = 1 - e^-1 = 0.63212,
    # expected depth 1.20902 (worked out there). surface_color colours each ray once, at
    # o + depth * d: rgb = acc * c(1.20902) + (1 - acc) * background, e.g. red =
    # 0.63212 * (1.20902 / 3)^2 + 0.36788 * 0.2 = 0.63212 * 0.16242 + 0.07358 = 0.17625.
    density, _ = _slab(2.0, 1.0, 1.5)
    o, d = _rays()
    bg = torch.tensor([0.2, 0.4, 0.6])
    acc = 1.0 - math.exp(-1.0)
    depth = 1.0 + 0.5 - 0.5 * math.exp(-1.0) / (1.0 - math.exp(-1.0))
    expect = (acc * _at(depth) + (1.0 - acc) * bg).expand(4, 3)
    assert abs(float(expect[0, 0]) - 0.17625) < 1e-4  # the hand value above
    kw = dict(near=0.0, far=3.0, step=0.01, background=bg, surface_color=True)
    surf = render_rays(o, d, field_of(density, _depth_colour), RenderOptions(prune_eps=0.0, **kw))
    # the depth is the midpoint-sample estimate (within ~1e-4 m of the exact mean, see above)
    # and the colour changes by < 2.5 per metre there: well within 2e-4
    torch.testing.assert_close(surf["rgb"], expect, atol=2e-4, rtol=0)
    torch.testing.assert_close(surf["acc"], torch.full((4,), acc), atol=1e-4, rtol=0)
    with torch.no_grad():  # the block-wise marcher of full-view renders gives the same
        blocks = render_rays(
            o, d, field_of(density, _depth_colour), RenderOptions(prune_eps=1e-4, **kw)
        )
    torch.testing.assert_close(blocks["rgb"], expect, atol=2e-4, rtol=0)
    # compositing averages c over the slab's weights instead: red = acc E[(t/3)^2] =
    # acc (E[t]^2 + Var[t]) / 9. For the truncated exponential (rate 2 on [0, 0.5] past x = 1)
    # E[s^2] = 2/4 - (0.25 + 0.5) e^-1 / (1 - e^-1) = 0.06351, Var = 0.06351 - 0.20902^2 =
    # 0.01982: red = 0.63212 (1.46173 + 0.01982) / 9 = 0.10406, vs 0.10267 at the surface.
    comp = render_rays(
        o,
        d,
        field_of(density, _depth_colour),
        RenderOptions(prune_eps=0.0, near=0.0, far=3.0, step=0.01),
    )
    torch.testing.assert_close(comp["rgb"][:, 0], torch.full((4,), 0.10406), atol=2e-4, rtol=0)
    torch.testing.assert_close(
        surf["rgb"][:, 0] - (1.0 - acc) * bg[0], torch.full((4,), 0.10267), atol=2e-4, rtol=0
    )


def test_surface_color_matches_compositing_for_a_sharp_step():
    # All the weight in the first sample past x = 2 (at its middle, 2.005): compositing
    # gives c(2.005), and so does colouring once at the expected depth 2.005.
    density, _ = _slab(1e5, 2.0, 10.0)
    o, d = _rays()
    bg = torch.tensor([0.2, 0.4, 0.6])
    kw = dict(near=0.0, far=5.0, step=0.01, background=bg)
    comp = render_rays(o, d, field_of(density, _depth_colour), RenderOptions(**kw))
    surf = render_rays(
        o, d, field_of(density, _depth_colour), RenderOptions(surface_color=True, **kw)
    )
    torch.testing.assert_close(comp["rgb"], _at(2.005).expand(4, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(surf["rgb"], comp["rgb"], atol=1e-5, rtol=0)
    torch.testing.assert_close(surf["depth"], comp["depth"])


def test_surface_color_misses_give_the_background_and_gradients_flow():
    # Rays 0-1 hit the step at x = 2, rays 2-3 start past x = 10 (empty beyond the slab):
    # the misses are pure background and the colour function is only asked about the hits.
    density, _ = _slab(1e5, 2.0, 10.0)
    o, d = _rays()
    o[2:, 0] = 10.5
    bg = torch.tensor([0.2, 0.4, 0.6])
    asked: list[int] = []
    gain = torch.tensor(1.0, requires_grad=True)

    def colour(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        asked.append(len(x))
        return gain * _depth_colour(x, v)

    out = render_rays(
        o,
        d,
        field_of(density, colour),
        RenderOptions(near=0.0, far=5.0, step=0.01, background=bg, surface_color=True),
    )
    assert asked == [2]
    torch.testing.assert_close(out["rgb"][2:], bg.expand(2, 3))
    torch.testing.assert_close(out["rgb"][:2].detach(), _at(2.005).expand(2, 3), atol=1e-5, rtol=0)
    # d(sum of the hits' rgb) / d gain = sum of c(2.005) over the two hits
    out["rgb"].sum().backward()
    torch.testing.assert_close(gain.grad, 2.0 * _at(2.005).sum(), atol=1e-5, rtol=0)

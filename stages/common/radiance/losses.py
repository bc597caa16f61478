"""The training losses of one step, apart from the loop: the marched batch's colour, depth,
surface and class terms, and the direct field queries (surface colour, geometry, edges)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from stages.common.radiance.compositing import RenderOut
from stages.common.radiance.config import LossConfig
from stages.common.radiance.field import RadianceField
from stages.common.radiance.views import Rays

HUBER_DELTA = 0.1
RGB_LOSSES = ("mse", "huber")


def depth_pixels(rays: Rays, n: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Up to n random training pixels among those with a depth reading (never more than
    there are: SfM tracks may give fewer readings than n): (index [M], ray distance of the
    reading [M]); none when no pixel has one."""
    assert rays.t_depth is not None
    pool = rays.with_depth
    if len(pool) == 0:
        return pool, rays.t_depth[pool]
    idx = pool[torch.randint(0, len(pool), (min(n, len(pool)),), generator=gen)]
    return idx, rays.t_depth[idx]


def surface_loss(cfg: LossConfig, model: RadianceField, rays: Rays, gen: torch.Generator) -> Tensor:
    """Colour of random pixels with depth, fitted at their depth point (jittered along the
    ray): one field query per pixel teaches the texture far faster than marching does."""
    idx, t = depth_pixels(rays, cfg.surface_rays, gen)
    if len(idx) == 0:
        return torch.zeros(())
    jit = (torch.rand(len(idx), generator=gen) * 2.0 - 1.0) * cfg.surface_jitter * model.step
    x = rays.origins[idx] + (t + jit)[:, None] * rays.dirs[idx]
    c = model.color(x, rays.dirs[idx])
    return F.mse_loss(c, rays.rgb[idx])


def geometry_loss(
    cfg: LossConfig, model: RadianceField, rays: Rays, gen: torch.Generator, dense: bool = True
) -> Tensor:
    """Density fitted directly from depth readings: one step's opacity is 0 at a point drawn
    in the geo_front metres (sparse depth: anywhere) in front of the reading (up to half a
    step before it) and 1 at a point drawn in the two steps behind it. Binary cross-entropy
    on that opacity, written with terms of sigma * step so it stays finite for any density."""
    idx, t = depth_pixels(rays, cfg.geo_rays, gen)
    if len(idx) == 0:
        return torch.zeros(())
    s = model.step
    u = torch.rand(2, len(idx), generator=gen)
    # dense depth: the grid already holds only the surfaces' cells, so the free point only
    # sharpens the front of the surface; sparse depth: anywhere between camera and reading
    # (the tracks' rays carve out the floaters that the photometric loss alone leaves)
    front = cfg.geo_front if dense else t - 0.5 * s
    t_free = (t - 0.5 * s - u[0] * front).clamp(min=0.0)
    t_full = t + u[1] * 2.0 * s
    tt = torch.cat([t_free, t_full])
    o, d = rays.origins[idx].repeat(2, 1), rays.dirs[idx].repeat(2, 1)
    sd = model.sigma(o + tt[:, None] * d) * s  # [2M] optical depth of one step
    m = len(idx)
    # free: -log(1 - alpha) = sd; full: -log(alpha) = -log(1 - exp(-sd))
    free = sd[:m].mean()
    # clamped far below any density the field can reach (exp(-15) * step), not at 1e-6: a
    # clamp there would zero the gradient that revives a region the field emptied
    full = -torch.log(-torch.expm1(-sd[m:].clamp(min=1e-30))).mean()
    return free + full


def edge_loss(cfg: LossConfig, model: RadianceField, rays: Rays, gen: torch.Generator) -> Tensor:
    """Silhouettes: a ray beside a nearer surface is empty where it passes that surface.

    Up to edge_rays rays with `t_edge` are drawn; each gets a free point within a step of
    t_edge (never within edge_gap / 2 of its own reading) whose one-step optical depth is
    pushed to 0, as `geometry_loss` does for its free points. The density that blurs an
    object's outline over the pixels beside it (it stands where those rays pass) is what
    this removes; random draws along the whole ray would land there about 1 % of the time.
    """
    assert rays.t_edge is not None and rays.t_depth is not None
    pool = rays.edges
    idx = pool[torch.randint(0, len(pool), (min(cfg.edge_rays, len(pool)),), generator=gen)]
    s = model.step
    u = torch.rand(len(idx), generator=gen) * 2.0 - 1.0
    t = (rays.t_edge[idx] + u * s).clamp(min=0.0)
    t = torch.minimum(t, rays.t_depth[idx] - 0.5 * cfg.edge_gap)
    sd = model.sigma(rays.origins[idx] + t[:, None] * rays.dirs[idx]) * s  # [K]
    return sd.mean()


def render_loss(cfg: LossConfig, out: RenderOut, rays: Rays, idx: Tensor, margin: float) -> Tensor:
    """RGB (+ depth L1 where valid, + semantic cross-entropy) loss of one batch."""
    target = rays.rgb[idx]
    if cfg.rgb == "mse":
        loss = F.mse_loss(out["rgb"], target)
    else:
        loss = F.huber_loss(out["rgb"], target, delta=HUBER_DELTA)
    if rays.t_depth is not None and cfg.depth_weight > 0:
        t = rays.t_depth[idx]
        ok = t > 0
        if ok.any():
            loss = loss + cfg.depth_weight * (out["depth"][ok] - t[ok]).abs().mean()
    if rays.t_depth is not None and cfg.surface_weight > 0:
        # a ray with a depth reading is opaque, and empty until trunc_steps before it
        t = rays.t_depth[idx]
        ok = t > 0
        if ok.any():
            ray, ts, w = out["ray"], out["t"], out["weights"]
            front = ts < t[ray] - margin
            w_front = torch.zeros(len(t)).index_add(0, ray[front], w[front])  # [R]
            term = (1.0 - out["acc"][ok]).mean() + w_front[ok].mean()
            loss = loss + cfg.surface_weight * term
    if rays.label is not None and out["semantics"] is not None and cfg.semantic_weight > 0:
        lab = rays.label[idx]
        if (lab >= 0).any():
            loss = loss + cfg.semantic_weight * F.cross_entropy(
                out["semantics"], lab, ignore_index=-1
            )
    return loss

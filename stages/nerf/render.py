"""Volume rendering with empty-space skipping, on fields given as functions.

`render_rays` marches each ray in steps of `step` metres from `near` to `far`, drops the
samples whose occupancy cell is empty, optionally drops (without gradient) the samples after
the transmittance has fallen below `prune_eps`, and composites the rest:
w_i = T_i (1 - exp(-sigma_i delta_i)), T_i = exp(-sum_{j<i} sigma_j delta_j). Because the
field enters only through `density_fn` / `color_fn` / `semantic_fn`, another stage can wrap
them (zero the density inside a box, recolour a region) without touching the training code.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import NotRequired, TypedDict

import numpy as np
import torch
from torch import Tensor

from stages.common.blueprint import Grid
from stages.common.camera import Intrinsics
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.nerf.field import NerfModel

DensityFn = Callable[[Tensor], Tensor]  # [N, 3] -> [N] density (1/m)
ColorFn = Callable[[Tensor, Tensor], Tensor]  # [N, 3], [N, 3] dirs -> [N, 3] RGB
SemanticFn = Callable[[Tensor], Tensor]  # [N, 3] -> [N, K] logits
MAX_SAMPLES = 8192  # samples per ray at most (a guard against a tiny step)
EARLY_BLOCK = 8  # samples per ray evaluated per round of the early-stop pass


class RenderOut(TypedDict):
    """What `render_rays` / `render_model` return (a plain dict at run time)."""

    rgb: Tensor  # [R, 3]
    depth: Tensor  # [R] expected ray distance t (= far where acc = 0)
    acc: Tensor  # [R] opacity
    semantics: Tensor | None  # [R, K] logits; None without a semantic function
    ray: NotRequired[Tensor]  # [N] ray of each sample (with return_samples)
    t: NotRequired[Tensor]  # [N] ray distance of each sample
    weights: NotRequired[Tensor]  # [N] compositing weight of each sample


class ViewOut(TypedDict):
    """What `render_view` returns (a plain dict at run time)."""

    rgb: np.ndarray  # [H, W, 3] in [0, 1]
    depth: np.ndarray  # [H, W] z-depth (metres)
    acc: np.ndarray  # [H, W]
    semantics: np.ndarray | None  # [H, W] uint8 class ids; None without a semantic head


class _Sums(TypedDict):
    """Per-ray weighted sums and the packed samples, before `_finish`."""

    acc: Tensor  # [R] sum of w
    rgb: Tensor  # [R, 3] sum of w c
    wt: Tensor  # [R] sum of w t
    semantics: Tensor | None  # [R, K] sum of w logits; None without a semantic function
    ray: Tensor  # [N]
    t: Tensor  # [N]
    weights: Tensor  # [N]


def _per_ray(v: float | Tensor, r: int) -> Tensor:
    return torch.as_tensor(v, dtype=torch.float32).expand(r).clone()


def render_rays(
    origins: Tensor,
    dirs: Tensor,
    density_fn: DensityFn,
    color_fn: ColorFn,
    semantic_fn: SemanticFn | None = None,
    near: float | Tensor = 0.0,
    far: float | Tensor = 1.0,
    occupancy=None,
    step: float = 0.01,
    perturb: bool = False,
    gen: torch.Generator | None = None,
    background: Tensor | None = None,
    prune_eps: float = 1e-4,
    return_samples: bool = False,
    surface_color: bool = False,
) -> RenderOut:
    """Render rays through a field given as functions.

    Args:
        origins, dirs: [R, 3] world origins and unit directions (t is in metres).
        density_fn, color_fn, semantic_fn: the field; color / semantic functions are called
            right after density_fn on the same points tensor.
        near, far: scalars or [R]; far < near is treated as far = near (no sample).
        occupancy: an object with `.query(x [N, 3]) -> bool [N]`, or None (all occupied).
        step: marching step (metres); sample i sits in [near + i step, near + (i+1) step).
        perturb: jitter each sample inside its interval (training), else at its middle.
        background: [3] colour added with weight 1 - acc (default black).
        prune_eps: skip samples after transmittance < this (first pass without gradient).
        surface_color: colour each ray once, at its expected depth, instead of compositing
            the colours of its samples (sharp for a depth-supervised field, whose density is a
            thin shell: off-surface samples would blend colours the field never fitted).
    Returns:
        rgb [R, 3], depth [R] (expected ray distance t, = far where acc = 0), acc [R],
        semantics [R, K] logits or None; with return_samples also ray [N], t [N], weights [N].
    """
    if surface_color:
        out = render_rays(
            origins,
            dirs,
            density_fn,
            _no_color,
            semantic_fn,
            near,
            far,
            occupancy,
            step,
            perturb,
            gen,
            None,
            prune_eps,
            return_samples,
        )
        hit = (out["acc"] > 1e-6).nonzero().squeeze(1)
        rgb = torch.zeros(len(origins), 3)
        if len(hit):
            x = origins[hit] + out["depth"][hit, None] * dirs[hit]
            density_fn(x)
            c = color_fn(x, dirs[hit])
            rgb = rgb.index_put((hit,), out["acc"][hit, None] * c)
        if background is not None:
            rgb = rgb + (1.0 - out["acc"])[:, None] * background
        out["rgb"] = rgb
        return out
    r = origins.shape[0]
    near_t = torch.nan_to_num(_per_ray(near, r), nan=0.0)  # [R]
    far_t = torch.maximum(torch.nan_to_num(_per_ray(far, r), nan=0.0), near_t)  # [R]
    span = float((far_t - near_t).max()) if r else 0.0
    s = int(min(MAX_SAMPLES, max(1, math.ceil(span / step - 1e-6)))) if span > 0 else 1
    ray, k = _candidates(origins, dirs, near_t, far_t, step, s, occupancy)  # [N] packed
    t0 = near_t[ray] + step * k  # [N] start of each sample's interval
    d_s = (torch.minimum(t0 + step, far_t[ray]) - t0).clamp(min=0.0)  # [N]
    u = torch.rand(len(ray), generator=gen) if perturb else torch.full((len(ray),), 0.5)
    t = t0 + u * d_s  # [N]
    x = origins[ray] + t[:, None] * dirs[ray]  # [N, 3]
    if occupancy is not None and len(x):
        keep = occupancy.query(x) & (d_s > 0)
        ray, k, d_s, t, x = ray[keep], k[keep], d_s[keep], t[keep], x[keep]
    if prune_eps > 0 and len(x) and not torch.is_grad_enabled():
        sums = _march_blocks(
            (density_fn, color_fn, semantic_fn), x, dirs, d_s, t, ray, r, prune_eps
        )
        return _finish(sums, near_t, far_t, background, return_samples)
    if prune_eps > 0 and len(x):
        keep = _early_stop(density_fn, x, d_s, ray, r, prune_eps)
        ray, k, d_s, t, x = ray[keep], k[keep], d_s[keep], t[keep], x[keep]
    if len(x):
        sigma = density_fn(x)  # [N]
        rgb_s = color_fn(x, dirs[ray])  # [N, 3]
        sem_s = semantic_fn(x) if semantic_fn is not None else None  # [N, K]
    else:  # no sample at all: still call nothing, return the background
        sigma, rgb_s, sem_s = torch.zeros(0), torch.zeros(0, 3), None
    trans, alpha = _transmittance(sigma * d_s, ray * s + k.long(), r, s)
    w = trans * alpha  # [N]
    # acc, rgb, wt, then semantics: the order of these ops sets the order in which backward
    # sums the gradients of w (float rounding: keep it for bit-identical training)
    acc = torch.zeros(r).index_add(0, ray, w)  # [R]
    rgb_sum = torch.zeros(r, 3).index_add(0, ray, w[:, None] * rgb_s)  # [R, 3]
    wt = torch.zeros(r).index_add(0, ray, w * t)  # [R]
    sem_sum: Tensor | None = None
    if semantic_fn is not None:
        k_cls = sem_s.shape[1] if sem_s is not None else 0
        sem_sum = torch.zeros(r, k_cls)  # [R, K]
        if sem_s is not None:
            sem_sum = sem_sum.index_add(0, ray, w[:, None] * sem_s)
    sums = {
        "acc": acc,
        "rgb": rgb_sum,
        "wt": wt,
        "semantics": sem_sum,
        "ray": ray,
        "t": t,
        "weights": w,
    }
    return _finish(sums, near_t, far_t, background, return_samples)


def _no_color(x: Tensor, dirs: Tensor) -> Tensor:
    return torch.zeros(len(x), 3)


def _finish(
    out: _Sums, near: Tensor, far: Tensor, background: Tensor | None, return_samples: bool
) -> RenderOut:
    """Expected depth (far where nothing was hit), background, and the returned keys."""
    acc = out["acc"]
    depth = torch.where(acc > 1e-10, out["wt"] / acc.clamp(min=1e-10), far)
    depth = torch.minimum(torch.maximum(depth, near), far)
    rgb = out["rgb"]
    if background is not None:
        rgb = rgb + (1.0 - acc)[:, None] * background
    res: RenderOut = {"rgb": rgb, "depth": depth, "acc": acc, "semantics": out["semantics"]}
    if return_samples:
        res["ray"], res["t"], res["weights"] = out["ray"], out["t"], out["weights"]
    return res


def _march_blocks(
    fns: tuple[DensityFn, ColorFn, SemanticFn | None],
    x: Tensor,
    dirs: Tensor,
    d_s: Tensor,
    t: Tensor,
    ray: Tensor,
    r: int,
    eps: float,
) -> _Sums:
    """Render without gradient, EARLY_BLOCK samples per ray at a time, stopping each ray
    once its transmittance is below eps: every sample's field is evaluated once."""
    density_fn, color_fn, semantic_fn = fns
    tau = torch.zeros(r)  # [R] optical depth so far
    acc, rgb_sum, wt = torch.zeros(r), torch.zeros(r, 3), torch.zeros(r)  # [R], [R, 3], [R]
    sem_sum: Tensor | None = None  # [R, K]
    rays: list[Tensor] = []
    ts: list[Tensor] = []
    ws: list[Tensor] = []
    for idx in _transparent_blocks(ray, r, tau, eps):
        xi, ri = x[idx], ray[idx]
        sd = (density_fn(xi) * d_s[idx]).clamp(min=0.0)  # [M]
        rgb = color_fn(xi, dirs[ri])  # [M, 3]
        sem = semantic_fn(xi) if semantic_fn is not None else None  # [M, K]
        w = torch.exp(-(tau[ri] + _exclusive_cumsum(sd, ri, r))) * -torch.expm1(-sd)  # [M]
        acc.index_add_(0, ri, w)
        rgb_sum.index_add_(0, ri, w[:, None] * rgb)
        wt.index_add_(0, ri, w * t[idx])
        if sem is not None:
            if sem_sum is None:
                sem_sum = torch.zeros(r, sem.shape[1])
            sem_sum.index_add_(0, ri, w[:, None] * sem)
        tau.index_add_(0, ri, sd)
        rays.append(ri)
        ts.append(t[idx])
        ws.append(w)
    if semantic_fn is not None and sem_sum is None:
        sem_sum = torch.zeros(r, 0)

    def cat(v: list[Tensor], dt: torch.dtype) -> Tensor:
        return torch.cat(v) if v else torch.zeros(0, dtype=dt)

    return {
        "acc": acc,
        "rgb": rgb_sum,
        "wt": wt,
        "semantics": sem_sum,
        "ray": cat(rays, torch.int64),
        "t": cat(ts, torch.float32),
        "weights": cat(ws, torch.float32),
    }


def _transparent_blocks(ray: Tensor, r: int, tau: Tensor, eps: float) -> Iterator[Tensor]:
    """Indices of packed samples (sorted by ray then t), EARLY_BLOCK per ray at a time, of
    the rays whose transmittance exp(-tau) is still >= eps; the caller adds each block's
    optical depths to tau [R] (in place) before asking for the next block."""
    n = len(ray)
    first = torch.zeros(r, dtype=torch.int64).scatter_reduce(
        0, ray, torch.arange(n), "amin", include_self=False
    )
    rank = torch.arange(n) - first[ray]  # [N] position of the sample along its ray
    pend = torch.arange(n)  # samples not evaluated yet, of rays still transparent
    b = 0
    while len(pend):
        pend = pend[torch.exp(-tau[ray[pend]]) >= eps]
        now = rank[pend] < b + EARLY_BLOCK
        idx, pend = pend[now], pend[~now]
        b += EARLY_BLOCK
        if len(idx):
            yield idx


def _exclusive_cumsum(v: Tensor, ray: Tensor, r: int) -> Tensor:
    """Per-ray exclusive cumulative sum of packed values v [M] (a ray's entries consecutive
    and in order), computed in float64 to keep long rays exact. Returns float32 [M]."""
    cs = torch.cumsum(v.double(), 0) - v.double()
    start = torch.zeros(r, dtype=torch.int64).scatter_reduce(
        0, ray, torch.arange(len(v)), "amin", include_self=False
    )
    return (cs - cs[start[ray]]).float()


def _candidates(
    origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor, step: float, s: int, occupancy
) -> tuple[Tensor, Tensor]:
    """(ray [N], k [N]) of the samples worth testing, sorted by ray then k. With an
    occupancy grid offering `query_coarse`, rays are first walked in segments no longer
    than its coarse blocks, and only the samples of segments near an occupied block are
    kept (the fine test against the cells follows)."""
    if occupancy is None or not hasattr(occupancy, "query_coarse"):
        k = torch.arange(s, dtype=torch.float32)
        ray, k_i = (near[:, None] + step * k < far[:, None]).nonzero(as_tuple=True)
        return ray, k_i.to(torch.float32)
    m = max(1, int(occupancy.coarse_size() / step))  # fine samples per coarse segment
    sc = math.ceil(s / m)
    tc = near[:, None] + (m * step) * torch.arange(sc, dtype=torch.float32)  # [R, Sc]
    ray, j = (tc < far[:, None]).nonzero(as_tuple=True)
    mid = tc[ray, j] + 0.5 * m * step
    keep = occupancy.query_coarse(origins[ray] + mid[:, None] * dirs[ray])
    ray, j = ray[keep], j[keep]
    k = (j[:, None] * m + torch.arange(m)).view(-1)  # [N m]
    ray = ray[:, None].expand(-1, m).reshape(-1)
    ok = k < s
    return ray[ok], k[ok].to(torch.float32)


@torch.no_grad()
def _early_stop(
    density_fn: DensityFn, x: Tensor, d_s: Tensor, ray: Tensor, r: int, eps: float
) -> Tensor:
    """Which packed samples (sorted by ray then t) come before their ray's transmittance
    falls below eps. Densities are evaluated in blocks of each ray's next EARLY_BLOCK
    samples, for the rays still transparent only. Returns bool [N]."""
    tau = torch.zeros(r)  # [R] optical depth so far
    keep = torch.zeros(len(x), dtype=torch.bool)
    for idx in _transparent_blocks(ray, r, tau, eps):
        sd = (density_fn(x[idx]) * d_s[idx]).clamp(min=0.0)  # [M]
        ri = ray[idx]
        keep[idx] = torch.exp(-(tau[ri] + _exclusive_cumsum(sd, ri, r))) >= eps
        tau.index_add_(0, ri, sd)
    return keep


def _transmittance(sd: Tensor, flat: Tensor, r: int, s: int) -> tuple[Tensor, Tensor]:
    """Packed optical depths sigma*delta [N] at flat (ray * S + k) -> (T_i [N], alpha_i [N])."""
    sd = sd.clamp(min=0.0)
    dense = torch.zeros(r * s).index_put((flat,), sd)  # [R S]
    cum = torch.cumsum(dense.view(r, s), dim=1).view(-1) - dense  # exclusive, per ray
    trans = torch.exp(-cum[flat])
    alpha = -torch.expm1(-sd)  # 1 - exp(-sd), exact for small sd
    return trans, alpha


def ray_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test: (t_enter [R], t_exit [R]); t_exit < t_enter when the ray misses the box."""
    d = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    a = (lo - origins) / d
    b = (hi - origins) / d
    return torch.minimum(a, b).amax(dim=1), torch.maximum(a, b).amin(dim=1)


def render_model(
    model: NerfModel,
    origins: Tensor,
    dirs: Tensor,
    near: float | None = None,
    perturb: bool = False,
    gen: torch.Generator | None = None,
    semantics: bool = True,
    return_samples: bool = False,
    far: Tensor | None = None,
    prune: bool = True,
    surface_color: bool | None = None,
    density_fn: DensityFn | None = None,
    color_fn: ColorFn | None = None,
) -> RenderOut:
    """render_rays with the model's field, box, occupancy grid and step; `far` [R] (metres)
    cuts rays shorter than the box, `prune` = False skips the transmittance pre-pass.
    `density_fn` / `color_fn` replace the model's own (an edited field; no colour at all
    when only the weights matter)."""
    t_in, t_out = ray_box(origins, dirs, model.lo, model.hi)
    if far is not None:
        t_out = torch.minimum(t_out, far)
    n = model.cfg.near if near is None else near
    near_t = t_in.clamp(min=n)
    sem_fn = model.semantics if (semantics and model.sem_head is not None) else None
    out = render_rays(
        origins,
        dirs,
        model.density if density_fn is None else density_fn,
        model.color if color_fn is None else color_fn,
        sem_fn,
        near=near_t,
        far=t_out,
        occupancy=model.occupancy,
        step=model.step,
        perturb=perturb,
        gen=gen,
        prune_eps=model.cfg.prune_eps if prune else 0.0,
        return_samples=return_samples,
        surface_color=model.surface_color if surface_color is None else surface_color,
    )
    model.clear_cache()
    return out


def camera_rays(pose: np.ndarray, intr: Intrinsics) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through every pixel centre (integer u, v). Returns origins [HW, 3], unit dirs
    [HW, 3] and z_scale [HW] (z-depth = ray distance * z_scale), row-major."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    d_cam = np.stack(
        [(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1
    ).reshape(-1, 3)  # [HW, 3]
    norm = np.linalg.norm(d_cam, axis=1)
    dirs = (d_cam / norm[:, None]) @ np.asarray(pose)[:3, :3].T
    origins = np.broadcast_to(np.asarray(pose)[:3, 3], dirs.shape)
    return (
        torch.from_numpy(np.ascontiguousarray(origins, np.float32)),
        torch.from_numpy(dirs.astype(np.float32)),
        torch.from_numpy((1.0 / norm).astype(np.float32)),
    )


@torch.no_grad()
def render_view(
    model: NerfModel,
    pose: np.ndarray,
    intr: Intrinsics,
    chunk: int = 16384,
    color: bool = True,
    pixels: np.ndarray | None = None,
) -> ViewOut:
    """Render a full view: rgb [H, W, 3] in [0, 1], depth [H, W] (z along the optical axis,
    metres), acc [H, W], semantics [H, W] uint8 class ids (255 where acc < acc_threshold)
    or None when the model has no semantic head. `color` False: depth and opacity only
    (rgb black, semantics None), without the colour queries (~40 % of the time). `pixels`
    (bool [H, W]): only those are rendered, the others are 0 (no opacity: unknown class)."""
    o, d, zs = camera_rays(pose, intr)
    h, w = intr.height, intr.width
    if pixels is not None:
        if pixels.shape != (h, w):
            raise BlunfError(f"render_view: pixel mask of {pixels.shape} for a {h}x{w} view")
        sel = torch.from_numpy(np.flatnonzero(pixels))
        o, d, zs = o[sel], d[sel], zs[sel]
    parts: dict[str, list[Tensor]] = {"rgb": [], "depth": [], "acc": [], "sem": []}
    for i in range(0, len(o), chunk):
        out = render_model(
            model,
            o[i : i + chunk],
            d[i : i + chunk],
            semantics=color,
            surface_color=None if color else False,
            color_fn=None if color else _no_color,
        )
        parts["rgb"].append(out["rgb"])
        parts["depth"].append(out["depth"] * zs[i : i + chunk])
        parts["acc"].append(out["acc"])
        if out["semantics"] is not None:
            parts["sem"].append(out["semantics"].argmax(dim=1))

    def whole(t: list[Tensor], *shape: int) -> np.ndarray:
        """The rendered values [N, ...] in a full view [H, W, ...] (0 where not rendered)."""
        x = torch.cat(t) if t else torch.zeros((0, *shape))
        if pixels is None:
            return x.reshape(h, w, *shape).numpy()
        full = torch.zeros((h * w, *shape), dtype=x.dtype)
        full[sel] = x
        return full.reshape(h, w, *shape).numpy()

    acc = whole(parts["acc"])
    sem = None
    if parts["sem"]:
        ids = np.asarray(model.class_ids, np.uint8)[whole(parts["sem"]).reshape(-1)]
        sem = np.where(acc.reshape(-1) >= model.cfg.acc_threshold, ids, UNKNOWN)
        sem = sem.astype(np.uint8).reshape(h, w)
    return {
        "rgb": np.clip(whole(parts["rgb"], 3), 0, 1),
        "depth": whole(parts["depth"]),
        "acc": acc,
        "semantics": sem,
    }


@torch.no_grad()
def top_view_labels(
    model: NerfModel, grid: Grid, heights: list[float], chunk: int = 16384
) -> dict[float, np.ndarray]:
    """The NeRF top-view baseline: per height, one vertical ray down from each cell centre.

    A cell's label is the semantic argmax at the ray's highest-weight sample (its first
    surface); 255 where the ray's opacity is below acc_threshold. Returns {height: uint8
    [H, W]} (row 0 = highest y, as the grid).
    """
    if model.sem_head is None:
        raise BlunfError("NeRF top view: the model was trained without labels")
    xy = torch.from_numpy(grid.centers().reshape(-1, 2).astype(np.float32))  # [HW, 2]
    ids = np.asarray(model.class_ids, np.uint8)
    out: dict[float, np.ndarray] = {}
    for h in heights:
        labels = np.full(len(xy), UNKNOWN, np.uint8)
        for i in range(0, len(xy), chunk):
            p = xy[i : i + chunk]
            o = torch.cat([p, torch.full((len(p), 1), float(h))], dim=1)
            d = torch.tensor([0.0, 0.0, -1.0]).expand(len(p), 3)
            res = render_model(
                model,
                o,
                d,
                near=0.0,
                semantics=False,
                return_samples=True,
                surface_color=False,
                color_fn=_no_color,  # the labels need the weights only
            )
            ray, t, w = res["ray"], res["t"], res["weights"]
            wmax = torch.zeros(len(p)).scatter_reduce(0, ray, w, "amax")
            top = w >= wmax[ray]
            t_top = torch.full((len(p),), float("inf")).scatter_reduce(0, ray[top], t[top], "amin")
            hit = (res["acc"] >= model.cfg.acc_threshold) & torch.isfinite(t_top)
            if hit.any():
                x = o[hit] + t_top[hit, None] * d[hit]
                cls = model.semantics(x).argmax(dim=1).numpy()
                model.clear_cache()
                labels[i : i + chunk][hit.numpy()] = ids[cls]
        out[float(h)] = labels.reshape(grid.shape)
    return out

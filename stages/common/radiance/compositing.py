"""Compositing: packed samples and their densities, colours and logits -> per-ray colour,
depth, opacity and class logits.

w_i = T_i (1 - exp(-sigma_i delta_i)), T_i = exp(-sum_{j<i} sigma_j delta_j); a ray's colour is
sum w_i c_i (+ (1 - acc) background), its depth sum w_i t_i / acc (far where acc = 0), its
logits sum w_i l_i.
"""

from __future__ import annotations

from typing import NotRequired, TypedDict

import torch
from torch import Tensor

from stages.common.radiance.field import QueryFn
from stages.common.radiance.marching import Samples, exclusive_cumsum, transparent_blocks


class RenderOut(TypedDict):
    """What the renderer returns for R rays (a plain dict at run time)."""

    rgb: Tensor  # [R, 3]
    depth: Tensor  # [R] expected ray distance t (= far where acc = 0)
    acc: Tensor  # [R] opacity
    semantics: Tensor | None  # [R, K] logits; None without semantics
    ray: NotRequired[Tensor]  # [N] ray of each sample (with return_samples)
    t: NotRequired[Tensor]  # [N] ray distance of each sample
    weights: NotRequired[Tensor]  # [N] compositing weight of each sample


class Sums(TypedDict):
    """Per-ray weighted sums and the packed samples, before `finish`."""

    acc: Tensor  # [R] sum of w
    rgb: Tensor  # [R, 3] sum of w c
    wt: Tensor  # [R] sum of w t
    semantics: Tensor | None  # [R, K] sum of w logits; None without logits
    ray: Tensor  # [N]
    t: Tensor  # [N]
    weights: Tensor  # [N]


def transmittance(sd: Tensor, flat: Tensor, r: int, s: int) -> tuple[Tensor, Tensor]:
    """Packed optical depths sigma*delta [N] at flat (ray * S + k) -> (T_i [N], alpha_i [N])."""
    sd = sd.clamp(min=0.0)
    dense = torch.zeros(r * s).index_put((flat,), sd)  # [R S]
    cum = torch.cumsum(dense.view(r, s), dim=1).view(-1) - dense  # exclusive, per ray
    trans = torch.exp(-cum[flat])
    alpha = -torch.expm1(-sd)  # 1 - exp(-sd), exact for small sd
    return trans, alpha


def accumulate(
    samples: Samples, sigma: Tensor, rgb: Tensor, logits: Tensor | None, with_logits: bool
) -> Sums:
    """Weights of the samples from their densities sigma [N], and the per-ray sums of the
    colours rgb [N, 3] and logits [N, K] (None: none; `with_logits` then still gives [R, 0])."""
    r, s = len(samples.near), samples.per_ray
    ray, t = samples.ray, samples.t
    trans, alpha = transmittance(sigma * samples.delta, ray * s + samples.k.long(), r, s)
    w = trans * alpha  # [N]
    # acc, rgb, wt, then semantics: the order of these ops sets the order in which backward
    # sums the gradients of w (float rounding: keep it for bit-identical training)
    acc = torch.zeros(r).index_add(0, ray, w)  # [R]
    rgb_sum = torch.zeros(r, 3).index_add(0, ray, w[:, None] * rgb)  # [R, 3]
    wt = torch.zeros(r).index_add(0, ray, w * t)  # [R]
    sem_sum: Tensor | None = None
    if logits is not None or with_logits:
        k_cls = logits.shape[1] if logits is not None else 0
        sem_sum = torch.zeros(r, k_cls)  # [R, K]
        if logits is not None:
            sem_sum = sem_sum.index_add(0, ray, w[:, None] * logits)
    return {"acc": acc, "rgb": rgb_sum, "wt": wt, "semantics": sem_sum, "ray": ray, "t": t,
            "weights": w}  # fmt: skip


@torch.no_grad()
def accumulate_blocks(query: QueryFn, dirs: Tensor | None, samples: Samples, eps: float) -> Sums:
    """`accumulate` without gradient, querying the field EARLY_BLOCK samples per ray at a
    time and stopping each ray once its transmittance is below eps: every sample's field is
    evaluated once. dirs [R, 3] of the rays (None: no colour asked)."""
    r = len(samples.near)
    x, d_s, t, ray = samples.x, samples.delta, samples.t, samples.ray
    tau = torch.zeros(r)  # [R] optical depth so far
    acc, rgb_sum, wt = torch.zeros(r), torch.zeros(r, 3), torch.zeros(r)  # [R], [R, 3], [R]
    sem_sum: Tensor | None = None  # [R, K]
    rays: list[Tensor] = []
    ts: list[Tensor] = []
    ws: list[Tensor] = []
    for idx in transparent_blocks(ray, r, tau, eps):
        xi, ri = x[idx], ray[idx]
        f = query(xi, None if dirs is None else dirs[ri])
        sd = (f.sigma * d_s[idx]).clamp(min=0.0)  # [M]
        w = torch.exp(-(tau[ri] + exclusive_cumsum(sd, ri, r))) * -torch.expm1(-sd)  # [M]
        acc.index_add_(0, ri, w)
        if f.rgb is not None:
            rgb_sum.index_add_(0, ri, w[:, None] * f.rgb)
        wt.index_add_(0, ri, w * t[idx])
        if f.logits is not None:
            if sem_sum is None:
                sem_sum = torch.zeros(r, f.logits.shape[1])
            sem_sum.index_add_(0, ri, w[:, None] * f.logits)
        tau.index_add_(0, ri, sd)
        rays.append(ri)
        ts.append(t[idx])
        ws.append(w)

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


def finish(
    out: Sums, near: Tensor, far: Tensor, background: Tensor | None, return_samples: bool
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

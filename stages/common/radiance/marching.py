"""Ray marching: rays -> packed samples, with empty-space skipping and early stop.

Each ray is walked in steps of `step` metres from `near` to `far`; sample i sits in
[near + i step, near + (i+1) step), at its middle or (training) jittered inside it. Samples
whose occupancy cell is empty are dropped; `early_stop` drops (without gradient) those after
the ray's transmittance has fallen below a threshold. Samples are packed: sorted by ray,
then by distance along it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

from stages.common.radiance.field import SigmaFn
from stages.common.radiance.occupancy import Occupancy

MAX_SAMPLES = 8192  # samples per ray at most (a guard against a tiny step)
EARLY_BLOCK = 8  # samples per ray evaluated per round of the early-stop pass


@dataclass(frozen=True)
class Samples:
    """Packed samples of R rays (sorted by ray, then t)."""

    ray: Tensor  # [N] int64 ray of each sample
    k: Tensor  # [N] float32 index of the sample along its ray
    t: Tensor  # [N] ray distance of the sample (metres)
    delta: Tensor  # [N] length of its interval (metres; shorter at far)
    x: Tensor  # [N, 3] world position
    near: Tensor  # [R] where each ray starts
    far: Tensor  # [R] where it ends (>= near)
    per_ray: int  # S: samples a ray may hold at most (k < S)

    def take(self, keep: Tensor) -> Samples:
        """The samples where keep (bool or indices [N]) holds."""
        return Samples(
            self.ray[keep],
            self.k[keep],
            self.t[keep],
            self.delta[keep],
            self.x[keep],
            self.near,
            self.far,
            self.per_ray,
        )


def _per_ray(v: float | Tensor, r: int) -> Tensor:
    return torch.as_tensor(v, dtype=torch.float32).expand(r).clone()


def march(
    origins: Tensor,
    dirs: Tensor,
    near: float | Tensor,
    far: float | Tensor,
    step: float,
    occupancy: Occupancy | None = None,
    gen: torch.Generator | None = None,
    perturb: bool = False,
) -> Samples:
    """The samples of rays origins, dirs [R, 3] (unit dirs; near, far scalars or [R], far <
    near read as far = near) that the occupancy grid (None: everywhere) finds occupied.
    `perturb`: jitter each sample inside its interval (one draw of `gen` per candidate)."""
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
    out = Samples(ray, k, t, d_s, x, near_t, far_t, s)
    if occupancy is not None and len(x):
        out = out.take(occupancy.query(x) & (d_s > 0))
    return out


def _candidates(
    origins: Tensor,
    dirs: Tensor,
    near: Tensor,
    far: Tensor,
    step: float,
    s: int,
    occupancy: Occupancy | None,
) -> tuple[Tensor, Tensor]:
    """(ray [N], k [N]) of the samples worth testing, sorted by ray then k. With an
    occupancy grid, rays are first walked in segments no longer than its coarse blocks, and
    only the samples of segments near an occupied block are kept (the fine test against the
    cells follows)."""
    if occupancy is None:
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


def transparent_blocks(ray: Tensor, r: int, tau: Tensor, eps: float) -> Iterator[Tensor]:
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


def exclusive_cumsum(v: Tensor, ray: Tensor, r: int) -> Tensor:
    """Per-ray exclusive cumulative sum of packed values v [M] (a ray's entries consecutive
    and in order), computed in float64 to keep long rays exact. Returns float32 [M]."""
    cs = torch.cumsum(v.double(), 0) - v.double()
    start = torch.zeros(r, dtype=torch.int64).scatter_reduce(
        0, ray, torch.arange(len(v)), "amin", include_self=False
    )
    return (cs - cs[start[ray]]).float()


@torch.no_grad()
def early_stop(sigma: SigmaFn, samples: Samples, eps: float) -> Tensor:
    """Which samples come before their ray's transmittance falls below eps. Densities are
    evaluated in blocks of each ray's next EARLY_BLOCK samples, for the rays still
    transparent only. Returns bool [N]."""
    r = len(samples.near)
    x, d_s, ray = samples.x, samples.delta, samples.ray
    tau = torch.zeros(r)  # [R] optical depth so far
    keep = torch.zeros(len(x), dtype=torch.bool)
    for idx in transparent_blocks(ray, r, tau, eps):
        sd = (sigma(x[idx]) * d_s[idx]).clamp(min=0.0)  # [M]
        ri = ray[idx]
        keep[idx] = torch.exp(-(tau[ri] + exclusive_cumsum(sd, ri, r))) >= eps
        tau.index_add_(0, ri, sd)
    return keep

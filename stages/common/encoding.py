"""Coordinate encodings of the BluNF field, on plan coordinates already normalised to [-1, 1]
(the positional encoding, the table gather and the ReLU MLP serve the NeRF field too).

- "none": the coordinates as they are.
- "pe": NeRF's positional encoding [u, sin(2^k pi u), cos(2^k pi u)], k < n_freqs.
- "hash": Instant-NGP's multi-resolution grid in 2-D: per level, the 4 corner features of the
  cell holding the point are bilinearly interpolated; levels whose (res + 1)^2 vertices fit the
  table are indexed densely, finer ones through the spatial hash (x * 1) xor (y * 2654435761).
- "siren": sine layers with SIREN's initialisation (the whole MLP, not an input encoding).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

ENCODINGS = ("none", "pe", "hash", "siren")
_PRIME = 2654435761  # Instant-NGP's second hashing prime (the first is 1)


class Identity(nn.Module):
    """No encoding: [B, 2] -> [B, 2]."""

    out_dim = 2

    def forward(self, u: Tensor) -> Tensor:
        return u


class PositionalEncoding(nn.Module):
    """[N, D] -> [N, D (1 + 2 n_freqs)]: the input, then sin and cos of 2^k pi x."""

    freqs: Tensor  # [n_freqs] buffer

    def __init__(self, dims: int, n_freqs: int) -> None:
        super().__init__()
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(n_freqs, dtype=torch.float32))
        self.out_dim = dims * (1 + 2 * n_freqs)

    def forward(self, x: Tensor) -> Tensor:
        a = (x[:, :, None] * self.freqs).flatten(1)  # [N, D n]
        return torch.cat([x, torch.sin(a), torch.cos(a)], dim=-1)


class HashGrid2D(nn.Module):
    """Multi-resolution hash grid: [B, 2] in [-1, 1] -> [B, levels * features].

    Level l has resolution floor(base_res * g^l) with g chosen so the last level is max_res.
    """

    def __init__(
        self, levels: int, features: int, log2_size: int, base_res: int, max_res: int
    ) -> None:
        super().__init__()
        g = math.exp((math.log(max_res) - math.log(base_res)) / (levels - 1)) if levels > 1 else 1
        res = [max(1, math.floor(base_res * g**level + 1e-6)) for level in range(levels)]
        size = 2**log2_size
        sizes = [min(size, (r + 1) ** 2) for r in res]
        offsets = [sum(sizes[:i]) for i in range(levels)]
        dense = [i for i in range(levels) if (res[i] + 1) ** 2 <= size]
        hashed = [i for i in range(levels) if (res[i] + 1) ** 2 > size]
        self.groups = [(tuple(g), g is hashed) for g in (dense, hashed) if g]
        for name, lv in (("dense", dense), ("hashed", hashed)):
            self.register_buffer(f"{name}_res", torch.tensor([res[i] for i in lv]).float())
            self.register_buffer(f"{name}_off", torch.tensor([offsets[i] for i in lv]))
        self.mask = size - 1
        self.table = nn.Parameter(torch.empty(sum(sizes), features).uniform_(-1e-4, 1e-4))
        self.out_dim = levels * features
        self.res = res

    def forward(self, u: Tensor) -> Tensor:
        p = ((u + 1) * 0.5).clamp(0.0, 1.0)  # [B, 2] in the unit square
        out = []
        for name, is_hashed in (("dense", False), ("hashed", True)):
            res = getattr(self, f"{name}_res")  # [Lg]
            if len(res) == 0:
                continue
            pos = p[None] * res[:, None, None]  # [Lg, B, 2]
            i0 = torch.minimum(pos.floor(), (res - 1)[:, None, None])  # [Lg, B, 2]
            f = pos - i0  # [Lg, B, 2] position inside the cell
            x0, y0 = i0[..., 0].long(), i0[..., 1].long()  # [Lg, B]
            if is_hashed:
                hy0, hy1 = y0 * _PRIME, (y0 + 1) * _PRIME
                corners = [x0 ^ hy0, (x0 + 1) ^ hy0, x0 ^ hy1, (x0 + 1) ^ hy1]
                idx = torch.stack(corners, -1) & self.mask  # [Lg, B, 4]
            else:
                row = (res.long() + 1)[:, None]  # [Lg, 1] vertices per grid row
                i00 = x0 + y0 * row
                idx = torch.stack([i00, i00 + 1, i00 + row, i00 + row + 1], -1)  # [Lg, B, 4]
            idx = idx + getattr(self, f"{name}_off")[:, None, None]
            fx, fy = f[..., 0], f[..., 1]  # [Lg, B]
            w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
            feats = gather_rows(self.table, idx.flatten()).view(*idx.shape, -1)  # [Lg, B, 4, F]
            out.append((w[..., None] * feats).sum(dim=2))  # [Lg, B, F]
        return torch.cat(out).permute(1, 0, 2).flatten(1)  # [B, L F], levels coarse to fine


class _Gather(torch.autograd.Function):
    """rows = table[idx] for a [T, F] float32 table, with faster CPU kernels than index_select
    on rows: pairs of features are read as one float64 (a 1-D gather) and the backward
    accumulates one contiguous column at a time (1-D index_add, deterministic on CPU)."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor) -> Tensor:
        ctx.save_for_backward(idx)
        ctx.size = table.shape
        if table.shape[1] == 2 and table.dtype == torch.float32 and table.is_contiguous():
            pairs = table.view(torch.float64).view(-1).index_select(0, idx)  # [M]
            return pairs.view(torch.float32).view(-1, 2)
        return table.index_select(0, idx)

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor, None]:
        (idx,) = ctx.saved_tensors
        t, f = ctx.size
        grad = torch.zeros(f, t, dtype=g.dtype)
        for j in range(f):
            grad[j].index_add_(0, idx, g[:, j].contiguous())
        return grad.t().contiguous(), None


def gather_rows(table: Tensor, idx: Tensor) -> Tensor:
    """table[idx] for a [T, F] table and flat indices [M] -> [M, F] (see _Gather)."""
    out: Tensor = _Gather.apply(table, idx)
    return out


class SineLayer(nn.Module):
    """sin(omega * (W x + b)) with SIREN's initialisation."""

    def __init__(self, n_in: int, n_out: int, omega: float, first: bool) -> None:
        super().__init__()
        self.linear = nn.Linear(n_in, n_out)
        self.omega = omega
        bound = 1.0 / n_in if first else math.sqrt(6.0 / n_in) / omega
        with torch.no_grad():
            self.linear.weight.uniform_(-bound, bound)

    def forward(self, x: Tensor) -> Tensor:
        return torch.sin(self.omega * self.linear(x))


def siren(width: int, layers: int, n_out: int, omega: float) -> nn.Sequential:
    """SIREN [B, 2] -> [B, n_out]: `layers` sine layers then a linear map (SIREN init)."""
    mods: list[nn.Module] = [SineLayer(2, width, omega, first=True)]
    mods += [SineLayer(width, width, omega, first=False) for _ in range(layers - 1)]
    last = nn.Linear(width, n_out)
    with torch.no_grad():
        bound = math.sqrt(6.0 / width) / omega
        last.weight.uniform_(-bound, bound)
    return nn.Sequential(*mods, last)


def relu_mlp(n_in: int, width: int, layers: int, n_out: int) -> nn.Sequential:
    """[B, n_in] -> [B, n_out]: `layers` hidden ReLU layers of `width` units."""
    mods: list[nn.Module] = []
    for i in range(layers):
        mods += [nn.Linear(n_in if i == 0 else width, width), nn.ReLU()]
    mods.append(nn.Linear(width if layers else n_in, n_out))
    return nn.Sequential(*mods)

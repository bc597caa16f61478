"""The radiance field: world points -> colour, density (1/m) and class logits, in one query.

World points are mapped into the unit cube by the scene box (per axis) before encoding.
Two encodings share the heads: Instant-NGP's multi-resolution hash grid (the default: a few
table look-ups per sample and a 64-wide MLP) and NeRF's positional encoding with a 4 x 128
MLP (the baseline the bench compares against). Density uses a truncated exponential: exp
with its argument clamped at 15 in both passes, so it never overflows.

A renderer takes the field as functions (`FieldFns`): `sigma` for density alone (marching,
occupancy updates) and `query` for one pass per sample batch; nothing is kept between calls.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor, nn

from stages.common.encoding import PositionalEncoding, gather_rows, relu_mlp
from stages.common.errors import BlunfError
from stages.common.radiance.config import FIELDS, FieldConfig, SamplingConfig
from stages.common.radiance.occupancy import OccupancyGrid

EXP_CLAMP = 15.0  # density = exp(min(raw, 15)) <= 3.3e6 per metre
# Instant-NGP's hashing primes, as wrapped int32 (int32 products wrap the same way every run).
_PRIMES = (1, 2654435761 - 2**32, 805459861)


class TruncExp(torch.autograd.Function):
    """exp(x) with x clamped to EXP_CLAMP in the forward and the backward pass."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        y = torch.exp(x.clamp(max=EXP_CLAMP))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        (y,) = ctx.saved_tensors
        return g * y


class HashGrid3D(nn.Module):
    """Multi-resolution hash grid: [N, 3] in [0, 1] -> [N, levels * features], trilinear.

    Level l has resolution floor(base_res * g^l) with g chosen so the last level is max_res.
    Coarse levels whose vertices fit the table in a (2^k)^3 block are indexed densely
    (x | y << k | z << 2k), finer ones through Instant-NGP's spatial hash
    (x * 1) xor (y * 2654435761) xor (z * 805459861) mod table size: both are xor of
    per-axis terms, so one code path serves every level.
    """

    # buffers (registered in __init__; declared here for the type checker)
    res: Tensor  # [L] resolution per level
    mult: Tensor  # [L, 3] int32 per-axis multipliers
    mask: Tensor  # [L] int32 table size - 1 per level
    offset: Tensor  # [L] int64 first row of each level in the table

    def __init__(
        self, levels: int, features: int, log2_size: int, base_res: int, max_res: int
    ) -> None:
        super().__init__()
        g = math.exp((math.log(max_res) - math.log(base_res)) / (levels - 1)) if levels > 1 else 1
        res = [max(1, math.floor(base_res * g**lv + 1e-6)) for lv in range(levels)]
        mult, sizes = [], []
        for r in res:
            k = max(1, math.ceil(math.log2(r + 2)))  # bits per axis: corners 0 .. r + 1
            dense = 3 * k <= log2_size
            mult.append([1, 2**k, 2 ** (2 * k)] if dense else list(_PRIMES))
            sizes.append(2 ** (3 * k) if dense else 2**log2_size)
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32))  # [L]
        self.register_buffer("mult", torch.tensor(mult, dtype=torch.int32))  # [L, 3]
        self.register_buffer("mask", torch.tensor([s - 1 for s in sizes], dtype=torch.int32))
        offsets = [sum(sizes[:i]) for i in range(levels)]
        self.register_buffer("offset", torch.tensor(offsets, dtype=torch.int64))  # [L]
        self.levels, self.features = levels, features
        self.table = nn.Parameter(torch.empty(sum(sizes), features).uniform_(-1e-4, 1e-4))
        self.out_dim = levels * features

    def forward(self, x: Tensor) -> Tensor:
        n, lv = x.shape[0], self.levels
        pos = x.clamp(0.0, 1.0)[:, None, :] * self.res[:, None]  # [N, L, 3]
        lo = pos.floor()
        frac = pos - lo  # [N, L, 3]
        a = lo.to(torch.int32) * self.mult  # [N, L, 3] per-axis hash terms of the low corner
        # per axis, the low and high corner's hash term and trilinear weight, each [N, L]
        tx, ty, tz = zip(a.unbind(-1), (a + self.mult).unbind(-1), strict=True)
        wx, wy, wz = ((1.0 - f, f) for f in frac.unbind(-1))
        # the 8 corners in (z, y, x) order, each an [N, L] term: broadcasting [N, L, 2, 2, 2]
        # products over trailing axes of 2 ran 1.3x slower on one thread (the same values: the
        # same products in the same order, (wx wy) wz)
        corners = [(k, j, i) for k in range(2) for j in range(2) for i in range(2)]
        h = torch.stack([ty[j] ^ tx[i] ^ tz[k] for k, j, i in corners], -1) & self.mask[:, None]
        idx = h.to(torch.int64) + self.offset[:, None]  # [N, L, 8]
        wt = torch.stack([(wx[i] * wy[j]) * wz[k] for k, j, i in corners], -1)  # [N, L, 8]
        feat = gather_rows(self.table, idx.view(-1)).view(n, lv, 8, self.features)
        return (feat * wt[..., None]).sum(dim=2).view(n, self.out_dim)


class FieldOut(NamedTuple):
    """One query's answer for N samples."""

    rgb: Tensor | None  # [N, 3] in [0, 1]; None when no colour was asked (dirs None)
    sigma: Tensor  # [N] density (1/m), finite and >= 0
    logits: Tensor | None  # [N, K] class logits; None without semantics


SigmaFn = Callable[[Tensor], Tensor]  # [N, 3] world points -> [N] density (1/m)
QueryFn = Callable[[Tensor, Tensor | None], FieldOut]  # points [N, 3], dirs [N, 3] | None


@dataclass(frozen=True)
class FieldFns:
    """A field as functions, what the renderer takes (an edit wraps them)."""

    sigma: SigmaFn  # density alone
    query: QueryFn  # colour (when dirs are given), density and logits in one pass


class RadianceField(nn.Module):
    """Field + scene box + occupancy grid + class table + sampling: what a renderer needs.

    `query(x, dirs)` answers colour, density and class logits of a sample batch in one pass;
    `sigma(x)` the density alone. Class logits are over `class_ids` (no semantic head when
    trained without labels).
    """

    # buffers (registered in __init__; declared here for the type checker)
    lo: Tensor  # [3] world corner of the scene box
    hi: Tensor  # [3]
    surface: Tensor  # [] bool: colour rays at their expected depth

    def __init__(
        self,
        cfg: FieldConfig,
        sampling: SamplingConfig,
        lo: Tensor,
        hi: Tensor,
        class_ids: list[int],
        occupancy: OccupancyGrid,
    ) -> None:
        super().__init__()
        if cfg.kind not in FIELDS:
            raise BlunfError(f"nerf.field.kind must be one of {FIELDS}, got {cfg.kind!r}")
        self.cfg = cfg
        self.sampling = sampling
        self.register_buffer("lo", lo.float())  # [3] world corner of the scene box
        self.register_buffer("hi", hi.float())  # [3]
        self.class_ids = list(class_ids)
        self.occupancy = occupancy
        g = cfg.geo_features
        if cfg.kind == "hash":
            self.encoding: nn.Module = HashGrid3D(
                cfg.hash_levels,
                cfg.hash_features,
                cfg.hash_log2_size,
                cfg.hash_base_res,
                max(cfg.hash_max_res, cfg.hash_base_res),
            )
            self.trunk = relu_mlp(int(self.encoding.out_dim), cfg.width, 1, 1 + g)
        else:
            self.encoding = PositionalEncoding(3, cfg.pe_freqs)
            self.trunk = relu_mlp(int(self.encoding.out_dim), cfg.pe_width, cfg.pe_layers, 1 + g)
        # start nearly empty (density ~ 0.05 / m) so the occupancy grid only keeps what is learnt
        last = self.trunk[-1]
        assert isinstance(last, nn.Linear)  # relu_mlp() ends with its output layer
        with torch.no_grad():
            last.bias[0] = -3.0
        self.dir_enc = PositionalEncoding(3, cfg.pe_dir_freqs) if cfg.view_dependent else None
        d_dir = int(self.dir_enc.out_dim) if self.dir_enc is not None else 0
        # colour from a grid of its own: the density's losses (large, sharp gradients at the
        # surfaces) would otherwise drown the colour's in the shared table's Adam statistics
        self.color_encoding: nn.Module | None = None
        d_col = g
        if cfg.color_grid and cfg.kind == "hash":
            self.color_encoding = HashGrid3D(
                cfg.hash_levels,
                cfg.hash_features,
                cfg.hash_log2_size,
                cfg.hash_base_res,
                max(cfg.hash_max_res, cfg.hash_base_res),
            )
            d_col = int(self.color_encoding.out_dim)
        self.color_head = relu_mlp(d_col + d_dir, cfg.width, 1, 3)
        self.sem_head = relu_mlp(g, cfg.width, 1, len(class_ids)) if class_ids else None
        # rendering colours each ray at its expected depth (set when trained with depth)
        self.register_buffer("surface", torch.zeros((), dtype=torch.bool))

    @property
    def surface_color(self) -> bool:
        return bool(self.surface)

    @property
    def step(self) -> float:
        """Ray-marching step in metres (scene box diagonal / samples_across)."""
        return float(torch.linalg.norm(self.hi - self.lo)) / self.sampling.samples_across

    def normalise(self, x: Tensor) -> Tensor:
        """World [N, 3] -> unit cube [N, 3] (hash) or [-1, 1]^3 (pe)."""
        u = (x - self.lo) / (self.hi - self.lo)
        return u if self.cfg.kind == "hash" else 2.0 * u - 1.0

    def _trunk(self, x: Tensor) -> Tensor:
        return self.trunk(self.encoding(self.normalise(x)))  # [N, 1 + G]

    def sigma(self, x: Tensor) -> Tensor:
        """[N, 3] world points -> [N] density (1/m), finite and >= 0."""
        return TruncExp.apply(self._trunk(x)[:, 0])

    def query(self, x: Tensor, dirs: Tensor | None, semantics: bool = True) -> FieldOut:
        """One pass over a sample batch: x [N, 3] world points, dirs [N, 3] unit directions
        (None: no colour) -> colour [N, 3], density [N], logits [N, K] (with `semantics` and
        a semantic head, else None)."""
        h = self._trunk(x)  # [N, 1 + G]
        sigma = TruncExp.apply(h[:, 0])
        rgb = None if dirs is None else self._color(x, dirs, h)
        logits = self.sem_head(h[:, 1:]) if semantics and self.sem_head is not None else None
        return FieldOut(rgb, sigma, logits)

    def color(self, x: Tensor, dirs: Tensor) -> Tensor:
        """[N, 3] world points, [N, 3] unit directions -> [N, 3] RGB in [0, 1]."""
        h = None if self.color_encoding is not None else self._trunk(x)
        return self._color(x, dirs, h)

    def _color(self, x: Tensor, dirs: Tensor, h: Tensor | None) -> Tensor:
        if self.color_encoding is not None:
            geo = self.color_encoding(self.normalise(x))  # [N, E]
        else:
            assert h is not None
            geo = h[:, 1:]  # [N, G]
        if self.dir_enc is not None:
            geo = torch.cat([geo, self.dir_enc(dirs)], dim=-1)
        return torch.sigmoid(self.color_head(geo))

    def logits(self, x: Tensor) -> Tensor:
        """[N, 3] world points -> [N, K] class logits (raises when trained without labels)."""
        if self.sem_head is None:
            raise BlunfError("this NeRF was trained without labels: no semantic head")
        return self.sem_head(self._trunk(x)[:, 1:])

    def fns(self, semantics: bool = True) -> FieldFns:
        """The field as the renderer takes it; `semantics` False: no logits are computed."""

        def query(x: Tensor, dirs: Tensor | None) -> FieldOut:
            return self.query(x, dirs, semantics)

        return FieldFns(self.sigma, query)


def save_field(field: RadianceField, path: Path) -> None:
    """model.pt: state dict, field and sampling settings, class table, occupancy grid shape."""
    torch.save(
        {
            "state_dict": field.state_dict(),
            "field": asdict(field.cfg),
            "sampling": asdict(field.sampling),
            "class_ids": field.class_ids,
            "occ_shape": list(field.occupancy.shape),
        },
        path,
    )


def load_field(path: Path) -> RadianceField:
    """Read model.pt written by `save_field`; returns the field in eval mode."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        cfg = FieldConfig(**ck["field"])
        sampling = SamplingConfig(**ck["sampling"])
        sd = ck["state_dict"]
        occ = OccupancyGrid(sd["occupancy.lo"], sd["occupancy.hi"], tuple(ck["occ_shape"]))
        field = RadianceField(cfg, sampling, sd["lo"], sd["hi"], ck["class_ids"], occ)
        field.load_state_dict(sd)
    except (OSError, RuntimeError, KeyError, TypeError) as e:
        raise BlunfError(f"{path}: not a NeRF model ({e.__class__.__name__}: {e})") from None
    field.eval()
    return field


def field_of(
    density: SigmaFn,
    color: Callable[[Tensor, Tensor], Tensor],
    logits: Callable[[Tensor], Tensor] | None = None,
) -> FieldFns:
    """A field given as separate functions (analytic scenes, tests): each is called once per
    query, density first."""

    def query(x: Tensor, dirs: Tensor | None) -> FieldOut:
        sigma = density(x)
        rgb = None if dirs is None else color(x, dirs)
        return FieldOut(rgb, sigma, None if logits is None else logits(x))

    return FieldFns(density, query)

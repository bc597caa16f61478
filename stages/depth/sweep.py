"""Plane-sweep multi-view stereo: dense depth from posed photos, for the photos-only path.

A NeRF trained on photos and SfM tracks alone (under 2 % of the pixels with depth) learns
its geometry slowly and leaves floaters; with dense depth it converges in a few hundred
steps. This module gives the photos-only path that dense depth, as Roessle et al. ("Dense
Depth Priors for NeRF", 2022) and depth-supervised NeRFs do: each view is matched against
the views that overlap it most, over fronto-parallel planes spaced evenly in inverse depth
(Collins 1996; Gallup et al. 2007), with zero-mean normalised cross-correlation on a
window. The costs of the best half of the neighbours are averaged (occlusion: a surface
hidden in one neighbour is seen in another), the cheapest plane wins, a second sweep of
finer per-pixel hypotheses round it and a parabola through the best one's neighbours refine
it. Readings with a weak match, on flat texture or at the ends of the sweep are dropped;
`consistency.consistent_depth` then keeps only those other views confirm.

Written in torch because nothing in the stack gives it on a CPU: pycolmap's patch-match
stereo needs CUDA, Open3D and kornia have no multi-view stereo.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import Tensor

from stages.common.camera import pixel_grid, unproject
from stages.common.errors import BlunfError
from stages.common.io import gray
from stages.common.progress import track
from stages.common.threads import side_by_side
from stages.depth.config import StereoConfig
from stages.depth.consistency import consistent_depth, overlap_order

log = logging.getLogger(__name__)


def sweep_depths(
    images: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    sparse: list[np.ndarray],
    cfg: StereoConfig,
) -> tuple[list[np.ndarray], dict]:
    """Dense z-depth for every view, checked across views.

    Args:
        images: per view [H, W, 3] float RGB in [0, 1].
        Ks: per view [3, 3] intrinsics. poses: per view [4, 4] camera-to-world.
        sparse: per view [H, W] z-depth of the SfM tracks (0 = none): each view's sweep
            spans the depths its own tracks span (all tracks' when it has too few).
    Returns:
        (per view [H // s, W // s] float32 depth, 0 = no reading, s the sweep's scale
        (`stereo_scale`; its intrinsics: `scaled_K`); facts: fractions kept, scale, planes).
    """
    n = len(images)
    if not n == len(Ks) == len(poses) == len(sparse):
        raise BlunfError("stereo: images, intrinsics, poses and sparse depth differ in number")
    order = overlap_order(sparse, Ks, poses, stride=1, angle=cfg.select_angle)
    everything = np.concatenate([s[s > 0] for s in sparse]) if n else np.zeros(0)
    k = stereo_scale(cfg, Ks, everything)
    grays = [torch.from_numpy(gray(im)) for im in images]
    fine = [_level(g, K, k) for g, K in zip(grays, Ks, strict=True)]
    coarse = [_level(g, K, k * cfg.coarse) for g, K in zip(grays, Ks, strict=True)]
    del grays

    def view(i: int) -> tuple[np.ndarray, int]:
        """View i's depth (0 = none) and the planes it swept (0: not swept)."""
        nbrs = order[i][: cfg.views]
        own = sparse[i][sparse[i] > 0]
        lo, hi = _bounds(own if len(own) >= 20 else everything)
        if not nbrs or not hi > lo > 0:
            return np.zeros(fine[i][0].shape, np.float32), 0
        planes = plane_count(cfg, coarse[i][1], poses, i, nbrs, lo, hi)
        return _sweep(coarse, fine, poses, i, nbrs, lo, hi, replace(cfg, planes=planes)), planes

    # views side by side, one per torch thread (the sweep's ops are many and memory-bound);
    # the same readings, in view order
    done = list(track(side_by_side(view, range(n)), "stereo", total=n, unit="view"))
    raw = [d for d, _ in done]
    swept = [p for _, p in done if p > 0]  # planes of each view's sweep
    matched = sum(int((d > 0).sum()) for d in raw)
    total = sum(d.size for d in raw)
    # agreement only: a stereo reading seen through by a neighbour is that neighbour's
    # occlusion as often as a floater, so the see-through count is not limited
    checked, _ = consistent_depth(
        raw, [K for _, K in fine], poses, cfg.tol, cfg.agree, 10**6, 2 * cfg.views
    )
    facts = {
        "matched": round(matched / max(1, total), 4),
        "kept": round(sum(int((c > 0).sum()) for c in checked) / max(1, total), 4),
        "scale": k,
        "coarse": cfg.coarse,
        "planes": cfg.planes,
        "planes_mean": round(float(np.mean(swept)), 2) if swept else 0.0,
        "views": cfg.views,
    }
    return checked, facts


EDGE_JUMP = 0.1  # a reading this share farther within edge_px pixels: an edge or a steep slope


def near_edge(depth: np.ndarray, px: int) -> np.ndarray:
    """bool [H, W]: the readings of depth [H, W] (0 = none) within px pixels (a square) of a
    reading EDGE_JUMP farther than theirs. At a depth edge these are its near side, where a
    correlation window over the edge matched the nearer surface and carried it out over the
    farther one; on a surface seen so obliquely that its depth grows EDGE_JUMP in px pixels,
    a window spans a wide range of depths and matches none of them well. Kept, both put
    object where there is floor (a rim round every chair and table) and walls a cell off.
    (Continuing each reading's own surface, a plane's inverse depth being affine in the
    pixels, keeps the oblique readings: the 7-Scenes kitchen's plan from its photos then
    gained 0.2 where this gains 2.4, docs/figures.md#depth-stereo-edge-px.)"""
    far = ndimage.maximum_filter(depth, size=2 * px + 1, mode="nearest")
    return (depth > 0) & (far > depth * (1.0 + EDGE_JUMP))


def stereo_scale(cfg: StereoConfig, Ks: list[np.ndarray], z: np.ndarray) -> int:
    """The sweep's resolution divisor: `cfg.scale`, or (0, auto) the largest k at which one
    pixel at the median track depth `z` spans at most `cfg.cell` metres (the plan's cell: a
    finer depth map adds no detail to a plan of that cell), at least 1."""
    if cfg.scale > 0:
        return cfg.scale
    if not len(z) or not Ks:
        return 1
    f = float(np.median([min(K[0, 0], K[1, 1]) for K in Ks]))
    return max(1, int(cfg.cell * f / float(np.median(z))))


def plane_count(
    cfg: StereoConfig,
    K: np.ndarray,
    poses: list[np.ndarray],
    i: int,
    nbrs: list[int],
    lo: float,
    hi: float,
) -> int:
    """Planes of view i's sweep over depths [lo, hi]: `cfg.planes`, or (plane_px > 0) enough
    that one plane step moves a point by at most plane_px pixels (K: the swept level's
    intrinsics) in the neighbour farthest away: its disparity over the range is at most
    focal x baseline x (1/lo - 1/hi). At least 8, at most `cfg.planes`."""
    if cfg.plane_px <= 0 or not nbrs:
        return cfg.planes
    c = np.asarray(poses[i], np.float64)[:3, 3]
    base = max(float(np.linalg.norm(np.asarray(poses[j], np.float64)[:3, 3] - c)) for j in nbrs)
    span = max(float(K[0, 0]), float(K[1, 1])) * base * (1.0 / lo - 1.0 / hi)  # pixels
    return int(min(cfg.planes, max(8, math.ceil(span / cfg.plane_px) + 1)))


def scaled_K(K: np.ndarray, k: int) -> np.ndarray:
    """Intrinsics [3, 3] of an image binned k x k (pixel centres at integers, as
    Intrinsics.scaled: the principal point scales about the corner at (-0.5, -0.5))."""
    out = np.asarray(K, np.float64).copy()
    out[:2, :2] /= k
    out[:2, 2] = (out[:2, 2] + 0.5) / k - 0.5
    return out


def _level(gray: Tensor, K: np.ndarray, k: int) -> tuple[Tensor, np.ndarray]:
    """(gray [H, W] binned k x k (rows and columns beyond whole blocks dropped), its K)."""
    if k <= 1:
        return gray, np.asarray(K, np.float64)
    h, w = gray.shape[0] // k, gray.shape[1] // k
    if h < 1 or w < 1:
        raise BlunfError(f"depth.stereo.scale: {k} leaves no pixel of a {tuple(gray.shape)} image")
    g = F.avg_pool2d(gray[None, None, : h * k, : w * k], k)[0, 0].contiguous()
    return g, scaled_K(K, k)


def _bounds(z: np.ndarray) -> tuple[float, float]:
    """Depth range of a sweep from track depths z [N]: their 2nd-98th percentiles, widened
    (0.7x, 1.3x) for the surfaces no track landed on."""
    if len(z) == 0:
        return 0.0, 0.0
    a, b = np.percentile(z, [2, 98])
    return float(0.7 * a), float(1.3 * b)


class _Level:
    """One view matched against its neighbours at one resolution: cost of depth hypotheses."""

    def __init__(
        self,
        levels: list[tuple[Tensor, np.ndarray]],
        poses: list[np.ndarray],
        i: int,
        nbrs: list[int],
        cfg: StereoConfig,
    ):
        self.ref, K = levels[i]
        h, w = self.ref.shape
        self.shape = (h, w)
        self.window = cfg.window
        uv = pixel_grid(w, h).reshape(-1, 2)
        # [HW, 3] camera-frame rays with z = 1: a point at depth d is d * ray
        rays = torch.from_numpy(unproject(uv, np.ones(len(uv)), K, np.eye(4)))
        self.r_mean, self.r_std = _window_stats(self.ref[None, None], cfg.window)  # [1,1,H,W]
        self.warps = []
        for j in nbrs:
            w2c = np.linalg.inv(np.asarray(poses[j], np.float64))
            rel = torch.from_numpy(w2c @ np.asarray(poses[i], np.float64))  # ref cam -> nbr cam
            a = (rays @ rel[:3, :3].T).float()  # [HW, 3] nbr-camera direction of each ref ray
            kj = torch.from_numpy(np.asarray(levels[j][1], np.float32))
            # the ref pixel at depth d lands at pixel (d ka + kb)[:2] / (d ka + kb)[2] in view j
            self.warps.append((levels[j][0], a @ kj.T, kj @ rel[:3, 3].float()))
        self.k = max(1, math.ceil(len(nbrs) / 2))

    def cost(self, depth: Tensor) -> Tensor:
        """Matching cost [D, H, W] of depth hypotheses [D] (every pixel) or [D, HW]: the
        mean of the best k neighbours' costs (a surface one neighbour cannot see)."""
        c = (
            costs_for(g, ka, kb, depth, self.ref, self.r_mean, self.r_std, self.window)
            for g, ka, kb in self.warps
        )
        return smallest_mean(c, self.k)


def smallest_mean(costs: Iterable[Tensor], k: int) -> Tensor:
    """Elementwise mean of the k smallest of `costs` (tensors of one shape), kept sorted by
    insertion (min / max per element) as they come: a fifth of torch.topk's time over a
    stacked [N, D, H, W] on these few neighbours, and no stack in memory."""
    best: list[Tensor] = []  # ascending, at most k
    for c in costs:
        for j, b in enumerate(best):
            best[j], c = torch.minimum(b, c), torch.maximum(b, c)
        if len(best) < k:
            best.append(c)
    if not best:
        raise BlunfError("stereo: no neighbour cost to average")
    total = best[0]
    for b in best[1:]:
        total = total + b
    return total / len(best)


def _sweep(
    coarse: list[tuple[Tensor, np.ndarray]],
    fine: list[tuple[Tensor, np.ndarray]],
    poses: list[np.ndarray],
    i: int,
    nbrs: list[int],
    lo: float,
    hi: float,
    cfg: StereoConfig,
) -> np.ndarray:
    """One view's depth at the fine level's resolution (0 = no reading) from its neighbours
    `nbrs`: planes over the whole range at the coarse level, then (refine) per-pixel
    hypotheses across one plane step either side at the fine level (coarse to fine)."""
    lc = _Level(coarse, poses, i, nbrs, cfg)
    h, w = lc.shape
    step = (1.0 / hi - 1.0 / lo) / (cfg.planes - 1)  # < 0: near to far
    inv = 1.0 / lo + step * torch.arange(cfg.planes, dtype=torch.float32)  # [D]
    best, pos, arg = _cheapest(lc.cost(1.0 / inv))
    inv_c = 1.0 / lo + pos * step  # [H, W]
    ok = (lc.r_std[0, 0] >= cfg.min_std) & (arg > 0) & (arg < cfg.planes - 1)
    lf = lc
    if cfg.coarse > 1:  # the coarse estimate, block by block, at the fine resolution
        lf = _Level(fine, poses, i, nbrs, cfg)
        h, w = lf.shape
        ok = _blocks(ok, cfg.coarse, (h, w)) & (lf.r_std[0, 0] >= cfg.min_std)
        inv_c = _blocks(inv_c, cfg.coarse, (h, w))
    inv_c = inv_c.reshape(-1)  # [HW]
    if cfg.refine > 1:
        # fine: refine planes per pixel across one coarse step either side of its estimate
        off = torch.linspace(-1.0, 1.0, cfg.refine) * abs(step)  # [F]
        inv_f = (inv_c[None] + off[:, None]).clamp(min=0.5 / hi)  # [F, HW]
        best, pos, _ = _cheapest(lf.cost(1.0 / inv_f))
        inv_c = inv_c - abs(step) + pos.reshape(-1) * (2.0 * abs(step) / (cfg.refine - 1))
    z = (1.0 / inv_c.clamp(min=0.5 / hi)).view(h, w)
    ok &= (best < cfg.max_cost) & torch.isfinite(z)
    return torch.where(ok, z, torch.zeros_like(z)).numpy().astype(np.float32)


def _blocks(x: Tensor, k: int, shape: tuple[int, int]) -> Tensor:
    """x [h, w] with each value repeated over a k x k block, cut or padded (edge values) to
    `shape` (the finer level's size)."""
    up = x.repeat_interleave(k, 0).repeat_interleave(k, 1)[: shape[0], : shape[1]]
    ph, pw = shape[0] - up.shape[0], shape[1] - up.shape[1]
    if ph or pw:
        up = torch.cat([up, up[-1:].expand(ph, -1)], 0) if ph else up
        up = torch.cat([up, up[:, -1:].expand(-1, pw)], 1) if pw else up
    return up


def _cheapest(cost: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per pixel of cost [D, H, W]: (lowest cost, its sub-plane position from a parabola
    through it and its two neighbours, its plane index), each [H, W]."""
    d = cost.shape[0]
    best, arg = cost.min(0)
    ai = arg.clamp(1, d - 2)
    c0 = cost.gather(0, (ai - 1)[None])[0]
    c1 = cost.gather(0, ai[None])[0]
    c2 = cost.gather(0, (ai + 1)[None])[0]
    den = c0 - 2 * c1 + c2
    off = torch.where(den > 1e-6, 0.5 * (c0 - c2) / den.clamp(min=1e-6), torch.zeros_like(den))
    # a minimum at either end stays there (no parabola beyond the range)
    pos = torch.where((arg > 0) & (arg < d - 1), ai + off.clamp(-0.5, 0.5), arg.float())
    return best, pos.float(), arg


def _window_stats(x: Tensor, window: int) -> tuple[Tensor, Tensor]:
    """Mean and standard deviation of x [B, 1, H, W] over each pixel's window (in place where
    it can be: on the sweep's [D, 1, H, W] stacks these ops are memory-bound)."""
    m = _box(x, window)
    var = _box(x * x, window).sub_(m * m).clamp_(min=0.0)
    return m, var.sqrt_()


def _box(x: Tensor, window: int) -> Tensor:
    """Mean over a window x window box at every pixel of x [B, 1, H, W] (edges average what
    lies inside)."""
    h, w = x.shape[2:]
    return _box_sum(x, window).div_(_box_sum(torch.ones(1, 1, h, w, dtype=x.dtype), window))


def _box_sum(x: Tensor, window: int) -> Tensor:
    """Sum over a window x window box at every pixel of x [B, 1, H, W] (zeros beyond the
    edges). Sums over unfolded windows: ~9x faster here than avg_pool2d on these one-channel
    stacks, and faster than running sums (cumsum) at these window sizes."""
    p = window // 2
    t = F.pad(x, (p, p, p, p))
    return t.unfold(3, window, 1).sum(-1).unfold(2, window, 1).sum(-1)


def costs_for(
    gray: Tensor,
    ka: Tensor,
    kb: Tensor,
    depth: Tensor,
    ref: Tensor,
    r_mean: Tensor,
    r_std: Tensor,
    window: int,
) -> Tensor:
    """1 - ZNCC of the reference window against the neighbour `gray` [H', W'] warped by
    every depth hypothesis (depth [D]: the same planes for every pixel; [D, HW]: per pixel):
    the ref pixel at depth d lands at pixel (d ka + kb)[:2] / (d ka + kb)[2] of the neighbour
    (ka [HW, 3], kb [3]). Where the warp leaves the neighbour, the cost is 2 (no match).
    Returns [D, H, W]."""
    h, w = ref.shape
    hn, wn = gray.shape
    n = len(depth)
    d = depth if depth.dim() == 2 else depth[:, None]  # [D, HW | 1]
    # each coordinate as its own [D, HW] (no [D, HW, 3] product), in place where it can be:
    # these ops are memory-bound. One neighbour, 32 planes of 320x240: 82 against 129 ms for
    # the plain expressions; the demo room's stereo 22.5 against 29.8 s
    z = torch.addcmul(kb[2], d, ka[:, 2])  # [D, HW] depth in the neighbour
    front = z > 1e-6
    iz = torch.where(front, z, torch.ones_like(z)).reciprocal_()
    # grid_sample's normalised coordinates (align_corners=True: -1 and 1 are pixel centres)
    grid = torch.empty(n, h * w, 2, dtype=z.dtype)
    for c, size in ((0, wn), (1, hn)):
        torch.mul(torch.addcmul(kb[c], d, ka[:, c]), iz, out=grid[..., c])
        grid[..., c].mul_(2.0 / max(1, size - 1)).sub_(1.0)
    inside = front & (grid.abs().amax(-1) <= 1.0)  # [D, HW]
    src = gray[None, None].expand(n, 1, hn, wn)
    warped = F.grid_sample(
        src, grid.view(n, h, w, 2), mode="bilinear", padding_mode="border", align_corners=True
    )  # [D, 1, H, W]
    s_mean, s_std = _window_stats(warped, window)  # [D, 1, H, W]
    cross = _box(warped * ref, window).sub_(s_mean * r_mean)
    ncc = cross.div_(s_std.mul_(r_std).clamp_(min=1e-4))
    cost = ncc.neg_().add_(1.0).clamp_(0.0, 2.0)[:, 0]  # [D, H, W] = 1 - ZNCC
    seen = _window_inside(inside.view(n, h, w), window)
    return cost.masked_fill_(~seen, 2.0)


def _window_inside(inside: Tensor, window: int) -> Tensor:
    """Per pixel of inside [D, H, W] (bool): whether its whole window (clipped to the image)
    is inside. The pixels a plane warps into the neighbour, and in front of it, form a convex
    set (a homography's preimage of the image rectangle, cut by a half-plane), so the window
    is inside when its four corners are: four shifted copies instead of a windowed sum."""
    p = window // 2
    rows = _shifted(inside, 1, -p) & _shifted(inside, 1, p)
    return _shifted(rows, 2, -p) & _shifted(rows, 2, p)


def _shifted(x: Tensor, dim: int, s: int) -> Tensor:
    """x with index i along `dim` reading index i + s, clamped to the ends."""
    n = x.shape[dim]
    if s == 0:
        return x
    if s > 0:
        body = x.narrow(dim, min(s, n - 1), n - min(s, n - 1))
        edge = x.narrow(dim, n - 1, 1)
        return torch.cat([body, edge.expand_as(x.narrow(dim, 0, min(s, n - 1)))], dim)
    s = min(-s, n - 1)
    body = x.narrow(dim, 0, n - s)
    edge = x.narrow(dim, 0, 1)
    return torch.cat([edge.expand_as(x.narrow(dim, 0, s)), body], dim)

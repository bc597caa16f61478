"""Training: views to rays, the scene box, the optimisation loop and held-out scoring."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import Tensor

from stages.common.camera import depth_to_points
from stages.common.capture import UNKNOWN, Capture, heldout_views
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label
from stages.nerf.config import NerfConfig
from stages.nerf.field import NerfModel
from stages.nerf.occupancy import OccupancyGrid
from stages.nerf.render import RenderOut, camera_rays, render_model

log = logging.getLogger(__name__)

SEED_FACTOR = 10.0  # seeded cells start at this many times the occupancy threshold
SPARSE_DILATE = 2  # sparse depth: cells kept round each SfM track point (at least)
HUBER_DELTA = 0.1
RGB_LOSSES = ("mse", "huber")


@dataclass
class Views:
    """Per-view pixels as flat tensors (row-major, H W of each view)."""

    stems: list[str]
    rgb: list[Tensor]  # [HW, 3] in [0, 1]
    depth: list[Tensor | None]  # [HW] z-depth metres, 0 = missing
    label: list[Tensor | None]  # [HW] class index into class_ids, -1 = ignored
    class_ids: list[int]


def load_views(cap: Capture, use_labels: bool) -> Views:
    """Read images, depth (capture units -> metres) and labels (ids -> contiguous indices)."""
    class_ids = sorted(cap.classes) if (use_labels and cap.has_labels and cap.classes) else []
    lut = np.full(65536, -1, np.int64)
    for i, c in enumerate(class_ids):
        if c != UNKNOWN:
            lut[c] = i
    v = Views([], [], [], [], class_ids)
    for f in cap.frames:
        img = read_image(f.image)
        if img.shape[:2] != (f.intrinsics.height, f.intrinsics.width):
            raise BlunfError(
                f"{f.image}: image is {img.shape[1]}x{img.shape[0]}, intrinsics say "
                f"{f.intrinsics.width}x{f.intrinsics.height}"
            )
        v.stems.append(f.stem)
        v.rgb.append(torch.from_numpy(img.reshape(-1, 3).astype(np.float32) / 255.0))
        d = None
        if f.depth is not None:
            dm = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
            if dm.shape != img.shape[:2]:
                raise BlunfError(f"{f.depth}: depth size {dm.shape} differs from its image")
            d = torch.from_numpy(dm.reshape(-1))
        v.depth.append(d)
        lab = None
        if class_ids and f.label is not None:
            lm = read_label(f.label)
            if lm.shape != img.shape[:2]:
                raise BlunfError(f"{f.label}: label size {lm.shape} differs from its image")
            lab = torch.from_numpy(lut[np.clip(lm, 0, 65535)].reshape(-1))
        v.label.append(lab)
    return v


def split(n: int, every: int) -> tuple[list[int], list[int]]:
    """(training, held-out) view indices: index % every == every // 2 is held out."""
    held = heldout_views(n, every)
    return [i for i in range(n) if i not in held], held


def depth_points(cap: Capture, views: Views, idx: list[int], stride: int) -> np.ndarray:
    """World points [N, 3] of the depth maps of views `idx` at a pixel stride."""
    pts = []
    for i in idx:
        d = views.depth[i]
        if d is None:
            continue
        f = cap.frames[i]
        h, w = f.intrinsics.height, f.intrinsics.width
        p, _ = depth_to_points(d.view(h, w).numpy(), f.intrinsics.K, np.asarray(f.pose), stride)
        pts.append(p)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def scene_box(centers: np.ndarray, points: np.ndarray, cfg: NerfConfig) -> tuple[Tensor, Tensor]:
    """(lo [3], hi [3]): cameras and robust depth-point bounds, padded by aabb_pad."""
    if len(points):
        p_lo, p_hi = np.percentile(points, 0.5, axis=0), np.percentile(points, 99.5, axis=0)
        lo = np.minimum(centers.min(0), p_lo)
        hi = np.maximum(centers.max(0), p_hi)
    else:
        lo = centers.min(0) - cfg.no_depth_margin
        hi = centers.max(0) + cfg.no_depth_margin
    ext = np.maximum(hi - lo, 1e-3)
    lo, hi = lo - cfg.aabb_pad * ext, hi + cfg.aabb_pad * ext
    return torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)


def occupancy_threshold(cfg: NerfConfig, step: float) -> float:
    """Density (1/m) at which one marching step has opacity occ_alpha."""
    return -math.log(1.0 - cfg.occ_alpha) / step


def build_model(
    cfg: NerfConfig,
    lo: Tensor,
    hi: Tensor,
    class_ids: list[int],
    seeds: Iterable[np.ndarray],
    dense: bool = True,
) -> NerfModel:
    """A fresh model whose occupancy grid is seeded from the point sets `seeds` ([N, 3]
    each, e.g. one per depth map). With dense depth the seeded cells are the grid; with
    sparse depth (SfM tracks) the seeded cells are kept and updates add more; with no depth
    at all every cell starts occupied."""
    occ = OccupancyGrid.for_box(lo, hi, cfg.occ_res)
    model = NerfModel(cfg, lo, hi, class_ids, occ)
    thr = occupancy_threshold(cfg, model.step)
    dilate = cfg.occ_dilate
    if not dense:
        # cells round the tracks, for good; updates add the cells the field fills in
        # between (starting from a full grid costs hundreds of samples a ray for minutes)
        dilate = max(dilate, SPARSE_DILATE)
    n_pts = 0
    for pts in seeds:
        occ.seed(torch.from_numpy(pts.astype(np.float32)), SEED_FACTOR * thr, dilate)
        n_pts += len(pts)
    if n_pts:
        n = int(occ.binary.sum())
        log.info("nerf: occupancy %s seeded from %d depth points: %d cells", occ.shape, n_pts, n)
    else:
        occ.fill(SEED_FACTOR * thr)
    return model


def depth_coverage(views: Views, idx: list[int]) -> float:
    """Fraction of the pixels of views `idx` with a depth reading (0 without depth)."""
    n = sum(len(views.rgb[i]) for i in idx)
    k = sum(int((d > 0).sum()) for i in idx if (d := views.depth[i]) is not None)
    return k / max(1, n)


def seed_points(cap: Capture, views: Views, idx: list[int]) -> Iterator[np.ndarray]:
    """World points [N, 3] of every valid depth pixel, one view of `idx` at a time."""
    for i in idx:
        pts = depth_points(cap, views, [i], 1)
        if len(pts):
            yield pts


@dataclass
class Rays:
    """Flat rays of several views, with their targets."""

    origins: Tensor  # [N, 3]
    dirs: Tensor  # [N, 3] unit
    rgb: Tensor  # [N, 3]
    t_depth: Tensor | None  # [N] ray distance of the depth reading, 0 = missing
    label: Tensor | None  # [N] class index, -1 = ignored
    # [N] ray distance at which the ray passes a nearer reading of a neighbouring pixel (a
    # silhouette beside it), 0 = none; see `nearer_neighbour`
    t_edge: Tensor | None = None
    with_depth: Tensor = field(init=False)  # [M] indices of the rays with a depth reading
    edges: Tensor = field(init=False)  # [K] indices of the rays with t_edge > 0

    def __post_init__(self) -> None:
        # found once: SfM tracks cover ~2 % of the pixels, so the depth losses draw from
        # these indices rather than from all pixels (98 % of those draws would be wasted)
        none = torch.empty(0, dtype=torch.long)
        t = self.t_depth
        self.with_depth = none if t is None else (t > 0).nonzero()[:, 0]
        self.edges = none if self.t_edge is None else (self.t_edge > 0).nonzero()[:, 0]


def nearer_neighbour(depth: np.ndarray, radius: int, gap: float) -> np.ndarray:
    """Per pixel, the nearest z-depth within `radius` pixels when it is more than `gap` metres
    nearer than the pixel's own reading, else 0. depth [H, W] metres (0 = missing) -> [H, W].

    Such a pixel lies beside a silhouette: its ray passes the nearer surface at about that
    depth and, the reading says, misses it. A grey erosion (scipy's minimum filter over a
    square window) finds the neighbour; missing readings never count as nearer.
    """
    z = np.where(depth > 0, depth, np.inf).astype(np.float32)
    near = ndimage.minimum_filter(z, size=2 * radius + 1, mode="nearest")
    edge = (depth > 0) & np.isfinite(near) & (near < depth - gap)
    return np.where(edge, near, 0.0).astype(np.float32)


def gather_rays(
    cap: Capture, views: Views, idx: list[int], edge_radius: int = 0, edge_gap: float = 0.1
) -> Rays:
    """All pixels of views `idx` as rays; depth only when every one of them has depth.
    With `edge_radius` > 0 (dense depth), the rays beside a nearer reading get `t_edge`
    (`nearer_neighbour` with that radius and gap)."""
    o: list[Tensor] = []
    d: list[Tensor] = []
    c: list[Tensor] = []
    t: list[Tensor] = []
    te: list[Tensor] = []
    lab: list[Tensor] = []
    with_depth = all(views.depth[i] is not None for i in idx)
    with_label = all(views.label[i] is not None for i in idx) and bool(views.class_ids)
    for i in idx:
        f = cap.frames[i]
        oi, di, zs = camera_rays(np.asarray(f.pose), f.intrinsics)
        o.append(oi)
        d.append(di)
        c.append(views.rgb[i])
        depth_i, label_i = views.depth[i], views.label[i]
        if with_depth:
            assert depth_i is not None  # with_depth: every view of idx has depth
            t.append(depth_i / zs)
            if edge_radius > 0:
                h, w = f.intrinsics.height, f.intrinsics.width
                near = nearer_neighbour(depth_i.numpy().reshape(h, w), edge_radius, edge_gap)
                te.append(torch.from_numpy(near.reshape(-1)) / zs)
        if with_label:
            assert label_i is not None  # with_label: every view of idx has labels
            lab.append(label_i)
    return Rays(
        torch.cat(o),
        torch.cat(d),
        torch.cat(c),
        torch.cat(t) if with_depth else None,
        torch.cat(lab) if with_label else None,
        torch.cat(te) if te else None,
    )


def psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


@torch.no_grad()
def score(model: NerfModel, rays: Rays, chunk: int) -> float:
    """PSNR (dB) of the model on the given rays."""
    err = 0.0
    for i in range(0, len(rays.rgb), chunk):
        out = render_model(
            model, rays.origins[i : i + chunk], rays.dirs[i : i + chunk], semantics=False
        )
        err += float(((out["rgb"] - rays.rgb[i : i + chunk]) ** 2).sum())
    return psnr(err / max(1, rays.rgb.numel()))


def train(
    cfg: NerfConfig, model: NerfModel, rays: Rays, held: Rays | None, dense: bool = True
) -> dict:
    """Optimise the model on `rays`; stop on a held-out plateau, the time budget or max_steps.
    `dense`: the depth covers most pixels (sensor or fused), not just SfM tracks."""
    if cfg.rgb_loss not in RGB_LOSSES:
        raise BlunfError(f"nerf.rgb_loss must be one of {RGB_LOSSES}, got {cfg.rgb_loss!r}")
    gen = torch.Generator().manual_seed(cfg.seed)
    table = [p for n, p in model.named_parameters() if n.endswith("table")]
    rest = [p for n, p in model.named_parameters() if not n.endswith("table")]
    groups = [{"params": rest, "eps": 1e-8}] + ([{"params": table, "eps": 1e-15}] if table else [])
    opt = torch.optim.Adam(groups, lr=cfg.lr, betas=(0.9, 0.99))
    base = [g["lr"] for g in opt.param_groups]
    thr = occupancy_threshold(cfg, model.step)
    if held is not None and cfg.eval_rays > 0 and len(held.rgb) > cfg.eval_rays:
        pick = torch.randperm(len(held.rgb), generator=torch.Generator().manual_seed(cfg.seed))
        pick = pick[: cfg.eval_rays]
        held = Rays(held.origins[pick], held.dirs[pick], held.rgb[pick], None, None)
    curve: list[tuple[float, float]] = []  # (training seconds, held-out PSNR)
    curve_cpu: list[tuple[float, float]] = []  # (training CPU seconds, held-out PSNR)
    best, stale, step, stop = -math.inf, 0, 0, "steps"
    train_s = cpu_s = 0.0
    losses: list[float] = []
    samples = 0
    frozen = dense and rays.t_depth is not None and cfg.occ_seeded_only
    model.surface.fill_(dense and rays.t_depth is not None and cfg.surface_color)
    model.train()
    while True:
        if cfg.max_steps > 0 and step >= cfg.max_steps:
            stop = "steps"
            break
        if cfg.time_budget > 0 and train_s >= cfg.time_budget:
            stop = "time"
            break
        t0, c0 = time.perf_counter(), time.process_time()
        idx = _batch(cfg, rays, gen)
        far, prune = None, True
        if rays.t_depth is not None and cfg.trunc_steps > 0:
            t_d = rays.t_depth[idx]
            far = torch.where(t_d > 0, t_d + cfg.trunc_steps * model.step, torch.inf)
            prune = False
        out = render_model(
            model,
            rays.origins[idx],
            rays.dirs[idx],
            perturb=True,
            gen=gen,
            semantics=rays.label is not None,
            return_samples=True,
            far=far,
            prune=prune,
            surface_color=False,
        )
        loss = _losses(cfg, out, rays, idx, cfg.trunc_steps * model.step)
        model.clear_cache()
        if rays.t_depth is not None and cfg.surface_rays > 0 and cfg.surface_rgb_weight > 0:
            loss = loss + cfg.surface_rgb_weight * _surface_loss(cfg, model, rays, gen)
        if rays.t_depth is not None and cfg.geo_rays > 0 and cfg.geo_weight > 0:
            loss = loss + cfg.geo_weight * _geometry_loss(cfg, model, rays, gen, dense)
        if len(rays.edges) > 0 and cfg.edge_rays > 0 and cfg.geo_weight > 0:
            loss = loss + cfg.geo_weight * _edge_loss(cfg, model, rays, gen)
        opt.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
            opt.step()
        for g, lr in zip(opt.param_groups, base, strict=True):
            g["lr"] = lr * cfg.lr_final ** _progress(cfg, step + 1, train_s)
        step += 1
        samples += len(out["ray"])
        losses.append(float(loss.detach()))
        if step % cfg.occ_every == 0 and not frozen:
            model.occupancy.update(model.density, thr, cfg.occ_decay, cfg.occ_cells, gen)
            model.clear_cache()
        train_s += time.perf_counter() - t0
        cpu_s += time.process_time() - c0
        if held is not None and cfg.eval_every > 0 and step % cfg.eval_every == 0:
            model.eval()
            p = score(model, held, cfg.chunk)
            model.train()
            curve.append((round(train_s, 2), round(p, 3)))
            curve_cpu.append((round(cpu_s, 2), round(p, 3)))
            log.info(
                "nerf: step %d, %.1f s (cpu %.1f s), loss %.4f, held-out PSNR %.2f dB, "
                "%.1f samples / ray, %d occupied cells",
                step,
                train_s,
                cpu_s,
                losses[-1],
                p,
                samples / max(1, step * cfg.batch_rays),
                int(model.occupancy.binary.sum()),
            )
            if p > best + cfg.min_delta:
                best, stale = p, 0
            else:
                stale += 1
                if stale >= cfg.patience:
                    stop = "plateau"
                    break
    model.eval()
    if not frozen:
        before = int(model.occupancy.binary.sum())
        after = model.occupancy.refresh(model.density, thr)
        model.clear_cache()
        log.info("nerf: occupancy refreshed: %d -> %d cells", before, after)
    tail = losses[-50:]
    return {
        "steps": step,
        "seconds": round(train_s, 3),
        "cpu_seconds": round(cpu_s, 3),
        "stop_reason": stop,
        "psnr_curve": curve,
        "psnr_curve_cpu": curve_cpu,
        "final_loss": float(np.mean(tail)) if tail else math.nan,
        "samples_per_ray": round(samples / max(1, step * cfg.batch_rays), 2),
        "occupied_cells": int(model.occupancy.binary.sum()),
    }


def _progress(cfg: NerfConfig, step: int, seconds: float) -> float:
    """How far training is, in [0, 1]: by the step limit or the time budget when set (the
    nearer one), else by lr_decay_steps. The learning rate decays with it."""
    fr = [step / cfg.max_steps] if cfg.max_steps > 0 else []
    fr += [seconds / cfg.time_budget] if cfg.time_budget > 0 else []
    return min(1.0, max(fr) if fr else step / max(1, cfg.lr_decay_steps))


def _batch(cfg: NerfConfig, rays: Rays, gen: torch.Generator) -> Tensor:
    """The marched rays of one step: batch_rays pixels, edge_batch of them (rounded) drawn
    among the rays beside a silhouette when there are such rays, the rest among all."""
    k = round(cfg.edge_batch * cfg.batch_rays) if len(rays.edges) > 0 else 0
    idx = torch.randint(0, len(rays.rgb), (cfg.batch_rays - k,), generator=gen)
    if k == 0:
        return idx
    pick = rays.edges[torch.randint(0, len(rays.edges), (k,), generator=gen)]
    return torch.cat([idx, pick])


def _depth_pixels(rays: Rays, n: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Up to n random training pixels among those with a depth reading (never more than
    there are: SfM tracks may give fewer readings than n): (index [M], ray distance of the
    reading [M]); none when no pixel has one."""
    assert rays.t_depth is not None
    pool = rays.with_depth
    if len(pool) == 0:
        return pool, rays.t_depth[pool]
    idx = pool[torch.randint(0, len(pool), (min(n, len(pool)),), generator=gen)]
    return idx, rays.t_depth[idx]


def _surface_loss(cfg: NerfConfig, model: NerfModel, rays: Rays, gen: torch.Generator) -> Tensor:
    """Colour of random pixels with depth, fitted at their depth point (jittered along the
    ray): one field query per pixel teaches the texture far faster than marching does."""
    idx, t = _depth_pixels(rays, cfg.surface_rays, gen)
    if len(idx) == 0:
        return torch.zeros(())
    jit = (torch.rand(len(idx), generator=gen) * 2.0 - 1.0) * cfg.surface_jitter * model.step
    x = rays.origins[idx] + (t + jit)[:, None] * rays.dirs[idx]
    model.clear_cache()
    c = model.color(x, rays.dirs[idx])
    model.clear_cache()
    return F.mse_loss(c, rays.rgb[idx])


def _geometry_loss(
    cfg: NerfConfig, model: NerfModel, rays: Rays, gen: torch.Generator, dense: bool = True
) -> Tensor:
    """Density fitted directly from depth readings: one step's opacity is 0 at a point drawn
    in the geo_front metres (sparse depth: anywhere) in front of the reading (up to half a
    step before it) and 1 at a point drawn in the two steps behind it. Binary cross-entropy
    on that opacity, written with terms of sigma * step so it stays finite for any density."""
    idx, t = _depth_pixels(rays, cfg.geo_rays, gen)
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
    model.clear_cache()
    sd = model.density(o + tt[:, None] * d) * s  # [2M] optical depth of one step
    model.clear_cache()
    m = len(idx)
    # free: -log(1 - alpha) = sd; full: -log(alpha) = -log(1 - exp(-sd))
    free = sd[:m].mean()
    # clamped far below any density the field can reach (exp(-15) * step), not at 1e-6: a
    # clamp there would zero the gradient that revives a region the field emptied
    full = -torch.log(-torch.expm1(-sd[m:].clamp(min=1e-30))).mean()
    return free + full


def _edge_loss(cfg: NerfConfig, model: NerfModel, rays: Rays, gen: torch.Generator) -> Tensor:
    """Silhouettes: a ray beside a nearer surface is empty where it passes that surface.

    Up to edge_rays rays with `t_edge` are drawn; each gets a free point within a step of
    t_edge (never within edge_gap / 2 of its own reading) whose one-step optical depth is
    pushed to 0, as `_geometry_loss` does for its free points. The density that blurs an
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
    model.clear_cache()
    sd = model.density(rays.origins[idx] + t[:, None] * rays.dirs[idx]) * s  # [K]
    model.clear_cache()
    return sd.mean()


def _losses(cfg: NerfConfig, out: RenderOut, rays: Rays, idx: Tensor, margin: float) -> Tensor:
    """RGB (+ depth L1 where valid, + semantic cross-entropy) loss of one batch."""
    target = rays.rgb[idx]
    if cfg.rgb_loss == "mse":
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

"""The optimisation loop: batches, losses, learning rate, occupancy updates, held-out stops."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch
from torch import Tensor

from stages.common.errors import BlunfError
from stages.common.progress import progress
from stages.common.radiance.config import TrainConfig, TrainingConfig
from stages.common.radiance.evaluate import score
from stages.common.radiance.field import RadianceField
from stages.common.radiance.losses import (
    RGB_LOSSES,
    edge_loss,
    geometry_loss,
    render_loss,
    surface_loss,
)
from stages.common.radiance.render import FieldRender, render_field
from stages.common.radiance.scene import occupancy_threshold
from stages.common.radiance.views import Rays
from stages.common.threads import torch_threads

log = logging.getLogger(__name__)


def train(
    cfg: TrainingConfig, model: RadianceField, rays: Rays, held: Rays | None, dense: bool = True
) -> dict:
    """Optimise the model on `rays`; stop on a held-out plateau, the time budget (once past
    min_steps) or max_steps. Torch computes with train.threads threads meanwhile (the same
    count whatever the machine's load: the weights depend on it).
    `dense`: the depth covers most pixels (sensor or fused), not just SfM tracks."""
    with torch_threads(cfg.train.threads):
        return _train(cfg, model, rays, held, dense)


def _train(
    cfg: TrainingConfig, model: RadianceField, rays: Rays, held: Rays | None, dense: bool
) -> dict:
    if cfg.losses.rgb not in RGB_LOSSES:
        raise BlunfError(f"nerf.losses.rgb must be one of {RGB_LOSSES}, got {cfg.losses.rgb!r}")
    tc, lc, oc = cfg.train, cfg.losses, cfg.occupancy
    gen = torch.Generator().manual_seed(cfg.seed)
    table = [p for n, p in model.named_parameters() if n.endswith("table")]
    rest = [p for n, p in model.named_parameters() if not n.endswith("table")]
    groups = [{"params": rest, "eps": 1e-8}] + ([{"params": table, "eps": 1e-15}] if table else [])
    opt = torch.optim.Adam(groups, lr=tc.lr, betas=(0.9, 0.99))
    base = [g["lr"] for g in opt.param_groups]
    thr = occupancy_threshold(cfg, model.step)
    if held is not None and tc.eval_rays > 0 and len(held.rgb) > tc.eval_rays:
        pick = torch.randperm(len(held.rgb), generator=torch.Generator().manual_seed(cfg.seed))
        pick = pick[: tc.eval_rays]
        t_held = None if held.t_depth is None else held.t_depth[pick]
        held = Rays(held.origins[pick], held.dirs[pick], held.rgb[pick], t_held, None)
    curve: list[tuple[float, float]] = []  # (training seconds, held-out PSNR)
    curve_cpu: list[tuple[float, float]] = []  # (training CPU seconds, held-out PSNR)
    best, stale, step, stop = -math.inf, 0, 0, "steps"
    last: tuple[int, float, float | None] | None = None  # (step, PSNR, AbsRel) of the last score
    train_s = cpu_s = 0.0
    losses: list[float] = []
    samples = 0
    frozen = dense and rays.t_depth is not None and oc.seeded_only
    model.surface.fill_(dense and rays.t_depth is not None and tc.surface_color)
    model.train()
    fns = model.fns(semantics=rays.label is not None)
    bar = progress("nerf", tc.max_steps or tc.time_budget or None, "step" if tc.max_steps else "s")
    while True:
        if tc.max_steps > 0 and step >= tc.max_steps:
            stop = "steps"
            break
        if tc.time_budget > 0 and train_s >= tc.time_budget and step >= tc.min_steps:
            stop = "time"
            log.warning(
                "nerf: the time budget (train.time_budget %.0f s) stopped training at step "
                "%d of %s: the result depends on the machine's load",
                tc.time_budget,
                step,
                tc.max_steps or "no step limit",
            )
            break
        t0, c0 = time.perf_counter(), time.process_time()
        idx = _batch(tc, rays, gen)
        far, prune = None, True
        if rays.t_depth is not None and lc.trunc_steps > 0:
            t_d = rays.t_depth[idx]
            far = torch.where(t_d > 0, t_d + lc.trunc_steps * model.step, torch.inf)
            prune = False
        how = FieldRender(far=far, perturb=True, gen=gen, prune=prune, return_samples=True,
                          surface_color=False)  # fmt: skip
        out = render_field(model, rays.origins[idx], rays.dirs[idx], fns, how)
        loss = render_loss(lc, out, rays, idx, lc.trunc_steps * model.step)
        if rays.t_depth is not None and lc.surface_rays > 0 and lc.surface_rgb_weight > 0:
            loss = loss + lc.surface_rgb_weight * surface_loss(lc, model, rays, gen)
        if rays.t_depth is not None and lc.geo_rays > 0 and lc.geo_weight > 0:
            loss = loss + lc.geo_weight * geometry_loss(lc, model, rays, gen, dense)
        if len(rays.edges) > 0 and lc.edge_rays > 0 and lc.geo_weight > 0:
            loss = loss + lc.geo_weight * edge_loss(lc, model, rays, gen)
        opt.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
            opt.step()
        for g, lr in zip(opt.param_groups, base, strict=True):
            g["lr"] = lr * tc.lr_final ** _progress(tc, step + 1, train_s)
        step += 1
        samples += len(out["ray"])
        losses.append(float(loss.detach()))
        if step % oc.every == 0 and not frozen:
            model.occupancy.update(model.sigma, thr, oc.decay, oc.cells, gen)
        train_s += time.perf_counter() - t0
        cpu_s += time.process_time() - c0
        bar.moveto(step if tc.max_steps > 0 else train_s, step=step)
        if held is not None and tc.eval_every > 0 and step % tc.eval_every == 0:
            model.eval()
            p, rel = score(model, held, cfg.chunk)
            last = (step, p, rel)
            model.train()
            curve.append((round(train_s, 2), round(p, 3)))
            curve_cpu.append((round(cpu_s, 2), round(p, 3)))
            bar.update(0, psnr=round(p, 2))
            log.info(
                "nerf: step %d, %.1f s (cpu %.1f s), loss %.4f, held-out PSNR %.2f dB, "
                "%.1f samples / ray, %d occupied cells",
                step,
                train_s,
                cpu_s,
                losses[-1],
                p,
                samples / max(1, step * tc.batch_rays),
                int(model.occupancy.binary.sum()),
            )
            if p > best + tc.min_delta:
                best, stale = p, 0
            else:
                stale += 1
                if stale >= tc.patience:
                    stop = "plateau"
                    break
    bar.close()
    model.eval()
    if not frozen:
        before = int(model.occupancy.binary.sum())
        after = model.occupancy.refresh(model.sigma, thr)
        log.info("nerf: occupancy refreshed: %d -> %d cells", before, after)
    fresh = last is not None and last[0] == step and frozen  # the model scored as it is now
    if held is not None and tc.heldout_score == "rays" and not fresh:
        last, fresh = (step, *score(model, held, cfg.chunk)), True  # the final score, once
    tail = losses[-50:]
    return {
        "steps": step,
        "seconds": round(train_s, 3),
        "cpu_seconds": round(cpu_s, 3),
        "stop_reason": stop,
        "psnr_curve": curve,
        "psnr_curve_cpu": curve_cpu,
        "final_loss": float(np.mean(tail)) if tail else math.nan,
        "samples_per_ray": round(samples / max(1, step * tc.batch_rays), 2),
        "occupied_cells": int(model.occupancy.binary.sum()),
        # the held-out score on the eval_rays pixels of the final model (None: not taken)
        "heldout_rays": _scored(last, len(held.rgb)) if fresh and held is not None else None,
    }


def _scored(last: tuple[int, float, float | None] | None, rays: int) -> dict | None:
    """A held-out score on rays as nerf.json keeps it."""
    if last is None:
        return None
    rel = None if last[2] is None else round(last[2], 4)
    return {"rays": rays, "psnr": round(last[1], 3), "depth_absrel": rel}


def _progress(cfg: TrainConfig, step: int, seconds: float) -> float:
    """How far training is, in [0, 1]: by the step limit or the time budget when set (the
    nearer one), else by lr_decay_steps. The learning rate decays with it."""
    fr = [step / cfg.max_steps] if cfg.max_steps > 0 else []
    fr += [seconds / cfg.time_budget] if cfg.time_budget > 0 else []
    return min(1.0, max(fr) if fr else step / max(1, cfg.lr_decay_steps))


def _batch(cfg: TrainConfig, rays: Rays, gen: torch.Generator) -> Tensor:
    """The marched rays of one step: batch_rays pixels, edge_batch of them (rounded) drawn
    among the rays beside a silhouette when there are such rays, the rest among all."""
    k = round(cfg.edge_batch * cfg.batch_rays) if len(rays.edges) > 0 else 0
    idx = torch.randint(0, len(rays.rgb), (cfg.batch_rays - k,), generator=gen)
    if k == 0:
        return idx
    pick = rays.edges[torch.randint(0, len(rays.edges), (k,), generator=gen)]
    return torch.cat([idx, pick])

"""NeRF stage, occupancy-grid implementation: train the field, score it, render depth.

Outputs model.pt (load_model), nerf.json (stats), heldout/<stem>.png renders and frames.json.
With sparse depth (photos only: SfM tracks) plane-sweep stereo first gives the training views
dense depth (stereo/<stem>.npy; stereo.py), then every view's depth is rendered into
depth/<stem>.npy (z-depth, float32 metres, 0 where the opacity is below acc_threshold) and
frames.json points at those renders: the photos-only depth path. With dense depth frames.json
is the input capture unchanged.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import write_depth_npy, write_image, write_json
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs
from stages.nerf.consistency import consistent_depth
from stages.nerf.field import NerfModel, save_model
from stages.nerf.render import render_view
from stages.nerf.stereo import SweepConfig, sweep_depths
from stages.nerf.train import (
    Views,
    build_model,
    depth_coverage,
    depth_points,
    gather_rays,
    load_views,
    psnr,
    scene_box,
    seed_points,
    split,
    train,
)

log = logging.getLogger(__name__)


def run(cfg: NerfConfig, inputs: NerfInputs, out: Path) -> NerfOutputs:
    """Train on the capture's posed frames; write the model, stats and rendered depth."""
    log.debug("nerf/grid: %s", cfg)  # the full config: meta.json
    out = Path(out)
    cap = Capture.load(inputs.frames)
    if not cap.frames:
        raise BlunfError(f"{inputs.frames}: no frames")
    if not cap.has_poses:
        raise BlunfError(f"{inputs.frames}: the NeRF needs a pose for every frame")
    t_start = time.perf_counter()
    old_threads = torch.get_num_threads()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    try:
        torch.manual_seed(cfg.seed)
        views = load_views(cap, cfg.semantics)
        tr, held = split(len(cap.frames), cfg.holdout_every)
        coverage = depth_coverage(views, tr)
        photos_only = coverage < cfg.dense_depth  # the capture's depth is SfM tracks at most
        log.info(
            "nerf: depth on %.1f %% of training pixels (%s)",
            100 * coverage,
            "sparse" if photos_only else "dense",
        )
        stereo: dict | None = None
        swept: dict[int, np.ndarray] = {}  # view index -> checked stereo depth [H, W]
        if photos_only and cfg.stereo and views.depth[tr[0]] is not None:
            stereo, swept = _stereo_depth(cap, views, tr, cfg)
        dense = depth_coverage(views, tr) >= cfg.dense_depth  # trains as with dense depth
        pts = depth_points(cap, views, tr, cfg.depth_stride if dense else 1)
        lo, hi = scene_box(cap.poses()[:, :3, 3], pts, cfg)
        model = build_model(cfg, lo, hi, views.class_ids, seed_points(cap, views, tr), dense=dense)
        edge = cfg.edge_radius if dense and (cfg.edge_rays > 0 or cfg.edge_batch > 0) else 0
        rays = gather_rays(cap, views, tr, edge, cfg.edge_gap)
        held_rays = gather_rays(cap, views, held) if held else None
        stats = train(cfg, model, rays, held_rays, dense=dense)
        t_render = time.perf_counter()
        outs = NerfOutputs.at(out)
        outs.depth.mkdir()
        (out / "heldout").mkdir()
        # depth is rendered for every view only when the input depth is sparse (photos only:
        # fusion needs it); with dense depth only the held-out views are rendered, for scores
        frames, psnrs, absrels = list(cap.frames), [], []
        if swept:  # kept for inspection: stereo/<stem>.npy, z-depth metres, 0 = none
            (out / "stereo").mkdir()
            for i, d in swept.items():
                write_depth_npy(out / "stereo" / f"{frames[i].stem}.npy", d)
        if photos_only:  # depth for fusion, at 1 / depth_render_scale of the resolution
            prior = swept if cfg.stereo_fuse else {}
            # too few stereo readings to train as with dense depth are too few to confirm the
            # render by: it is then fused unchecked
            check = cfg.stereo_check if dense else 0
            frames, checks = _write_depths(model, frames, cfg, outs.depth, prior, check)
            stats.update(checks)
        for i in held:
            f = frames[i]
            v = render_view(model, np.asarray(f.pose), f.intrinsics, cfg.chunk)
            depth = np.where(v["acc"] >= cfg.acc_threshold, v["depth"], 0.0)
            gt = views.rgb[i].view(v["rgb"].shape).numpy()
            psnrs.append(psnr(float(np.mean((v["rgb"] - gt) ** 2))))
            write_image(out / "heldout" / f"{f.stem}.png", np.round(v["rgb"] * 255))
            d_gt = views.depth[i]
            if d_gt is not None and not photos_only:  # sensor / fused depth is the reference
                absrels.append(depth_absrel(depth, d_gt.view(depth.shape).numpy()))
    finally:
        torch.set_num_threads(old_threads)
    save_model(model, outs.model)
    if not photos_only:
        cap.with_frames(frames).save(outs.frames)  # the input depth stays the depth
    else:
        replace(cap.with_frames(frames), depth_scale=1.0, depth_invalid=()).save(outs.frames)
    stats.update(
        {
            "field": cfg.field,
            "views": len(cap.frames),
            "train_views": len(tr),
            "heldout_views": len(held),
            "psnr_heldout": round(float(np.mean(psnrs)), 3) if psnrs else None,
            "depth_absrel": round(float(np.mean(absrels)), 4) if absrels else None,
            "depth_supervised": rays.t_depth is not None,
            "depth_coverage": round(coverage, 4),
            "depth_dense": not photos_only,
            "stereo": stereo,
            "semantics": bool(views.class_ids) and rays.label is not None,
            "box": [lo.tolist(), hi.tolist()],
            "occupancy_shape": list(model.occupancy.shape),
            "step_m": round(model.step, 5),
            "render_seconds": round(time.perf_counter() - t_render, 3),
            "total_seconds": round(time.perf_counter() - t_start, 3),
        }
    )
    write_json(outs.stats, stats)
    log.info(
        "nerf/grid: %d steps in %.1f s (%s), held-out PSNR %s dB, depth AbsRel %s",
        stats["steps"],
        stats["seconds"],
        stats["stop_reason"],
        stats["psnr_heldout"],
        stats["depth_absrel"],
    )
    return outs


def _stereo_depth(
    cap: Capture, views: Views, idx: list[int], cfg: NerfConfig
) -> tuple[dict, dict[int, np.ndarray]]:
    """Plane-sweep stereo among the training views `idx` (held-out views stay unseen): each
    gets the sweep's checked depth, its SfM track depth where the sweep has none. Changes
    views.depth in place; returns the sweep's facts and {view index: its stereo depth}."""
    t0 = time.perf_counter()
    frames = [cap.frames[i] for i in idx]
    hw = [(f.intrinsics.height, f.intrinsics.width) for f in frames]
    sparse = [views.depth[i].view(s).numpy() for i, s in zip(idx, hw, strict=True)]  # type: ignore[union-attr]
    images = [views.rgb[i].view(*s, 3).numpy() for i, s in zip(idx, hw, strict=True)]
    sweep = SweepConfig(
        planes=cfg.stereo_planes,
        refine=cfg.stereo_refine,
        neighbours=cfg.stereo_views,
        window=cfg.stereo_window,
        max_cost=cfg.stereo_max_cost,
        min_std=cfg.stereo_min_std,
        tol=cfg.stereo_tol,
        agree=cfg.stereo_agree,
    )
    depths, facts = sweep_depths(
        images,
        [f.intrinsics.K for f in frames],
        [np.asarray(f.pose) for f in frames],
        sparse,
        sweep,
    )
    for i, d, sp in zip(idx, depths, sparse, strict=True):
        views.depth[i] = torch.from_numpy(np.where(d > 0, d, sp).astype(np.float32).reshape(-1))
    facts["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "nerf: stereo depth on %.1f %% of training pixels (%.1f %% matched) in %.1f s",
        100 * facts["kept"],
        100 * facts["matched"],
        facts["seconds"],
    )
    return facts, dict(zip(idx, depths, strict=True))


def _write_depths(
    model: NerfModel,
    frames: list[Frame],
    cfg: NerfConfig,
    folder: Path,
    prior: dict[int, np.ndarray] | None = None,
    stereo_check: int = 0,
) -> tuple[list[Frame], dict]:
    """Render every frame's depth and write folder/<stem>.npy for fusion.

    View i's `prior` (its stereo readings, full resolution, 0 = none) is taken where it has
    a reading, at full resolution, the render (upsampled) elsewhere. With stereo_check > 0
    the rendered readings are kept only where at least that many other views' stereo
    readings agree with them (within stereo_tol) and none sees through them: the field's
    depth fills the stereo's holes where the photos confirm it (held-out views, which are
    never swept, get the checked render alone). With depth_check every reading is then
    checked against the other views' depth. Returns (the frames pointing at those files,
    facts: fractions of the rendered readings kept by each check, None when it did not run).
    """
    prior = prior or {}
    k = max(1, cfg.depth_render_scale)
    # a swept view's render is needed only where a block of its pixels lacks stereo
    need = {i: _block_any(p <= 0, k) for i, p in prior.items()}
    depths = [render_depth(model, f, cfg, need.get(i)) for i, f in enumerate(frames)]
    facts: dict = {
        "depth_check_kept": None,
        "stereo_check_kept": None,
        "rendered": round(
            sum(d.size if i not in need else int(need[i].sum()) for i, d in enumerate(depths))
            / max(1, sum(d.size for d in depths)),
            4,
        ),
    }
    full = {i: upsample_depth(depths[i], p.shape) for i, p in prior.items()}
    cands = [
        np.where(prior[i] > 0, 0.0, full[i]) if i in prior else d for i, d in enumerate(depths)
    ]
    if prior and stereo_check > 0:
        idx = sorted(prior)
        refs = (
            [prior[i] for i in idx],
            [_k_at(frames[i], prior[i]) for i in idx],
            [np.asarray(frames[i].pose, np.float64) for i in idx],
        )
        cands, kept = consistent_depth(
            cands,
            [_k_at(f, d) for f, d in zip(frames, cands, strict=True)],
            [np.asarray(f.pose, np.float64) for f in frames],
            cfg.stereo_tol,
            stereo_check,
            0,
            cfg.depth_check_views,
            refs=refs,
        )
        facts["stereo_check_kept"] = round(kept, 4)
        log.info("nerf: %.1f %% of the rendered depth readings confirmed by stereo", 100 * kept)
    depths = [
        np.where(prior[i] > 0, prior[i], c).astype(np.float32) if i in prior else c
        for i, c in enumerate(cands)
    ]
    if cfg.depth_check:
        depths, kept = consistent_depth(
            depths,
            [_k_at(f, d) for f, d in zip(frames, depths, strict=True)],
            [np.asarray(f.pose, np.float64) for f in frames],
            cfg.depth_check_tol,
            cfg.depth_check_agree,
            cfg.depth_check_through,
            cfg.depth_check_views,
        )
        facts["depth_check_kept"] = round(kept, 4)
        log.info("nerf: %.1f %% of the rendered depth readings confirmed by others", 100 * kept)
    out = []
    for f, d in zip(frames, depths, strict=True):
        path = folder / f"{f.stem}.npy"
        write_depth_npy(path, d)
        out.append(replace(f, depth=path))
    return out, facts


def _k_at(f: Frame, depth: np.ndarray) -> np.ndarray:
    """Frame f's [3, 3] intrinsics at the resolution of `depth`."""
    return f.intrinsics.scaled(depth.shape[1], depth.shape[0]).K


def upsample_depth(depth: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """depth [H // k, W // k] rendered at 1/k (Intrinsics.scaled: a small pixel's centre is
    its k x k block's centre) to `shape` = (H, W): each block takes its small pixel's value;
    rows and columns beyond the whole blocks repeat the last ones."""
    h, w = shape
    k = h // depth.shape[0]
    if k < 1 or w // depth.shape[1] != k:
        raise BlunfError(f"depth of {depth.shape} does not scale to {shape} by whole blocks")
    up = np.repeat(np.repeat(depth, k, axis=0), k, axis=1)
    return np.pad(up, ((0, h - up.shape[0]), (0, w - up.shape[1])), mode="edge")


def _block_any(mask: np.ndarray, k: int) -> np.ndarray:
    """mask [H, W] at 1/k (render_depth's pixels, each a k x k block; rows and columns
    beyond the whole blocks belong to the last): whether any pixel of a block is set."""
    h, w = max(1, mask.shape[0] // k), max(1, mask.shape[1] // k)
    rows = np.minimum(np.arange(mask.shape[0]) // k, h - 1)
    cols = np.minimum(np.arange(mask.shape[1]) // k, w - 1)
    out = np.zeros((h, w), bool)
    np.logical_or.at(out, (rows[:, None], cols[None, :]), mask)
    return out


def render_depth(
    model: NerfModel, f: Frame, cfg: NerfConfig, pixels: np.ndarray | None = None
) -> np.ndarray:
    """z-depth (metres, float32) of frame f at 1 / depth_render_scale of its resolution; 0
    where the opacity is below acc_threshold (fusion rescales the intrinsics to fit) and,
    given `pixels` (bool, at that resolution), where it is False (not rendered)."""
    k = max(1, cfg.depth_render_scale)
    w, h = f.intrinsics.width, f.intrinsics.height
    intr = f.intrinsics.scaled(max(1, w // k), max(1, h // k))
    v = render_view(model, np.asarray(f.pose), intr, cfg.chunk, color=False, pixels=pixels)
    return np.where(v["acc"] >= cfg.acc_threshold, v["depth"], 0.0).astype(np.float32)


def depth_absrel(pred: np.ndarray, gt: np.ndarray) -> float:
    """Median of |d - d*| / d* over pixels with valid ground truth (missing pred counts 1)."""
    ok = gt > 0
    if not ok.any():
        return float("nan")
    return float(np.median(np.abs(pred[ok] - gt[ok]) / gt[ok]))

"""NeRF stage, occupancy-grid implementation: train the field, score it, render depth.

Outputs model.pt (load_model), nerf.json (stats), heldout/<stem>.png renders and frames.json.
With sparse depth (photos only: SfM tracks) every view's depth is rendered into
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
from stages.nerf.train import (
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
    log.info("nerf/grid: %s", cfg)
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
        dense = coverage >= cfg.dense_depth
        log.info(
            "nerf: depth on %.1f %% of training pixels (%s)",
            100 * coverage,
            "dense" if dense else "sparse",
        )
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
        if not dense:  # depth for fusion, at 1 / depth_render_scale of the resolution
            frames, stats["depth_check_kept"] = _write_depths(model, frames, cfg, outs.depth)
        for i in held:
            f = frames[i]
            v = render_view(model, np.asarray(f.pose), f.intrinsics, cfg.chunk)
            depth = np.where(v["acc"] >= cfg.acc_threshold, v["depth"], 0.0)
            gt = views.rgb[i].view(v["rgb"].shape).numpy()
            psnrs.append(psnr(float(np.mean((v["rgb"] - gt) ** 2))))
            write_image(out / "heldout" / f"{f.stem}.png", np.round(v["rgb"] * 255))
            d_gt = views.depth[i]
            if d_gt is not None and dense:  # sensor / fused depth is the reference
                absrels.append(depth_absrel(depth, d_gt.view(depth.shape).numpy()))
    finally:
        torch.set_num_threads(old_threads)
    save_model(model, outs.model)
    if dense:
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
            "depth_dense": dense,
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


def _write_depths(
    model: NerfModel, frames: list[Frame], cfg: NerfConfig, folder: Path
) -> tuple[list[Frame], float | None]:
    """Render every frame's depth, drop the readings other views do not confirm (when
    depth_check), write folder/<stem>.npy. Returns (the frames pointing at those files, the
    fraction of readings kept or None without the check)."""
    depths = [render_depth(model, f, cfg) for f in frames]
    kept = None
    if cfg.depth_check:
        ks = [
            f.intrinsics.scaled(d.shape[1], d.shape[0]).K
            for f, d in zip(frames, depths, strict=True)
        ]
        poses = [np.asarray(f.pose, np.float64) for f in frames]
        depths, kept = consistent_depth(
            depths,
            ks,
            poses,
            cfg.depth_check_tol,
            cfg.depth_check_agree,
            cfg.depth_check_through,
            cfg.depth_check_views,
        )
        log.info("nerf: %.1f %% of the rendered depth readings confirmed by others", 100 * kept)
    out = []
    for f, d in zip(frames, depths, strict=True):
        path = folder / f"{f.stem}.npy"
        write_depth_npy(path, d)
        out.append(replace(f, depth=path))
    return out, None if kept is None else round(kept, 4)


def render_depth(model: NerfModel, f: Frame, cfg: NerfConfig) -> np.ndarray:
    """z-depth (metres, float32) of frame f at 1 / depth_render_scale of its resolution; 0
    where the opacity is below acc_threshold (fusion rescales the intrinsics to fit)."""
    k = max(1, cfg.depth_render_scale)
    w, h = f.intrinsics.width, f.intrinsics.height
    intr = f.intrinsics.scaled(max(1, w // k), max(1, h // k))
    v = render_view(model, np.asarray(f.pose), intr, cfg.chunk)
    return np.where(v["acc"] >= cfg.acc_threshold, v["depth"], 0.0).astype(np.float32)


def depth_absrel(pred: np.ndarray, gt: np.ndarray) -> float:
    """Median of |d - d*| / d* over pixels with valid ground truth (missing pred counts 1)."""
    ok = gt > 0
    if not ok.any():
        return float("nan")
    return float(np.median(np.abs(pred[ok] - gt[ok]) / gt[ok]))

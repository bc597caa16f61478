"""NeRF stage, occupancy-grid implementation: train the field, score it, render every depth.

Outputs model.pt (load_model), nerf.json (stats), depth/<stem>.png for every view (rendered
z-depth, uint16 mm, 0 where the opacity is below acc_threshold) and frames.json: the input
capture whose frames' depth points at those renders (the photos-only depth path).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import write_depth_png, write_image, write_json
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs
from stages.nerf.field import save_model
from stages.nerf.render import render_view
from stages.nerf.train import (
    build_model,
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
        pts = depth_points(cap, views, tr, cfg.depth_stride)
        lo, hi = scene_box(cap.poses()[:, :3, 3], pts, cfg)
        model = build_model(cfg, lo, hi, views.class_ids, seed_points(cap, views, tr))
        rays = gather_rays(cap, views, tr)
        held_rays = gather_rays(cap, views, held) if held else None
        stats = train(cfg, model, rays, held_rays)
        t_render = time.perf_counter()
        outs = NerfOutputs.at(out)
        outs.depth.mkdir()
        (out / "heldout").mkdir()
        frames, psnrs, psnrs_train, absrels = [], [], [], []
        for i, f in enumerate(cap.frames):
            v = render_view(model, np.asarray(f.pose), f.intrinsics, cfg.chunk)
            depth = np.where(v["acc"] >= cfg.acc_threshold, v["depth"], 0.0)  # type: ignore[operator]
            write_depth_png(outs.depth / f"{f.stem}.png", depth)
            frames.append(replace(f, depth=outs.depth / f"{f.stem}.png"))
            gt = views.rgb[i].view(v["rgb"].shape).numpy()  # type: ignore[union-attr]
            (psnrs if i in held else psnrs_train).append(psnr(float(np.mean((v["rgb"] - gt) ** 2))))
            if i in held:
                rgb = v["rgb"]
                write_image(out / "heldout" / f"{f.stem}.png", np.round(rgb * 255))  # type: ignore[operator]
                d_gt = views.depth[i]
                if d_gt is not None:
                    absrels.append(depth_absrel(depth, d_gt.view(depth.shape).numpy()))
    finally:
        torch.set_num_threads(old_threads)
    save_model(model, outs.model)
    replace(cap.with_frames(frames), depth_scale=1000.0, depth_invalid=(65535,)).save(outs.frames)
    stats.update(
        {
            "field": cfg.field,
            "views": len(cap.frames),
            "train_views": len(tr),
            "heldout_views": len(held),
            "psnr_heldout": round(float(np.mean(psnrs)), 3) if psnrs else None,
            "psnr_train": round(float(np.mean(psnrs_train)), 3) if psnrs_train else None,
            "depth_absrel": round(float(np.mean(absrels)), 4) if absrels else None,
            "depth_supervised": rays.t_depth is not None,
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


def depth_absrel(pred: np.ndarray, gt: np.ndarray) -> float:
    """Median of |d - d*| / d* over pixels with valid ground truth (missing pred counts 1)."""
    ok = gt > 0
    if not ok.any():
        return float("nan")
    return float(np.median(np.abs(pred[ok] - gt[ok]) / gt[ok]))

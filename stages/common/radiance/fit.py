"""Train a radiance field on a capture's views and score it on the views held out of it.

Shared by the nerf stage (the field for edits and the NeRF top view) and the depth stage's
field fill (a field whose render fills the holes of the photos-only depth). The caller loads
and splits the views (views.py) and decides whether their depth counts as dense; this builds
the scene box and the model, trains (train.py), renders the held-out views into
out/heldout/<stem>.png (train.heldout_score "views"; "rays" scores a fixed subset of their
pixels instead and renders none) and returns the model with its stats.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from stages.common.capture import Capture
from stages.common.io import write_image
from stages.common.progress import track
from stages.common.radiance.config import TrainingConfig
from stages.common.radiance.evaluate import depth_absrel, psnr
from stages.common.radiance.field import RadianceField
from stages.common.radiance.render import render_view
from stages.common.radiance.scene import build_model, scene_box
from stages.common.radiance.train import train
from stages.common.radiance.views import Views, depth_points, gather_rays, seed_points
from stages.common.threads import side_by_side


def fit_field(
    cfg: TrainingConfig,
    cap: Capture,
    views: Views,
    split: tuple[list[int], list[int]],
    out: Path,
    dense: bool,
    stride: int,
    score_depth: bool,
) -> tuple[RadianceField, dict]:
    """Train on the views `split[0]`, score on `split[1]` (held out). `dense`: the views'
    depth covers most pixels (trains as with a sensor); `stride`: the pixel stride of the
    depth points bounding the scene box; `score_depth`: the held-out views' depth is a
    reference (sensor or fused), scored as depth_absrel. Returns (model, stats)."""
    tr, held = split
    t0 = time.perf_counter()
    pts = depth_points(cap, views, tr, stride)
    lo, hi = scene_box(cap.poses()[:, :3, 3], pts, cfg)
    model = build_model(cfg, lo, hi, views.class_ids, seed_points(cap, views, tr), dense=dense)
    lc = cfg.losses
    edge = lc.edge_radius if dense and (lc.edge_rays > 0 or cfg.train.edge_batch > 0) else 0
    rays = gather_rays(cap, views, tr, edge, lc.edge_gap)
    held_rays = gather_rays(cap, views, held) if held else None
    stats = train(cfg, model, rays, held_rays, dense=dense)
    t_render = time.perf_counter()
    (out / "heldout").mkdir(exist_ok=True)
    frames = cap.frames

    def held_view(i: int):
        return render_view(model, np.asarray(frames[i].pose), frames[i].intrinsics, cfg.chunk)

    shown = held if cfg.train.heldout_score == "views" else []  # rays: scored in train
    psnrs, absrels = [], []
    rendered = side_by_side(held_view, shown)
    for i, v in zip(shown, track(rendered, "nerf held-out", len(shown), "view"), strict=True):
        depth = np.where(v["acc"] >= cfg.sampling.acc_threshold, v["depth"], 0.0)
        gt = views.rgb[i].view(v["rgb"].shape).numpy()
        psnrs.append(psnr(float(np.mean((v["rgb"] - gt) ** 2))))
        write_image(out / "heldout" / f"{frames[i].stem}.png", np.round(v["rgb"] * 255))
        d_gt = views.depth[i]
        if d_gt is not None and score_depth:
            absrels.append(depth_absrel(depth, d_gt.view(depth.shape).numpy()))
    stats.update(
        {
            "field": cfg.field.kind,
            "views": len(frames),
            "train_views": len(tr),
            "heldout_views": len(held),
            "psnr_heldout": round(float(np.mean(psnrs)), 3) if psnrs else None,
            "depth_absrel": round(float(np.mean(absrels)), 4) if absrels else None,
            "heldout_scored_on": "views" if psnrs else None,
            "depth_supervised": rays.t_depth is not None,
            "semantics": bool(views.class_ids) and rays.label is not None,
            "box": [lo.tolist(), hi.tolist()],
            "occupancy_shape": list(model.occupancy.shape),
            "step_m": round(model.step, 5),
            "render_seconds": round(time.perf_counter() - t_render, 3),
            "fit_seconds": round(time.perf_counter() - t0, 3),
        }
    )
    if cfg.train.heldout_score == "rays" and stats["heldout_rays"] is not None:
        on = stats["heldout_rays"]
        stats["psnr_heldout"] = on["psnr"]
        stats["depth_absrel"] = on["depth_absrel"] if score_depth else None
        stats["heldout_scored_on"] = f"{on['rays']} rays"
    return model, stats

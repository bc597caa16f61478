"""NeRF stage, occupancy-grid implementation: train the field, score it, render depth.

Outputs model.pt (`stages.common.radiance.field.load_field`), nerf.json (stats),
heldout/<stem>.png renders (train.heldout_score "views"; "rays" scores a fixed subset of the
held-out pixels instead and renders none) and frames.json.
With sparse depth (photos only: SfM tracks) plane-sweep stereo first gives the training views
dense depth (stereo/<stem>.npy; stereo.py), then every view's depth is rendered into
depth/<stem>.npy (z-depth, float32 metres, 0 where the opacity is below acc_threshold:
sampling.acc_threshold) and
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

from stages.common.capture import Capture
from stages.common.io import write_depth_npy, write_image, write_json
from stages.common.progress import track
from stages.common.radiance.field import save_field
from stages.common.radiance.render import render_view
from stages.common.threads import side_by_side, torch_threads
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs
from stages.nerf.depths import upsample_depth, write_depths
from stages.nerf.evaluate import depth_absrel, psnr
from stages.nerf.scene import build_model, scene_box
from stages.nerf.stereo import sweep_depths
from stages.nerf.train import train
from stages.nerf.views import (
    Views,
    binned,
    depth_coverage,
    depth_points,
    gather_rays,
    load_views,
    seed_points,
    split,
)

log = logging.getLogger(__name__)


def run(cfg: NerfConfig, inputs: NerfInputs, out: Path) -> NerfOutputs:
    """Train on the capture's posed frames; write the model, stats and rendered depth."""
    log.debug("nerf/grid: %s", cfg)  # the full config: meta.json
    return fit(cfg, Capture.load_posed(inputs.frames, "the NeRF"), Path(out))


def fit(
    cfg: NerfConfig,
    cap: Capture,
    out: Path,
    swept: dict[int, np.ndarray] | None = None,
    swept_scale: int = 1,
) -> NerfOutputs:
    """Train on `cap`'s posed frames into `out`. `swept` ({view index: stereo depth}, from
    the stereo implementation's sweep of every view) stands for this stage's own sweep of
    the training views when the capture's depth is sparse; `swept_scale` is the resolution
    divisor that sweep ran at (its stereo.json `scale`). A field that fills a sweep's holes
    trains and renders at that sweep's resolution (views.binned): the fill is no finer than
    the sweep, and the 7-Scenes kitchen (100 views of 640x480 swept at 1/5) trained on 27
    million full-resolution rays, 1.1 GB of them, of which its 120 s drew 160 thousand."""
    t_start = time.perf_counter()
    with torch_threads(cfg.threads):
        torch.manual_seed(cfg.seed)
        views = load_views(cap, cfg.semantics)
        tr, held = split(len(cap.frames), cfg.train.holdout_every)
        coverage = depth_coverage(views, tr)
        photos_only = coverage < cfg.train.dense_depth  # the capture's depth is SfM tracks at most
        log.info(
            "nerf: depth on %.1f %% of training pixels (%s)",
            100 * coverage,
            "sparse" if photos_only else "dense",
        )
        stereo: dict | None = None  # swept: view index -> checked stereo depth [H, W]
        full = cap  # the frames written out: the capture's own, whatever the field trains at
        binned_by = 1  # the views were binned to the sweep's resolution by this
        if photos_only and swept is not None:
            stereo = {"swept_by": "stereo"}  # its facts: the stereo implementation's
            if swept_scale > 1:
                cap, views = binned(cap, views, swept_scale)
                binned_by, swept_scale = swept_scale, 1
            swept = _take_depth(cap, views, {i: swept[i] for i in tr})
        elif photos_only and cfg.stereo.enabled and views.depth[tr[0]] is not None:
            stereo, swept = _stereo_depth(cap, views, tr, cfg)
            swept_scale = int(stereo.get("scale", 1))
        else:
            swept = {}
        dense = depth_coverage(views, tr) >= cfg.train.dense_depth  # trains as with dense depth
        # the box's bounds are percentiles: a pixel stride keeps them (dense depth), and a
        # sweep's depth upsampled from 1/k repeats each reading over k x k pixels (the
        # 7-Scenes kitchen's 88 swept views: 9.9 million points, 3 s of percentiles, at k = 1)
        stride = cfg.box.depth_stride if dense else swept_scale if swept else 1
        pts = depth_points(cap, views, tr, stride)
        lo, hi = scene_box(cap.poses()[:, :3, 3], pts, cfg)
        model = build_model(cfg, lo, hi, views.class_ids, seed_points(cap, views, tr), dense=dense)
        lc = cfg.losses
        edge = lc.edge_radius if dense and (lc.edge_rays > 0 or cfg.train.edge_batch > 0) else 0
        rays = gather_rays(cap, views, tr, edge, lc.edge_gap)
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
            prior = swept if cfg.stereo.fuse else {}
            # too few stereo readings to train as with dense depth are too few to confirm the
            # render by: it is then fused unchecked
            check = cfg.stereo.check if dense else 0
            # the render fills stereo's holes no finer than stereo itself ran: stereo.scale 0
            # picks the coarsest resolution whose pixel still covers the plan's cell (the
            # 7-Scenes kitchen at 640x480: 1/5), and a finer fill adds nothing the plan keeps
            k = max(cfg.depth_render_scale, swept_scale if prior else 1)
            k = -(-k // binned_by)  # at the binned resolution: no finer than the sweep
            frames, checks = write_depths(
                model, frames, replace(cfg, depth_render_scale=k), outs.depth, prior, check
            )
            stats.update(checks, depth_render_scale=k * binned_by)

        def held_view(i: int):
            return render_view(model, np.asarray(frames[i].pose), frames[i].intrinsics, cfg.chunk)

        shown = held if cfg.train.heldout_score == "views" else []  # rays: scored in train
        rendered = side_by_side(held_view, shown)
        for i, v in zip(shown, track(rendered, "nerf held-out", len(shown), "view"), strict=True):
            f = frames[i]
            depth = np.where(v["acc"] >= cfg.sampling.acc_threshold, v["depth"], 0.0)
            gt = views.rgb[i].view(v["rgb"].shape).numpy()
            psnrs.append(psnr(float(np.mean((v["rgb"] - gt) ** 2))))
            write_image(out / "heldout" / f"{f.stem}.png", np.round(v["rgb"] * 255))
            d_gt = views.depth[i]
            if d_gt is not None and not photos_only:  # sensor / fused depth is the reference
                absrels.append(depth_absrel(depth, d_gt.view(depth.shape).numpy()))
    save_field(model, outs.model)
    if not photos_only:
        cap.with_frames(frames).save(outs.frames)  # the input depth stays the depth
    else:  # the capture's frames (their images and intrinsics) with the depth written
        frames = [replace(f, depth=d.depth) for f, d in zip(full.frames, frames, strict=True)]
        replace(full.with_frames(frames), depth_scale=1.0, depth_invalid=()).save(outs.frames)
    stats.update(
        {
            "field": cfg.field.kind,
            "views": len(cap.frames),
            "train_views": len(tr),
            "heldout_views": len(held),
            "psnr_heldout": round(float(np.mean(psnrs)), 3) if psnrs else None,
            "depth_absrel": round(float(np.mean(absrels)), 4) if absrels else None,
            "heldout_scored_on": "views" if psnrs else None,
            "depth_supervised": rays.t_depth is not None,
            "depth_coverage": round(coverage, 4),
            "depth_dense": not photos_only,
            "stereo": stereo,
            "semantics": bool(views.class_ids) and rays.label is not None,
            "box": [lo.tolist(), hi.tolist()],
            "occupancy_shape": list(model.occupancy.shape),
            "train_scale": binned_by,  # trained on the views binned by this (views.binned)
            "step_m": round(model.step, 5),
            "render_seconds": round(time.perf_counter() - t_render, 3),
            "total_seconds": round(time.perf_counter() - t_start, 3),
        }
    )
    if cfg.train.heldout_score == "rays" and stats["heldout_rays"] is not None:
        on = stats["heldout_rays"]
        stats["psnr_heldout"] = on["psnr"]
        stats["depth_absrel"] = None if photos_only else on["depth_absrel"]
        stats["heldout_scored_on"] = f"{on['rays']} rays"
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
    depths, facts = sweep_depths(
        images,
        [f.intrinsics.K for f in frames],
        [np.asarray(f.pose) for f in frames],
        sparse,
        cfg.stereo,
    )
    swept = _take_depth(cap, views, dict(zip(idx, depths, strict=True)))
    facts["seconds"] = round(time.perf_counter() - t0, 3)
    log.info(
        "nerf: stereo depth on %.1f %% of training pixels (%.1f %% matched) in %.1f s",
        100 * facts["kept"],
        100 * facts["matched"],
        facts["seconds"],
    )
    return facts, swept


def _take_depth(cap: Capture, views: Views, swept: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Each swept view's depth becomes its stereo depth where it has one (upsampled to the
    view's pixels: the field trains on every pixel), its SfM track depth elsewhere. Returns
    the stereo depths at the views' pixels."""
    out = {}
    for i, d in swept.items():
        k = cap.frames[i].intrinsics
        hw = (k.height, k.width)
        full = d if d.shape == hw else upsample_depth(d, hw)
        sp = views.depth[i].view(hw).numpy()  # type: ignore[union-attr]
        depth = np.where(full > 0, full, sp).astype(np.float32)
        views.depth[i] = torch.from_numpy(depth.reshape(-1))
        out[i] = full
    return out

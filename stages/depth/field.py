"""The depth stage's field fill: a radiance field trained on the photos and the depth found so
far (stereo, planes; the SfM tracks where they found none), whose render fills the holes
where the other views' readings confirm it.

The field is the nerf stage's (stages.common.radiance). It trains and renders at the sweep's
resolution (views.binned): the fill is no finer than the sweep, and the 7-Scenes kitchen
(100 views of 640x480 swept at 1/5) trained on 27 million full-resolution rays, 1.1 GB of
them, of which a 120 s budget drew 160 thousand. Without a sweep (depth.stereo off, or no
SfM tracks) it learns depth from the photos (and the tracks) alone and every view's render
is its depth. The field, its stats and held-out renders go to field/ (model.pt, nerf.json).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from stages.common.capture import Capture
from stages.common.io import write_json
from stages.common.radiance.field import save_field
from stages.common.radiance.fit import fit_field
from stages.common.radiance.views import Views, binned, depth_coverage, load_views, split
from stages.depth.config import DepthConfig
from stages.depth.render import upsample_depth, write_depths

log = logging.getLogger(__name__)


def fill(
    cfg: DepthConfig,
    cap: Capture,
    out: Path,
    found: dict[int, np.ndarray] | None,
    found_scale: int = 1,
) -> tuple[list[np.ndarray], dict]:
    """Train the field on `cap`'s views into `out` (field/) and fill the holes of `found`
    ({view index: depth found so far at 1/found_scale of the photos, 0 = none}; None: no
    sweep ran). Returns (every view's depth at the resolution written, the field's stats:
    its nerf.json)."""
    fc = cfg.field
    t_start = time.perf_counter()
    out.mkdir(exist_ok=True)
    torch.manual_seed(fc.seed)
    views = load_views(cap, fc.semantics)
    tr, held = split(len(cap.frames), fc.train.holdout_every)
    binned_by = 1
    prior: dict[int, np.ndarray] = {}
    if found is not None:
        if found_scale > 1:
            cap, views = binned(cap, views, found_scale)
            binned_by = found_scale
        # the training views learn from their found depth; every view keeps it for fusion
        # (the held-out views too: the field is scored on them, their readings stay theirs)
        prior = _take_depth(cap, views, found, tr)
    coverage = depth_coverage(views, tr)
    dense = coverage >= fc.train.dense_depth  # trains as with dense depth
    # the box's bounds are percentiles: a found depth upsampled from 1/k repeats each
    # reading over k x k pixels
    stride = fc.box.depth_stride if dense else 1
    model, stats = fit_field(fc, cap, views, (tr, held), out, dense, stride, False)
    save_field(model, out / "model.pt")
    if not cfg.stereo.fuse:
        prior = {}
    # too few readings to train as with dense depth are too few to confirm the render by:
    # it is then fused unchecked
    check = fc.check if dense and prior else 0
    k = -(-max(fc.render_scale, 1) // binned_by)  # at the binned resolution
    (out / "depth").mkdir()
    _, checks, depths = write_depths(
        model,
        list(cap.frames),
        replace(fc, render_scale=k),
        out / "depth",
        prior,
        check,
        cfg.stereo.tol,
        cfg.check,
    )
    stats.update(
        checks,
        depth_render_scale=k * binned_by,
        depth_coverage=round(coverage, 4),
        depth_dense=dense,
        train_scale=binned_by,  # trained on the views binned by this (views.binned)
        total_seconds=round(time.perf_counter() - t_start, 3),
    )
    write_json(out / "nerf.json", stats)
    log.info(
        "depth/field: %d steps in %.1f s (%s), held-out PSNR %s dB",
        stats["steps"],
        stats["seconds"],
        stats["stop_reason"],
        stats["psnr_heldout"],
    )
    return depths, stats


def _take_depth(
    cap: Capture, views: Views, found: dict[int, np.ndarray], train: list[int]
) -> dict[int, np.ndarray]:
    """Each training view's depth becomes its found depth where it has one (upsampled to the
    view's pixels: the field trains on every pixel), its SfM track depth elsewhere. Returns
    every view's found depth at the views' pixels."""
    out = {}
    train_set = set(train)
    for i, d in found.items():
        k = cap.frames[i].intrinsics
        hw = (k.height, k.width)
        full = d if d.shape == hw else upsample_depth(d, hw)
        out[i] = full
        if i not in train_set:
            continue
        sp = views.depth[i].view(hw).numpy()  # type: ignore[union-attr]
        depth = np.where(full > 0, full, sp).astype(np.float32)
        views.depth[i] = torch.from_numpy(depth.reshape(-1))
    return out

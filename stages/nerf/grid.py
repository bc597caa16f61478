"""NeRF stage, occupancy-grid implementation: train the field for edits and the NeRF top view.

Outputs model.pt (`stages.common.radiance.field.load_field`), nerf.json (stats),
heldout/<stem>.png renders (train.heldout_score "views"; "rays" scores a fixed subset of the
held-out pixels instead and renders none) and frames.json (the input capture unchanged).
The field trains on the depth its frames carry: in a run, the fused depth (dense). Depth for
fusion from the photos alone is the depth stage's (stages/depth), whose field fill trains the
same field (stages.common.radiance.fit).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import torch

from stages.common.capture import Capture
from stages.common.io import write_json
from stages.common.radiance.field import save_field
from stages.common.radiance.fit import fit_field
from stages.common.radiance.views import depth_coverage, load_views, split
from stages.common.threads import torch_threads
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs

log = logging.getLogger(__name__)


def run(cfg: NerfConfig, inputs: NerfInputs, out: Path) -> NerfOutputs:
    """Train on the capture's posed frames; write the model, stats and frames."""
    log.debug("nerf/grid: %s", cfg)  # the full config: meta.json
    out = Path(out)
    t_start = time.perf_counter()
    cap = Capture.load_posed(inputs.frames, "the NeRF")
    with torch_threads(cfg.threads):
        torch.manual_seed(cfg.seed)
        views = load_views(cap, cfg.semantics)
        tr, held = split(len(cap.frames), cfg.train.holdout_every)
        coverage = depth_coverage(views, tr)
        dense = coverage >= cfg.train.dense_depth
        log.info(
            "nerf: depth on %.1f %% of training pixels (%s)",
            100 * coverage,
            "dense" if dense else "sparse",
        )
        stride = cfg.box.depth_stride if dense else 1
        model, stats = fit_field(cfg, cap, views, (tr, held), out, dense, stride, dense)
    outs = NerfOutputs.at(out)
    outs.depth.mkdir()
    save_field(model, outs.model)
    cap.save(outs.frames)  # the input depth stays the depth
    stats.update(
        {
            "depth_coverage": round(coverage, 4),
            "depth_dense": dense,
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

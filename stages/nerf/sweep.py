"""NeRF stage, stereo-only implementation: depth for fusion from plane-sweep stereo among
the photos, without training a field.

The photos-only path's depth. Training the field on the stereo depth and filling stereo's
holes with its render (`grid`) moved the demo room's plan by under half a point of fwIoU
for most of the run's time, so the planner picks this implementation when nothing else
needs a field (no edits, no NeRF top view, `nerf.stereo.field_fill` off). Every view is
swept (no view is held out: there is no field to score) and its checked readings written to
depth/<stem>.npy (z-depth, float32 metres, 0 = none, at the sweep's resolution: fusion
rescales the intrinsics to fit); frames.json points at them. stereo.json holds the facts.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_json, write_depth_npy, write_json
from stages.common.threads import torch_threads
from stages.nerf.config import NerfConfig, NerfInputs, StereoConfig, StereoOutputs
from stages.nerf.grid import fit
from stages.nerf.stereo import sweep_depths

log = logging.getLogger(__name__)


def run(cfg: NerfConfig, inputs: NerfInputs, out: Path) -> StereoOutputs:
    """Sweep every posed frame against its neighbours; write the checked depth maps."""
    log.debug("nerf/stereo: %s", cfg)  # the full config: meta.json
    out = Path(out)
    cap = Capture.load_posed(inputs.frames, "stereo")
    t0 = time.perf_counter()
    images, sparse = [], []
    for f in cap.frames:
        img = read_image(f.image)
        h, w = f.intrinsics.height, f.intrinsics.width
        if img.shape[:2] != (h, w):
            raise BlunfError(
                f"{f.image}: image is {img.shape[1]}x{img.shape[0]}, intrinsics say {w}x{h}"
            )
        images.append(img.astype(np.float32) / 255.0)
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid) if f.depth else None
        sparse.append(d if d is not None else np.zeros((h, w), np.float32))
    if not any((s > 0).any() for s in sparse):
        raise BlunfError(
            f"{inputs.frames}: no SfM track depth to bound the stereo sweep "
            "(give depth, or poses.impl=sfm)"
        )
    with torch_threads(cfg.threads):
        depths, facts = sweep_depths(
            images,
            [f.intrinsics.K for f in cap.frames],
            [np.asarray(f.pose) for f in cap.frames],
            sparse,
            cfg.stereo,
        )
    outs = StereoOutputs.at(out)
    outs.depth.mkdir()
    frames = []
    for f, d in zip(cap.frames, depths, strict=True):
        path = outs.depth / f"{f.stem}.npy"
        write_depth_npy(path, d)
        frames.append(replace(f, depth=path))
    facts["frames"] = len(frames)
    facts["sweep_seconds"] = round(time.perf_counter() - t0, 3)
    st = cfg.stereo
    fill = field_fill_needed(st, facts["kept"])
    facts["field_fill"] = fill
    log.info(
        "nerf/stereo: depth on %.1f %% of the pixels (%.1f %% matched) in %.1f s; %s",
        100 * facts["kept"],
        100 * facts["matched"],
        facts["sweep_seconds"],
        fill,
    )
    if fill.startswith("field"):  # fit() keeps the stereo readings and renders the rest
        (out / "field").mkdir()
        step = replace(cfg.sampling, samples_across=st.fill_samples_across)
        fill_cfg = replace(cfg, sampling=step)
        field = fit(fill_cfg, cap, out / "field", dict(enumerate(depths)), facts["scale"])
        facts["field"] = read_json(field.stats)
        Capture.load(field.frames).save(outs.frames)
    else:
        replace(cap.with_frames(frames), depth_scale=1.0, depth_invalid=()).save(outs.frames)
    facts["seconds"] = round(time.perf_counter() - t0, 3)
    write_json(outs.stats, facts)
    return outs


def field_fill_needed(st: StereoConfig, kept: float) -> str:
    """Whether the field trains to fill stereo's holes, and why (a line for the log and the
    report): always with field_fill true, never with false; with "auto" when stereo gave
    depth to fewer than field_fill_below of the pixels."""
    if st.field_fill is True:
        return "field trained to fill the rest (nerf.stereo.field_fill)"
    if st.field_fill is False:
        return "no field trained (nerf.stereo.field_fill off)"
    if kept < st.field_fill_below:
        return (
            f"field trained to fill the rest: stereo covers {100 * kept:.0f} % of the pixels, "
            f"under nerf.stereo.field_fill_below {100 * st.field_fill_below:.0f} %"
        )
    return (
        f"no field trained: stereo covers {100 * kept:.0f} % of the pixels "
        f"(nerf.stereo.field_fill_below {100 * st.field_fill_below:.0f} %)"
    )

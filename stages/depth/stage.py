"""The depth stage's driver: depth for fusion from the photos alone, part after part.

1. sweep (sweep.py): plane-sweep stereo of every posed view against its neighbours, its
   readings checked across views (consistency.py), at the sweep's resolution;
2. planes: where stereo read nothing, the room's planes (see the marked place in `run`);
3. field (field.py): when the readings so far cover too little of the views
   (`depth.field.fill` auto, under `depth.field.below`; true: always; false: never) a
   radiance field trains on them and its render fills the holes other views confirm;
   without a sweep (the `field` implementation) the field's render is the depth.

Writes depth/<stem>.npy (z-depth, float32 metres, 0 = none; fusion rescales the intrinsics
to fit), sources/<stem>.png (uint8, same size: 0 none, 1 stereo, 2 planes, 3 field),
frames.json pointing at the depth maps, and depth.json: each part's CPU seconds and the
share of the pixels with depth after it, by source.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, write_depth_npy, write_image, write_json
from stages.common.threads import torch_threads
from stages.depth.config import (
    FIELD,
    NONE,
    SOURCES,
    STEREO,
    DepthConfig,
    DepthInputs,
    DepthOutputs,
    FieldFillConfig,
)
from stages.depth.field import fill as field_fill
from stages.depth.planes import PlanesConfig
from stages.depth.planes.filling import fill as plane_fill
from stages.depth.render import upsample_depth
from stages.depth.sweep import near_edge, sweep_depths

log = logging.getLogger(__name__)


def run_stereo(cfg: DepthConfig, inputs: DepthInputs, out: Path) -> DepthOutputs:
    """Sweep, planes, then the field fill where needed."""
    return _run(cfg, inputs, Path(out), sweep=True)


def run_field(cfg: DepthConfig, inputs: DepthInputs, out: Path) -> DepthOutputs:
    """The field fill alone: no stereo (depth.stereo off) or no SfM tracks to bound it."""
    return _run(cfg, inputs, Path(out), sweep=False)


def _run(cfg: DepthConfig, inputs: DepthInputs, out: Path, sweep: bool) -> DepthOutputs:
    log.debug("depth: %s", cfg)  # the full config: meta.json
    cap = Capture.load_posed(inputs.frames, "depth")
    t0 = time.perf_counter()
    images, sparse = _load(cap)
    Ks = [f.intrinsics.K for f in cap.frames]
    poses = [np.asarray(f.pose) for f in cap.frames]  # camera-to-world, the aligned world
    facts: dict = {"frames": len(cap.frames), "parts": {}}
    parts = facts["parts"]
    depths: list[np.ndarray] | None = None
    sources: list[np.ndarray] | None = None
    with torch_threads(cfg.threads):
        if sweep:
            if not any((s > 0).any() for s in sparse):
                raise BlunfError(
                    f"{inputs.frames}: no SfM track depth to bound the stereo sweep "
                    "(give depth, or poses.impl=sfm)"
                )
            c0 = time.process_time()
            depths, swept = sweep_depths(images, Ks, poses, sparse, cfg.stereo)
            facts.update(swept)  # kept, matched, scale, planes...: the sweep's facts
            facts["sweep_seconds"] = round(time.perf_counter() - t0, 3)
            sources = [np.where(d > 0, STEREO, NONE).astype(np.uint8) for d in depths]
            parts["sweep"] = _part(sources, time.process_time() - c0)
            log.info(
                "depth/sweep: depth on %.1f %% of the pixels (%.1f %% matched) in %.1f s",
                100 * facts["kept"],
                100 * facts["matched"],
                facts["sweep_seconds"],
            )

            # planes: where stereo read nothing, the room's own planes (planes/); its facts
            # go under "plane_fill" ("planes" is the sweep's plane count)
            c0 = time.process_time()
            need = cfg.planes.enabled and facts["kept"] < cfg.planes.below
            reason = _planes_reason(cfg.planes, facts["kept"])
            if need:
                depths, sources, pf = plane_fill(
                    images, Ks, poses, sparse, depths, cfg.planes, cfg.threads
                )
                facts["plane_fill"] = pf
                need, reason = pf["ran"], pf.get("reason", reason)  # max_dropped may undo it
                if need:
                    reason += (
                        f"; the multi-view check dropped {100 * pf['fills_dropped_by_check']:.0f}"
                        f" % of its fills (depth.planes.max_dropped "
                        f"{100 * cfg.planes.max_dropped:.0f} %)"
                    )
                    if pf["planes_undone"]:
                        n_off, n_all = len(pf["planes_undone"]), len(pf["planes"])
                        reason += f" after {n_off} of its {n_all} planes, over it, gave none"
            facts["plane_fill_reason"] = reason
            log.info("depth: %s", reason)
            parts["planes"] = _part(sources, time.process_time() - c0, ran=need)

            # stereo's readings on the near side of a depth edge (depth.stereo.edge_px), here
            # after the plane fill: its planes' offsets read every checked reading (without
            # the oblique ones the honest room's walls moved 1-2 cm), and a reading carried
            # out over a plane-filled floor is as much the near side of an edge
            if cfg.stereo.edge_px > 0:
                c0 = time.process_time()
                depths, sources, dropped = _near_edges_dropped(depths, sources, cfg.stereo.edge_px)
                facts["edge_dropped"] = round(dropped / max(1, sum(d.size for d in depths)), 4)
                parts["edges"] = _part(sources, time.process_time() - c0)
                log.info(
                    "depth: %.1f %% of the pixels dropped beside depth edges",
                    100 * facts["edge_dropped"],
                )

        fill = _fill_needed(cfg.field, parts, sweep)
        facts["field_fill"] = fill
        log.info("depth: %s", fill)
        if fill.startswith("field"):
            c0 = time.process_time()
            found = dict(enumerate(depths)) if depths is not None else None
            filled, facts["field"] = field_fill(
                cfg, cap, out / "field", found, int(facts.get("scale", 1))
            )
            # how the field's training ended: "steps" by default; "time" when the opt-in
            # depth.field.train.time_budget fired (the depth then depends on the load)
            facts["field_stop_reason"] = facts["field"]["stop_reason"]
            # the spread limit on the fill's readings, how it was set and the share it
            # dropped (depth.field.max_spread, max_spread_agreeing; None: neither set)
            facts["field_spread"] = facts["field"].get("spread")
            sources = _field_sources(filled, depths, sources)
            depths = filled
            parts["field"] = _part(sources, time.process_time() - c0)
    assert depths is not None and sources is not None
    outs = DepthOutputs.at(out)
    outs.depth.mkdir()
    outs.sources.mkdir()
    frames = []
    for f, d, s in zip(cap.frames, depths, sources, strict=True):
        path = outs.depth / f"{f.stem}.npy"
        write_depth_npy(path, d)
        write_image(outs.sources / f"{f.stem}.png", np.where(d > 0, s, NONE).astype(np.uint8))
        frames.append(replace(f, depth=path))
    replace(cap.with_frames(frames), depth_scale=1.0, depth_invalid=()).save(outs.frames)
    facts["coverage"] = {k: v["coverage"] for k, v in parts.items()}  # after each part
    facts["by_source"] = _by_source(depths, sources)
    facts["cpu_seconds"] = round(sum(p["cpu_seconds"] for p in parts.values()), 3)
    facts["seconds"] = round(time.perf_counter() - t0, 3)
    write_json(outs.stats, facts)
    return outs


def _load(cap: Capture) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(images at full size, float32 0..1; SfM track depth maps at full size, 0 = none)."""
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
    return images, sparse


def _near_edges_dropped(
    depths: list[np.ndarray], sources: list[np.ndarray], px: int
) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """(depths, sources, readings dropped): the stereo readings on sweep.near_edge (px pixels
    of a reading 10 % farther, stereo's or a plane's) removed; plane fills stay."""
    out_d, out_s, dropped = [], [], 0
    for d, s in zip(depths, sources, strict=True):
        gone = near_edge(d, px) & (s == STEREO)
        dropped += int(gone.sum())
        out_d.append(np.where(gone, 0, d).astype(d.dtype))
        out_s.append(np.where(gone, NONE, s).astype(s.dtype))
    return out_d, out_s, dropped


def _part(sources: list[np.ndarray], cpu: float, ran: bool = True) -> dict:
    """A part's facts: the share of the pixels with depth after it, by source, its CPU-s."""
    n = max(1, sum(s.size for s in sources))
    by = {
        name: round(sum(int((s == k).sum()) for s in sources) / n, 4) for k, name in SOURCES.items()
    }
    cov = round(sum(int((s != NONE).sum()) for s in sources) / n, 4)
    return {"ran": ran, "coverage": cov, "by_source": by, "cpu_seconds": round(cpu, 3)}


def _by_source(depths: list[np.ndarray], sources: list[np.ndarray]) -> dict:
    """The share of the written pixels with depth from each source."""
    n = max(1, sum(d.size for d in depths))
    return {
        name: round(
            sum(int(((s == k) & (d > 0)).sum()) for s, d in zip(sources, depths, strict=True)) / n,
            4,
        )
        for k, name in SOURCES.items()
    }


def _field_sources(
    filled: list[np.ndarray], found: list[np.ndarray] | None, before: list[np.ndarray] | None
) -> list[np.ndarray]:
    """Each filled view's sources: the found reading's source where the fill kept it, FIELD
    where the field's render filled a hole (found maps at a coarser size are upsampled)."""
    out = []
    for i, d in enumerate(filled):
        src = np.full(d.shape, FIELD, np.uint8)
        if found is not None and before is not None:
            f, s = found[i], before[i]
            if f.shape != d.shape:
                f, s = upsample_depth(f, d.shape), upsample_depth(s, d.shape)
            keep = (f > 0) & np.isclose(d, f)
            src = np.where(keep, s, src).astype(np.uint8)
        out.append(np.where(d > 0, src, NONE).astype(np.uint8))
    return out


def _planes_reason(pc: PlanesConfig, kept: float) -> str:
    """Whether the plane fill ran, and why (a line for the log and the report)."""
    if not pc.enabled:
        return "no plane fill (depth.planes.enabled off)"
    if kept < pc.below:
        return (
            f"plane fill: stereo covers {100 * kept:.0f} % of the pixels, under "
            f"depth.planes.below {100 * pc.below:.0f} %"
        )
    return (
        f"no plane fill: stereo covers {100 * kept:.0f} % of the pixels "
        f"(depth.planes.below {100 * pc.below:.0f} %)"
    )


def _fill_needed(fc: FieldFillConfig, parts: dict, swept: bool) -> str:
    """Whether the field trains to fill the holes, and why (a line for the log and the
    report): always without a sweep or with depth.field.fill true, never with false; with
    "auto" when the readings so far cover fewer than depth.field.below of the pixels."""
    if not swept:
        return "field trained: its render is the depth (no sweep)"
    if fc.fill is True:
        return "field trained to fill the rest (depth.field.fill)"
    if fc.fill is False:
        return "no field trained (depth.field.fill off)"
    kept = list(parts.values())[-1]["coverage"]
    if kept < fc.below:
        return (
            f"field trained to fill the rest: the readings cover {100 * kept:.0f} % of the "
            f"pixels, under depth.field.below {100 * fc.below:.0f} %"
        )
    return (
        f"no field trained: the readings cover {100 * kept:.0f} % of the pixels "
        f"(depth.field.below {100 * fc.below:.0f} %)"
    )

"""The field fill's depth: each view's render where the readings found before it (stereo,
planes) have none, checked against the other views."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from stages.common.camera import Intrinsics
from stages.common.capture import Frame
from stages.common.errors import BlunfError
from stages.common.io import write_depth_npy
from stages.common.progress import track
from stages.common.radiance.field import RadianceField
from stages.common.radiance.rays import camera_rays
from stages.common.radiance.render import FieldRender, render_field, render_view
from stages.depth.config import DepthCheckConfig, FieldFillConfig
from stages.depth.consistency import consistent_depth
from stages.depth.debias import bias_curve, debiased
from stages.depth.spread import agreeing, at_blocks, sample_blocks, spread_limit

log = logging.getLogger(__name__)


def write_depths(
    model: RadianceField,
    frames: list[Frame],
    cfg: FieldFillConfig,
    folder: Path,
    prior: dict[int, np.ndarray] | None = None,
    stereo_check: int = 0,
    tol: float = 0.02,
    dc: DepthCheckConfig | None = None,
) -> tuple[list[Frame], dict, list[np.ndarray]]:
    """Render every frame's depth and write folder/<stem>.npy for fusion.

    View i's `prior` (its stereo readings, full resolution, 0 = none) is taken where it has
    a reading, at its resolution, the render (at 1 / cfg.render_scale, upsampled) elsewhere.
    With stereo_check > 0 the rendered readings are kept only where at least that many
    other views' prior readings agree with them (within `tol`, depth.stereo.tol) and none
    sees through them: the field's depth fills the holes where the photos confirm it. With
    `dc` enabled (depth.check) every reading is then checked against the other views' depth.
    Returns (the frames pointing at those files, facts: fractions of the rendered readings
    kept by each check, None when it did not run; the depth maps written).
    """
    prior = prior or {}
    k = max(1, cfg.render_scale)
    # a swept view's render is needed only where a block of its pixels lacks stereo
    need = {i: _block_any(p <= 0, k) for i, p in prior.items()}
    views = track(enumerate(frames), "field fill", len(frames), "view")
    if cfg.max_spread > 0 or cfg.max_spread_agreeing > 0 or cfg.debias:
        depths, spread_facts = _render_narrow(model, cfg, prior, need, tol, views)
    else:
        depths = [render_depth(model, f, cfg, need.get(i)) for i, f in views]
        spread_facts = None
    facts: dict = {
        "depth_check_kept": None,
        "stereo_check_kept": None,
        "spread": spread_facts,
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
            tol,
            stereo_check,
            0,
            dc.views if dc is not None else DepthCheckConfig().views,
            refs=refs,
        )
        facts["stereo_check_kept"] = round(kept, 4)
        log.info("depth: %.1f %% of the rendered readings confirmed by the others", 100 * kept)
    depths = [
        np.where(prior[i] > 0, prior[i], c).astype(np.float32) if i in prior else c
        for i, c in enumerate(cands)
    ]
    if dc is not None and dc.enabled:
        depths, kept = consistent_depth(
            depths,
            [_k_at(f, d) for f, d in zip(frames, depths, strict=True)],
            [np.asarray(f.pose, np.float64) for f in frames],
            dc.tol,
            dc.agree,
            dc.through,
            dc.views,
        )
        facts["depth_check_kept"] = round(kept, 4)
        log.info("depth: %.1f %% of the readings confirmed by other views", 100 * kept)
    out = []
    for f, d in zip(frames, depths, strict=True):
        path = folder / f"{f.stem}.npy"
        write_depth_npy(path, d)
        out.append(replace(f, depth=path))
    return out, facts, depths


def _render_narrow(
    model: RadianceField,
    cfg: FieldFillConfig,
    prior: dict[int, np.ndarray],
    need: dict[int, np.ndarray],
    tol: float,
    views,
) -> tuple[list[np.ndarray], dict]:
    """render_depth of every view with the readings whose weights spread too far along the
    ray dropped: past depth.field.max_spread, or past max_spread_agreeing times the median
    spread of the readings that agree with stereo (within `tol`) on a sample of the blocks
    stereo read (spread.py). Returns (the depths, facts: the limit, how it was set, the share
    of the rendered readings it dropped)."""
    k = max(1, cfg.render_scale)
    measure = cfg.max_spread_agreeing > 0 or cfg.debias
    renders, agree, pairs = [], [], []
    for i, f in views:
        w, h = f.intrinsics.width, f.intrinsics.height
        intr = f.intrinsics.scaled(max(1, w // k), max(1, h // k))
        want = need.get(i)
        pixels = want
        if measure and want is not None:
            pixels = want | sample_blocks(want)
        depth, acc, spread = ray_spread(model, np.asarray(f.pose), intr, cfg.chunk, pixels)
        ok = acc >= cfg.sampling.acc_threshold
        if measure and want is not None:
            beside = at_blocks(prior[i], depth.shape)
            agree.append(agreeing(depth, ok & ~want, spread, beside, tol))
            both = ok & ~want & (beside > 0)
            pairs.append((depth[both], beside[both]))
            ok &= want
        renders.append((depth, ok, spread))
    limit, facts = spread_limit(
        np.concatenate(agree) if agree else np.zeros(0, np.float32),
        cfg.max_spread_agreeing,
        cfg.max_spread,
    )
    curve = None
    if cfg.debias and pairs:
        curve = bias_curve(*(np.concatenate(x) for x in zip(*pairs, strict=True)))
        renders = [(debiased(d, curve), ok, s) for d, ok, s in renders]
    facts["debias"] = (
        None
        if curve is None
        else {"depth": curve[0].round(3).tolist(), "ratio": curve[1].round(4).tolist()}
    )
    read = sum(int(ok.sum()) for _, ok, _ in renders)
    out = [np.where(ok & (s <= limit), d, 0.0).astype(np.float32) for d, ok, s in renders]
    kept = sum(int((d > 0).sum()) for d in out)
    facts["dropped"] = round(1.0 - kept / read, 4) if read else 0.0
    log.info(
        "depth/field: spread limit %s (%s) dropped %.1f %% of the rendered readings",
        facts["limit"],
        facts["rule"],
        100 * facts["dropped"],
    )
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
    model: RadianceField, f: Frame, cfg: FieldFillConfig, pixels: np.ndarray | None = None
) -> np.ndarray:
    """z-depth (metres, float32) of frame f at 1 / render_scale of its resolution; 0
    where the opacity is below sampling.acc_threshold (fusion rescales the intrinsics to fit),
    where the weights spread along the ray by more than cfg.max_spread of the depth (when
    set: ray_spread) and, given `pixels` (bool, at that resolution), where it is False (not
    rendered)."""
    k = max(1, cfg.render_scale)
    w, h = f.intrinsics.width, f.intrinsics.height
    intr = f.intrinsics.scaled(max(1, w // k), max(1, h // k))
    if cfg.max_spread > 0:
        depth, acc, spread = ray_spread(model, np.asarray(f.pose), intr, cfg.chunk, pixels)
        ok = (acc >= cfg.sampling.acc_threshold) & (spread <= cfg.max_spread)
        return np.where(ok, depth, 0.0).astype(np.float32)
    v = render_view(model, np.asarray(f.pose), intr, cfg.chunk, color=False, pixels=pixels)
    return np.where(v["acc"] >= cfg.sampling.acc_threshold, v["depth"], 0.0).astype(np.float32)


@torch.no_grad()
def ray_spread(
    model: RadianceField,
    pose: np.ndarray,
    intr: Intrinsics,
    chunk: int = 16384,
    pixels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z-depth [H, W] metres, opacity [H, W], spread [H, W]) of a view: the spread is the
    standard deviation of the ray distance under the compositing weights over their mean.

    A surface the photos pin down (texture, stereo) concentrates a ray's weight within a
    step or two: the 7-Scenes kitchen's field-filled readings within 5 cm of the sensor's
    surface spread a median 1.5 % of their depth. A plain floor the field renders as fog
    spreads it along the ray and reads short: the readings that painted a table-high
    surface over the kitchen's floor, a median 4 % (a quarter above 10 %). Pixels outside
    `pixels` (bool [H, W]) are 0 in all three."""
    o, d, zs = camera_rays(pose, intr)
    h, w = intr.height, intr.width
    sel = torch.arange(h * w) if pixels is None else torch.from_numpy(np.flatnonzero(pixels))
    fns = model.fns(semantics=False)
    how = FieldRender(surface_color=False, color=False, return_samples=True)
    depth, acc, spread = (torch.zeros(h * w) for _ in range(3))
    for i in range(0, len(sel), chunk):
        part = sel[i : i + chunk]
        out = render_field(model, o[part], d[part], fns, how)
        n = len(part)
        ray, t, wt = out["ray"], out["t"], out["weights"]
        total = torch.zeros(n).index_add_(0, ray, wt).clamp(min=1e-10)
        mean = torch.zeros(n).index_add_(0, ray, wt * t) / total
        var = torch.zeros(n).index_add_(0, ray, wt * (t - mean[ray]) ** 2) / total
        depth[part] = out["depth"] * zs[part]
        acc[part] = out["acc"]
        spread[part] = var.sqrt() / mean.clamp(min=1e-6)
    return depth.reshape(h, w).numpy(), acc.reshape(h, w).numpy(), spread.reshape(h, w).numpy()

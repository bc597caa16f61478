"""Held-out scores: PSNR of rendered colour, AbsRel of rendered depth."""

from __future__ import annotations

import math

import numpy as np
import torch

from stages.common.radiance.field import RadianceField
from stages.common.radiance.render import render_field
from stages.common.radiance.views import Rays


def psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


@torch.no_grad()
def score(model: RadianceField, rays: Rays, chunk: int) -> tuple[float, float | None]:
    """PSNR (dB) of the model on the given rays (their pooled squared error), and the depth
    AbsRel on those with a depth reading (`depth_absrel` of the rendered ray distance, 0
    where the opacity is below acc_threshold: the ratio is that of z-depths) or None when
    the rays have no depth."""
    err = 0.0
    fns = model.fns(semantics=False)
    t = []
    for i in range(0, len(rays.rgb), chunk):
        out = render_field(model, rays.origins[i : i + chunk], rays.dirs[i : i + chunk], fns)
        err += float(((out["rgb"] - rays.rgb[i : i + chunk]) ** 2).sum())
        t.append(torch.where(out["acc"] >= model.sampling.acc_threshold, out["depth"], 0.0))
    rel = None
    if rays.t_depth is not None and t:
        rel = depth_absrel(torch.cat(t).numpy(), rays.t_depth.numpy())
    return psnr(err / max(1, rays.rgb.numel())), rel


def depth_absrel(pred: np.ndarray, gt: np.ndarray) -> float:
    """Median of |d - d*| / d* over pixels with valid ground truth (missing pred counts 1)."""
    ok = gt > 0
    if not ok.any():
        return float("nan")
    return float(np.median(np.abs(pred[ok] - gt[ok]) / gt[ok]))

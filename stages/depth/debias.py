"""The field fill's depth bias, measured against stereo in the same run and taken out.

A radiance field trained on photos places some density in front of the surfaces (fog where
only the photometric loss holds it), so its expected depth is short, more so the farther the
surface: on the 7-Scenes kitchen (configs/phone.yaml) its renders beside stereo's readings are
1.4 % short of them under 1 m and 3 % at 2.5-3 m, and its fills of stereo's holes 6-9 % short
of the sensor past 1.5 m. The counters' tops and fronts, filled short, stand out over the
aisles' floor in the plan. `depth.field.debias` divides each fill by the field's median ratio
to stereo at its depth, measured on the blocks rendered beside stereo (spread.sample_blocks).
"""

from __future__ import annotations

import numpy as np

MIN_PAIRS = 100  # fewer render-stereo pairs in a depth bin than this: the bin is not used
BINS = 8  # depth bins (quantiles of the paired renders' depth)
MAX_OFF = 0.2  # pairs further apart than this share of the stereo depth are other surfaces


def bias_curve(render: np.ndarray, stereo: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(depths [B], median render / stereo ratio at them [B]) from paired readings (both > 0,
    within MAX_OFF of each other), in up to BINS bins of equal count; None when too few."""
    r = np.asarray(render, np.float64)
    s = np.asarray(stereo, np.float64)
    ok = (r > 0) & (s > 0) & np.isfinite(r) & np.isfinite(s)
    ok &= np.abs(r - s) <= MAX_OFF * np.where(ok, s, 1.0)
    r, s = r[ok], s[ok]
    bins = min(BINS, len(r) // MIN_PAIRS)
    if bins < 1:
        return None
    order = np.argsort(r, kind="stable")
    parts = np.array_split(order, bins)
    at = np.array([float(np.median(r[p])) for p in parts])
    ratio = np.array([float(np.median(r[p] / s[p])) for p in parts])
    return at, ratio


def debiased(depth: np.ndarray, curve: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """depth [...] (0 = none) divided by the curve's ratio at each reading's depth (linear
    between the bins, the end bins' ratio beyond them); unchanged without a curve."""
    if curve is None:
        return depth
    ratio = np.interp(depth, curve[0], curve[1])
    return np.where(depth > 0, depth / np.maximum(ratio, 1e-6), 0.0).astype(depth.dtype)

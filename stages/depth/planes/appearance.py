"""Each plane's colours, from its inliers: a region far from every colour seen on a plane
is unlikely to be that plane (the floor under a table, a dark chair in front of a wall).

A coarse RGB histogram (BINS per channel, box-smoothed over neighbouring bins so that
exposure steps between views do not matter) per plane, scaled to a peak of 1."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter

from stages.depth.planes.hypotheses import Plane

BINS = 6  # per channel
GAIN = 4.0  # a colour at a quarter of the plane's most common one counts as fully seen


def plane_colours(
    planes: list[Plane],
    points: np.ndarray,
    colours: np.ndarray,
    band: float,
    normals: np.ndarray | None = None,
    normal_cos: float = 0.9,
) -> np.ndarray:
    """[P, BINS, BINS, BINS] colour histograms of the points within band of each plane and
    inside its inliers' box, peak 1 (all ones for a plane without coloured inliers). With
    normals (zeros where unknown), only the points whose own normal lies within normal_cos
    of the plane's: the surface itself, not what stands on it or crosses it (every chair
    leg and shadowed sofa foot lies within band of the floor: the office's floor took
    every dark colour, and its fills covered the dark chair seats)."""
    out = np.ones((len(planes), BINS, BINS, BINS))
    idx = bin_index(colours)
    for k, p in enumerate(planes):
        near = np.abs(points @ p.normal - p.offset) <= band
        near &= np.all((points >= p.lo - band) & (points <= p.hi + band), axis=1)
        if normals is not None:
            near &= np.abs(normals @ p.normal) >= normal_cos
        if near.sum() < 20:
            continue
        h = np.bincount(idx[near], minlength=BINS**3).reshape(BINS, BINS, BINS).astype(float)
        h = uniform_filter(h, 3, mode="nearest")
        out[k] = h / max(float(h.max()), 1e-12)
    return out


def bin_index(rgb: np.ndarray) -> np.ndarray:
    """Flat histogram bin [N] of colours [N, 3] in 0..1."""
    b = np.clip((np.asarray(rgb) * BINS).astype(np.int64), 0, BINS - 1)
    return (b[:, 0] * BINS + b[:, 1]) * BINS + b[:, 2]


def colour_cost(hists: np.ndarray, mean_rgb: np.ndarray) -> np.ndarray:
    """[S, P] in 0..1: how unlike each plane's colours each superpixel's mean colour is."""
    flat = hists.reshape(len(hists), -1)  # [P, B^3]
    return 1 - np.minimum(1.0, GAIN * flat[:, bin_index(mean_rgb)].T)

"""A view's depth from its labels: keep agreeing readings, drop fattened ones, fill planes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from stages.common.camera import pixel_grid
from stages.depth.planes.config import PlanesConfig
from stages.depth.planes.geometry import plane_depth, rays
from stages.depth.planes.hypotheses import FURNITURE_KINDS, ROOM_KINDS, Plane
from stages.depth.planes.view import Labelling


@dataclass
class Merged:
    """One view's depth at the readings' size."""

    kept: np.ndarray  # [h, w] stereo readings kept (0 = none)
    fill: np.ndarray  # [h, w] plane depth filled (0 = none), before the multi-view check
    plane: np.ndarray  # [h, w] int16 index of the filling plane (-1 = none)
    dropped: int  # readings dropped as disagreeing with a plane at a region's edge
    region: np.ndarray  # [h, w] int16 plane of the pixel's region (-1 = none)
    snapped: int = 0  # readings moved onto their region's floor, wall or ceiling (cfg.snap)


def merge_view(
    lab: Labelling,
    depth: np.ndarray,
    K: np.ndarray,
    pose: np.ndarray,
    planes: list[Plane],
    cfg: PlanesConfig,
) -> Merged:
    """Merge rules (see the package docstring) on the readings' grid h x w (K at h x w)."""
    h, w = depth.shape
    hs, ws = lab.seg.shape
    rows = np.minimum(((np.arange(h) + 0.5) * hs / h).astype(np.int64), hs - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * ws / w).astype(np.int64), ws - 1)
    seg = lab.seg[rows][:, cols]
    n_p = len(planes)
    per_sp = lab.labels
    margin = lab.unary[:, n_p] - lab.unary[np.arange(len(per_sp)), np.minimum(per_sp, n_p)]
    extra = np.array([cfg.furniture_extra if p.kind in FURNITURE_KINDS else 0.0 for p in planes])
    need = cfg.margin + np.append(extra, 0.0)[np.minimum(per_sp, n_p)]
    fillable = (per_sp < n_p) & (margin >= need)
    lab_px = per_sp[seg]  # [h, w]
    t = np.zeros(h * w)
    flat = lab_px.reshape(-1)
    uv = pixel_grid(w, h).reshape(-1, 2)
    for k in np.unique(flat[flat < n_p]):
        idx = np.flatnonzero(flat == k)
        t[idx] = plane_depth(rays(uv[idx], K, pose), pose[:3, 3], [planes[k]])[0]
    t = t.reshape(h, w)
    r = np.where(np.isfinite(depth), depth, 0.0)
    b = max(0, cfg.boundary_px)
    edge = maximum_filter(lab_px, 2 * b + 1) != minimum_filter(lab_px, 2 * b + 1) if b else False
    strong = np.array([p.support >= 2 * cfg.min_support for p in planes] + [False])
    is_plane = (lab_px < n_p) & (t > 0)
    agree = np.abs(r - t) <= cfg.tol * np.maximum(t, 1e-6)
    drop = (r > 0) & is_plane & ~agree & edge & strong[lab_px]
    kept = np.where((r > 0) & ~drop, r, 0.0).astype(np.float32)
    filled = is_plane & fillable[seg]  # the regions a plane wins by the margin
    snap = np.zeros_like(drop)
    if cfg.snap:  # a reading that agrees with the room's own plane takes its depth
        room = np.array([p.kind in ROOM_KINDS for p in planes] + [False])
        snap = (kept > 0) & filled & agree & room[lab_px]
        kept = np.where(snap, t, kept).astype(np.float32)
    fill_px = (kept == 0) & filled
    fill = np.where(fill_px, t, 0.0).astype(np.float32)
    plane = np.where(fill_px, lab_px, -1).astype(np.int16)
    region = np.where(lab_px < n_p, lab_px, -1).astype(np.int16)
    return Merged(kept, fill, plane, int(drop.sum()), region, int(snap.sum()))

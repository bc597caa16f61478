"""Multi-view geometric consistency of rendered depth maps (photos-only depth path).

A NeRF trained on photos and sparse SfM tracks renders floaters: density hanging in front
of the surface in some views, seen through in others. Such a reading is checked the way
multi-view stereo checks its depth maps before fusing them (COLMAP's fusion, Schönberger
et al. 2016): each pixel is lifted to a world point and projected into the views that
overlap its view. A neighbour *agrees* where its own depth at that pixel is within `tol`
(relative) of the point's depth, and *sees through* the point where its depth lies beyond
the point by more than `tol` (the point hangs in space that neighbour found empty). A
pixel is kept when at least `min_agree` neighbours agree and at most `max_through` see
through it; other pixels become missing depth, which TSDF fusion simply leaves out.

Neither Open3D nor pycolmap offers this check on depth maps given from outside (pycolmap's
stereo fusion needs its own CUDA patch-match outputs), hence this numpy implementation.
"""

from __future__ import annotations

import numpy as np

from stages.common.camera import depth_at, depth_to_points
from stages.common.errors import BlunfError
from stages.common.progress import track


def consistent_depth(
    depths: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    tol: float,
    min_agree: int,
    max_through: int,
    neighbours: int,
    refs: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] | None = None,
) -> tuple[list[np.ndarray], float]:
    """Depth maps with the readings the other views do not confirm set to 0.

    Args:
        depths: per view [H, W] z-depth (metres, 0 = missing).
        Ks: per view [3, 3] intrinsics at the depth maps' resolution.
        poses: per view [4, 4] camera-to-world.
        tol: relative depth difference within which two readings agree.
        min_agree: neighbours that must agree for a reading to be kept.
        max_through: at most this many neighbours may see through a kept reading.
        neighbours: each view is checked against this many others: those into which the
            most of its (strided) readings project, i.e. the views that overlap it most.
        refs: (depth maps, intrinsics, poses) the readings are checked against instead of
            the other maps of `depths` (e.g. rendered depth against stereo); None = depths.
    Returns:
        (filtered depth maps, float32, same shapes; fraction of the readings kept).
    """
    if not 0 < tol < 1:
        raise BlunfError(f"depth.check.tol must be in (0, 1), got {tol}")
    if min_agree < 0 or max_through < 0 or neighbours < 1:
        raise BlunfError(
            "depth.check.agree / depth.check.through must be >= 0 and "
            f"depth.check.views >= 1, got {min_agree}, {max_through}, {neighbours}"
        )
    n = len(depths)
    r_depths, r_Ks, r_poses = refs if refs is not None else (depths, Ks, poses)
    order = overlap_order(depths, Ks, poses, refs=refs)
    out: list[np.ndarray] = []
    total = kept = 0
    for i in track(range(n), "depth check", n, "view"):
        pts, flat = depth_to_points(depths[i], Ks[i], poses[i])
        agree = np.zeros(len(pts), np.int32)
        through = np.zeros(len(pts), np.int32)
        for j in order[i][:neighbours]:
            dj, z = depth_at(pts, r_depths[j], r_Ks[j], r_poses[j])
            seen = dj > 0
            # relative to the neighbour's reading (guarded: seen implies dj > 0)
            rel = (z - dj) / np.where(seen, dj, 1.0)
            agree += seen & (np.abs(rel) <= tol)
            through += seen & (rel < -tol)
        ok = (agree >= min_agree) & (through <= max_through)
        d = np.zeros(depths[i].size, np.float32)
        d[flat[ok]] = depths[i].reshape(-1)[flat[ok]]
        out.append(d.reshape(depths[i].shape))
        total += len(pts)
        kept += int(ok.sum())
    return out, kept / max(1, total)


def overlap_order(
    depths: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    stride: int = 8,
    refs: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] | None = None,
    angle: float = 0.0,
) -> list[list[int]]:
    """Per view, the other views (or the maps of `refs`) by decreasing overlap: how many of
    its readings (on a strided pixel grid) project inside them with a reading there. angle >
    0 (degrees): each such reading counts by the angle its two rays meet at, as MVSNet's view
    selection (Yao et al., ECCV 2018): exp(-(t - angle)^2 / 2 s^2), s = 1 degree below
    `angle`, 10 above, so a neighbour that sees the same points from nearly the same place
    (a dense walk's next photo) ranks below one a few steps on."""
    r_depths, r_Ks, r_poses = refs if refs is not None else (depths, Ks, poses)
    m = len(r_depths)
    order = []
    for i in range(len(depths)):
        h, w = depths[i].shape
        s = max(1, min(stride, min(h, w) // 8))
        pts, _ = depth_to_points(depths[i], Ks[i], poses[i], s)
        counts = np.zeros(m, np.float64)
        for j in range(m):
            if (refs is not None or j != i) and len(pts):
                seen = depth_at(pts, r_depths[j], r_Ks[j], r_poses[j])[0] > 0
                if angle <= 0:
                    counts[j] = float(seen.sum())
                    continue
                p = pts[seen]
                a = p - poses[i][:3, 3]
                b = p - r_poses[j][:3, 3]
                cos = (a * b).sum(1) / np.maximum(
                    np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12
                )
                t = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
                sd = np.where(t <= angle, 1.0, 10.0)
                counts[j] = float(np.exp(-((t - angle) ** 2) / (2 * sd**2)).sum())
        if refs is None:
            counts[i] = -1
        order.append([int(j) for j in np.argsort(-counts, kind="stable") if counts[j] > 0])
    return order

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


# a neighbour whose reading is this much nearer than the point (relative) does not see it.
# configs/phone.yaml, 0.1 (0.3; none): the 360-photo home 80.48 (79.13; 77.19), the kitchen
# 67.80 (64.63; 68.59), the office 59.62 (62.71; 62.24): docs/scale.md#check-through-walls
HIDDEN = 0.1


def overlap_order(
    depths: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    stride: int = 8,
    refs: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] | None = None,
    angle: float = 0.0,
    hidden: float = HIDDEN,
) -> list[list[int]]:
    """Per view, the other views (or the maps of `refs`) by decreasing overlap: how many of
    its readings (on a strided pixel grid) project inside them onto a reading of theirs that
    is not nearer than the point by more than `hidden` (relative): a view in the next room
    that looks the same way has readings there, on the wall between, and cannot confirm
    anything (0 = any reading counts; on the 480-view home 108 views had at most one view
    among their 8 check neighbours that saw a fifth of their points). angle >
    0 (degrees): each such reading counts by the angle its two rays meet at, as MVSNet's view
    selection (Yao et al., ECCV 2018): exp(-(t - angle)^2 / 2 s^2), s = 1 degree below
    `angle`, 10 above, so a neighbour that sees the same points from nearly the same place
    (a dense walk's next photo) ranks below one a few steps on.

    Every view is tested against every other, so the work grows with the square of the
    views. Each view's points go into all the other views at once (`_Maps.counts`): at 480
    views of 160x120, 2.1 CPU-s for 300 readings a view (3.5 s for the sweep's ~300 SfM
    track pixels at stride 1), against 17 s each with a `depth_at` call per pair."""
    r_depths, r_Ks, r_poses = refs if refs is not None else (depths, Ks, poses)
    if not r_depths:
        return [[] for _ in depths]
    maps = _Maps(r_depths, r_Ks, r_poses)
    order = []
    for i in range(len(depths)):
        h, w = depths[i].shape
        s = max(1, min(stride, min(h, w) // 8))
        pts, _ = depth_to_points(depths[i], Ks[i], poses[i], s)
        counts = maps.counts(pts, poses[i][:3, 3], angle, hidden)
        if refs is None:
            counts[i] = -1
        order.append([int(j) for j in np.argsort(-counts, kind="stable") if counts[j] > 0])
    return order


class _Maps:
    """Depth maps of several views, for projecting one set of world points into all of them
    at once: what `depth_at` does for one map, without a Python call per pair of views (at
    least one map)."""

    CHUNK = 1 << 20  # point-view pairs a block (a few tens of MB of float64 temporaries)

    def __init__(self, depths: list[np.ndarray], Ks: list[np.ndarray], poses: list[np.ndarray]):
        c2w = np.stack([np.asarray(c, np.float64) for c in poses])
        w2c = np.linalg.inv(c2w)
        self.R = w2c[:, :3, :3]
        self.t = w2c[:, :3, 3]
        self.centres = c2w[:, :3, 3]
        K = np.stack([np.asarray(k, np.float64) for k in Ks])
        self.fx, self.fy, self.cx, self.cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
        self.h = np.array([d.shape[0] for d in depths], np.int64)
        self.w = np.array([d.shape[1] for d in depths], np.int64)
        self.offset = np.concatenate([[0], np.cumsum(self.h * self.w)[:-1]]).astype(np.int64)
        self.flat = np.concatenate([np.asarray(d, np.float32).reshape(-1) for d in depths])

    def counts(
        self, pts: np.ndarray, centre: np.ndarray, angle: float, hidden: float = 0.0
    ) -> np.ndarray:
        """Per map, how many of `pts` [N, 3] project inside it onto a reading not nearer than
        the point by more than `hidden` of its depth (0: any reading; angle > 0: each weighted
        by the angle between its rays from `centre` and from the map's camera)."""
        m = len(self.h)
        out = np.zeros(m, np.float64)
        if not len(pts):
            return out
        x, y, zc = (pts[:, k][None, :] for k in range(3))
        if angle > 0:  # this view's rays, the same for every block
            ra = pts - centre  # [N, 3]
            ra_len = np.linalg.norm(ra, axis=1)[None]
        step = max(1, self.CHUNK // len(pts))
        for a in range(0, m, step):
            b = min(m, a + step)
            R, t = self.R[a:b], self.t[a:b]

            def axis(k: int, R=R, t=t) -> np.ndarray:
                """The points' camera-frame coordinate k in each view of the block [c, N],
                element-wise: no BLAS, whose summation order may depend on its threads."""
                return R[:, k, 0:1] * x + R[:, k, 1:2] * y + R[:, k, 2:3] * zc + t[:, k : k + 1]

            z = axis(2)
            safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
            pu, pv = axis(0), axis(1)
            u = np.rint(self.fx[a:b, None] * pu / safe + self.cx[a:b, None])
            v = np.rint(self.fy[a:b, None] * pv / safe + self.cy[a:b, None])
            w = self.w[a:b, None]
            inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < self.h[a:b, None])
            idx = np.where(inside, self.offset[a:b, None] + v * w + u, 0).astype(np.int64)
            d = self.flat[idx]
            seen = inside & (d > 0)
            if hidden > 0:
                seen &= d >= z * (1.0 - hidden)
            if angle <= 0:
                out[a:b] = seen.sum(1)
                continue
            rb = pts[None, :, :] - self.centres[a:b, None, :]  # [c, N, 3]
            cos = (ra[None] * rb).sum(2) / np.maximum(ra_len * np.linalg.norm(rb, axis=2), 1e-12)
            deg = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
            sd = np.where(deg <= angle, 1.0, 10.0)
            out[a:b] = np.where(seen, np.exp(-((deg - angle) ** 2) / (2 * sd**2)), 0.0).sum(1)
        return out

"""A plane through 3-D points by RANSAC, the same plane for the same points and seed.

Open3D's `PointCloud.segment_plane` is not used: in open3d 0.20 its iterations run in
parallel and draw from one shared sampler, so the same points and `o3d.utility.random.seed`
gave a different plane from one call to the next (measured: 2 of 5 calls in one process, and
runs of the same photos drew plans that differed in a few hundred cells). Here the
iterations' samples are drawn up front from the caller's numpy generator and scored in
blocks, in order: the first best-scoring sample wins.
"""

from __future__ import annotations

import numpy as np

BLOCK = 128  # hypotheses scored at once ([BLOCK, N] distances: 5 MB for 5 000 points)


def plane_ransac(
    points: np.ndarray, dist: float, iters: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The plane through the most of `points` [N, 3] within `dist`, and those points.

    Each of `iters` hypotheses is the plane through 3 distinct points drawn by `rng`; the one
    with the most inliers wins, ties going to the smaller inlier RMS and then to the earlier
    draw. Returns (plane [4]: unit normal n and d with n.p + d = 0, inlier indices [M]); a
    plane of zeros and no inliers when no 3 points span a plane.
    """
    p = np.asarray(points, np.float64)
    n = len(p)
    none = np.zeros(4), np.zeros(0, np.int64)
    if n < 3 or iters < 1:
        return none
    mid = p.mean(axis=0)
    q = p - mid  # centred: the offsets d stay small, the products well scaled
    # 3 distinct indices per hypothesis (the second and third shifted past the ones before)
    i = rng.integers(0, n, iters)
    j = rng.integers(0, n - 1, iters)
    j += j >= i
    k = rng.integers(0, n - 2, iters)
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    k += k >= lo
    k += k >= hi
    normal = np.cross(q[j] - q[i], q[k] - q[i])  # [iters, 3]
    norm = np.linalg.norm(normal, axis=1)
    good = norm > 1e-12 * max(float(np.abs(q).max()), 1e-12) ** 2  # not three points on a line
    normal = normal / np.where(good, norm, 1.0)[:, None]
    off = -np.einsum("ij,ij->i", normal, q[i])  # [iters]
    best = (-1, 0.0, -1)  # (inliers, -rms, index) of the best hypothesis so far
    qt = q.T
    for s in range(0, iters, BLOCK):
        e = min(s + BLOCK, iters)
        # elementwise products, not a matrix product: BLAS may sum in another order
        r = np.abs(
            normal[s:e, 0:1] * qt[0]
            + normal[s:e, 1:2] * qt[1]
            + normal[s:e, 2:3] * qt[2]
            + off[s:e, None]
        )  # [B, N]
        inl = r < dist
        count = np.where(good[s:e], inl.sum(axis=1), -1)
        sq = np.where(inl, r * r, 0.0).sum(axis=1) / np.maximum(count, 1)
        for b in np.flatnonzero(count == count.max()):
            cand = (int(count[b]), -float(sq[b]), s + int(b))
            if cand[:2] > best[:2]:
                best = cand
    if best[0] < 3:
        return none
    h = best[2]
    r = np.abs(normal[h, 0] * qt[0] + normal[h, 1] * qt[1] + normal[h, 2] * qt[2] + off[h])
    plane = np.append(normal[h], off[h] - normal[h] @ mid)  # back from the centred frame
    return plane, np.flatnonzero(r < dist)

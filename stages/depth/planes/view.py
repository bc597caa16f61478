"""One view's labelling: superpixels, each plane's data cost in each, the superpixel graph.

Labels are the planes plus `none` (the last: keep stereo). Per superpixel and plane the
cost sums (each a share of the superpixel, times its area over the mean area):
- disagreement with the view's own readings (robust, twice for a reading *beyond* the
  plane: the plane would hide a surface the view saw);
- free space: the share of other views' readings that lie beyond the plane's points (they
  look through it); and, weighted apart, the share that lie nearer (they see something in
  front of it: a plane continued under furniture);
- photo-consistency: 1 - ZNCC of the whole superpixel against the neighbours' images warped
  by the plane's homography (best half), times the superpixel's texture (a blank region
  casts no photometric vote);
- colour: how far the superpixel's mean colour lies from the colours of the plane's
  inliers (`appearance`);
- validity: the share of its pixels where the plane is behind, grazing, below the floor,
  above the ceiling or farther than support_margin from its inliers' box.
`none` costs none_cost, less the share of the superpixel read by stereo off every plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy.sparse import csr_matrix
from skimage.segmentation import slic

from stages.common.camera import pixel_grid
from stages.depth.planes.appearance import colour_cost
from stages.depth.planes.config import PlanesConfig
from stages.depth.planes.geometry import homographies, plane_depth, plane_valid, rays
from stages.depth.planes.hypotheses import Plane

EPS = 1e-6


@dataclass
class ViewData:
    """One view at the working size (h x w): what the data term reads."""

    rgb: np.ndarray  # [h, w, 3] float32 0..1
    gray: np.ndarray  # [h, w] float32
    K: np.ndarray  # [3, 3] at h x w
    pose: np.ndarray  # [4, 4] camera-to-world
    depth: np.ndarray  # [h, w] checked stereo z-depth sampled at h x w (0 = none)
    depth_full: np.ndarray  # the checked readings at their own size (free-space test)
    K_full: np.ndarray  # [3, 3] intrinsics of depth_full


@dataclass
class Labelling:
    """The view's superpixels, their costs and the labels chosen."""

    seg: np.ndarray  # [h, w] superpixel ids 0..S-1
    unary: np.ndarray  # [S, P + 1] (last: none), per unit area
    labels: np.ndarray  # [S] chosen label (P = none)
    edges: np.ndarray  # [E, 2]
    energy: float


def superpixels(rgb: np.ndarray, cfg: PlanesConfig) -> np.ndarray:
    """SLIC superpixels (seeded grid, deterministic), ids 0..S-1 without gaps."""
    seg = slic(
        rgb.astype(np.float64),
        n_segments=cfg.superpixels,
        compactness=cfg.compactness,
        start_label=0,
        channel_axis=-1,
        enforce_connectivity=True,
    )
    _, inv = np.unique(seg, return_inverse=True)
    return inv.reshape(seg.shape).astype(np.int64)


def data_costs(
    v: ViewData,
    seg: np.ndarray,
    planes: list[Plane],
    nbrs: list[ViewData],
    cfg: PlanesConfig,
    ceiling: float | None,
    hists: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """[S, P + 1] costs per unit area (see the module's docstring) and [S] areas."""
    h, w = seg.shape
    s_n = int(seg.max()) + 1
    flat = seg.reshape(-1)
    area = np.bincount(flat, minlength=s_n).astype(np.float64)
    onehot = csr_matrix((np.ones(flat.size), (flat, np.arange(flat.size))), shape=(s_n, flat.size))
    uv = pixel_grid(w, h).reshape(-1, 2)
    r = rays(uv, v.K, v.pose)
    c = v.pose[:3, 3]
    t = plane_depth(r, c, planes)  # [P, N]
    margins = (cfg.support_margin, cfg.furniture_margin)
    ok = plane_valid(t, r, c, planes, margins, ceiling)
    n_p = len(planes)
    cost = np.zeros((s_n, n_p + 1))
    # validity
    cost[:, :n_p] += cfg.w_valid * (onehot @ (~ok).T.astype(np.float64)) / area[:, None]
    # the view's own readings
    rd = v.depth.reshape(-1)
    has = rd > 0
    e = (rd[None] - t) / np.maximum(t, EPS)  # [P, N] relative, > 0: reading beyond the plane
    pen = np.minimum((e / cfg.tol) ** 2, 1.0) * np.where(e > 0, 2.0, 1.0)
    pen = np.where(ok, pen, 2.0) * has[None]
    cost[:, :n_p] += cfg.w_stereo * (onehot @ pen.T) / area[:, None]
    fits = (np.abs(e) <= cfg.tol) & ok & has[None]
    off_planes = has & ~fits.any(0) if n_p else has
    cost[:, n_p] = cfg.none_cost * (1 - (onehot @ off_planes.astype(np.float64)) / area)
    if n_p:
        through, hidden = _free_space(r, c, t, ok, seg, planes, nbrs, cfg)
        cost[:, :n_p] += cfg.w_free * through + cfg.w_hidden * hidden
        cost[:, :n_p] += cfg.w_photo * _photo(v, t, ok, onehot, area, planes, nbrs, cfg)
    if n_p and hists is not None and cfg.w_colour > 0:
        mean_rgb = (onehot @ v.rgb.reshape(-1, 3).astype(np.float64)) / area[:, None]
        cost[:, :n_p] += cfg.w_colour * colour_cost(hists, mean_rgb)
    return np.nan_to_num(cost, nan=1.0, posinf=10.0, neginf=0.0), area


def _free_space(
    r: np.ndarray,
    c: np.ndarray,
    t: np.ndarray,
    ok: np.ndarray,
    seg: np.ndarray,
    planes: list[Plane],
    nbrs: list[ViewData],
    cfg: PlanesConfig,
    stride: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """([S, P], [S, P]): per superpixel the share of neighbour readings that see through the
    plane (readings farther than the plane's point by more than tol), and the share that
    hide it (nearer by more than tol: the floor under a sofa, which every view sees the sofa
    in front of), on a strided pixel sample."""
    h, w = seg.shape
    grid = np.arange(stride // 2, h, stride)[:, None] * w + np.arange(stride // 2, w, stride)
    idx = grid.reshape(-1)
    sid = seg.reshape(-1)[idx]
    s_n = int(seg.max()) + 1
    through = np.zeros((s_n, len(planes)))
    hidden = np.zeros((s_n, len(planes)))
    seen = np.zeros((s_n, len(planes)))
    for k in range(len(planes)):
        good = ok[k, idx]
        if not good.any():
            continue
        x = c + t[k, idx[good], None] * r[idx[good]]  # [M, 3]
        sk = sid[good]
        for nb in nbrs:
            w2c = np.linalg.inv(nb.pose)
            pc = x @ w2c[:3, :3].T + w2c[:3, 3]
            z = pc[:, 2]
            front = z > EPS
            zs = np.where(front, z, 1.0)
            u = np.rint(nb.K_full[0, 0] * pc[:, 0] / zs + nb.K_full[0, 2]).astype(np.int64)
            vv = np.rint(nb.K_full[1, 1] * pc[:, 1] / zs + nb.K_full[1, 2]).astype(np.int64)
            hh, ww = nb.depth_full.shape
            inside = front & (u >= 0) & (u < ww) & (vv >= 0) & (vv < hh)
            dj = np.zeros(len(z))
            dj[inside] = nb.depth_full[vv[inside], u[inside]]
            obs = dj > 0
            thr = obs & (dj > z * (1 + cfg.tol))
            seen[:, k] += np.bincount(sk[obs], minlength=s_n)
            through[:, k] += np.bincount(sk[thr], minlength=s_n)
            hid = obs & (dj < z * (1 - cfg.tol))
            hidden[:, k] += np.bincount(sk[hid], minlength=s_n)
    return through / np.maximum(seen, 3.0), hidden / np.maximum(seen, 3.0)


def _photo(
    v: ViewData,
    t: np.ndarray,
    ok: np.ndarray,
    onehot: csr_matrix,
    area: np.ndarray,
    planes: list[Plane],
    nbrs: list[ViewData],
    cfg: PlanesConfig,
) -> np.ndarray:
    """[S, P]: texture-weighted (1 - ZNCC) / 2 of each superpixel against the neighbours'
    images warped by each plane's homography (mean of the best half of the neighbours)."""
    h, w = v.gray.shape
    a = v.gray.reshape(-1).astype(np.float64)
    sa_ = onehot @ a
    mean_a = sa_ / area
    var_a = np.maximum(onehot @ (a * a) / area - mean_a**2, 0.0)
    tex = np.clip(np.sqrt(var_a) / cfg.tex_std, 0.0, 1.0)  # [S]
    uv1 = torch.from_numpy(
        np.concatenate([pixel_grid(w, h).reshape(-1, 2), np.ones((h * w, 1))], 1)
    ).float()
    per = []
    for nb in nbrs:
        H = torch.from_numpy(homographies(v.K, v.pose, nb.K, nb.pose, planes)).float()
        q = torch.einsum("pij,nj->pni", H, uv1)  # [P, N, 3]
        z = q[..., 2]
        zs = torch.where(z.abs() > EPS, z, torch.full_like(z, EPS))
        hn, wn = nb.gray.shape
        gx = (q[..., 0] / zs + 0.5) / wn * 2 - 1
        gy = (q[..., 1] / zs + 0.5) / hn * 2 - 1
        inside = (z > EPS) & (gx.abs() <= 1) & (gy.abs() <= 1)
        img = torch.from_numpy(nb.gray).float()[None, None].expand(len(planes), 1, hn, wn)
        grid = torch.stack([gx, gy], -1).reshape(len(planes), h, w, 2)
        warped = F.grid_sample(img, grid, align_corners=False, padding_mode="border")
        b = warped.reshape(len(planes), -1).double().numpy()
        m = (inside.numpy() & ok).astype(np.float64)  # [P, N]
        n = (onehot @ m.T).T  # [P, S]
        sa = (onehot @ (m * a[None]).T).T
        sb = (onehot @ (m * b).T).T
        saa = (onehot @ (m * (a * a)[None]).T).T
        sbb = (onehot @ (m * b * b).T).T
        sab = (onehot @ (m * a[None] * b).T).T
        nn = np.maximum(n, 1.0)
        cov = sab - sa * sb / nn
        va = np.maximum(saa - sa * sa / nn, 0.0)
        vb = np.maximum(sbb - sb * sb / nn, 0.0)
        zncc = cov / np.sqrt(va * vb + EPS * nn)
        cst = (1 - np.clip(zncc, -1, 1)) / 2
        per.append(np.where(n >= 0.5 * area[None], cst, np.nan).T)  # [S, P]
    if not per:
        return np.zeros((len(area), len(planes)))
    stack = np.sort(np.stack(per), axis=0)  # NaN last
    best = max(1, len(per) // 2)
    with np.errstate(invalid="ignore"):
        cnt = np.sum(np.isfinite(stack[:best]), axis=0)
        mean = np.nansum(stack[:best], axis=0) / np.maximum(cnt, 1)
    mean = np.where(cnt > 0, mean, 0.5)
    return tex[:, None] * mean


def graph(
    seg: np.ndarray, rgb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Superpixel adjacency: edges [E, 2] (i < j), boundary length [E], boundary centre
    pixel [E, 2] (u, v), RGB distance of the two superpixels' means [E]."""
    h, w = seg.shape
    s_n = int(seg.max()) + 1
    a = np.concatenate([seg[:, :-1].reshape(-1), seg[:-1].reshape(-1)])
    b = np.concatenate([seg[:, 1:].reshape(-1), seg[1:].reshape(-1)])
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    mu = np.concatenate([(uu[:, :-1] + 0.5).reshape(-1), uu[:-1].reshape(-1)])
    mv = np.concatenate([vv[:, :-1].reshape(-1), (vv[:-1] + 0.5).reshape(-1)])
    diff = a != b
    lo, hi = np.minimum(a, b)[diff], np.maximum(a, b)[diff]
    key = lo * s_n + hi
    uniq, inv, length = np.unique(key, return_inverse=True, return_counts=True)
    edges = np.stack([uniq // s_n, uniq % s_n], 1)
    cu = np.bincount(inv, weights=mu[diff]) / length
    cv = np.bincount(inv, weights=mv[diff]) / length
    flat = seg.reshape(-1)
    area = np.bincount(flat, minlength=s_n).astype(np.float64)
    mean = (
        np.stack(
            [np.bincount(flat, weights=rgb[..., k].reshape(-1), minlength=s_n) for k in range(3)], 1
        )
        / np.maximum(area, 1)[:, None]
    )
    dist = np.linalg.norm(mean[edges[:, 0]] - mean[edges[:, 1]], axis=1)
    return edges, length.astype(np.float64), np.stack([cu, cv], 1), dist

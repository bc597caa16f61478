"""The views at the working size, and each view's neighbours."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from stages.common.errors import BlunfError
from stages.common.io import gray
from stages.depth.consistency import overlap_order
from stages.depth.planes.config import PlanesConfig
from stages.depth.planes.geometry import scale_K
from stages.depth.planes.view import ViewData


def view_data(
    images: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    depths: list[np.ndarray],
    cfg: PlanesConfig,
    sparse: list[np.ndarray] | None = None,
) -> list[ViewData]:
    """Every view's photo (area-averaged) and readings (nearest) at the working width; with
    sparse, the SfM tracks fill in where stereo has no reading (a track on a plain wall
    tells a plane in front of it from the wall itself)."""
    out = []
    for i, (img, K, pose, d) in enumerate(zip(images, Ks, poses, depths, strict=True)):
        img = np.asarray(img, np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or d.ndim != 2:
            raise BlunfError(f"depth.planes: view {i}: image must be HxWx3 and depth HxW")
        H, W = img.shape[:2]
        h, w = d.shape
        ww = min(cfg.width, W)
        hw = max(1, int(round(H * ww / W)))
        t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
        rgb = F.interpolate(t, size=(hw, ww), mode="area")[0].numpy().transpose(1, 2, 0)
        rgb = np.clip(np.nan_to_num(rgb), 0, 1).astype(np.float32)
        rows = np.minimum(((np.arange(hw) + 0.5) * h / hw).astype(np.int64), h - 1)
        cols = np.minimum(((np.arange(ww) + 0.5) * w / ww).astype(np.int64), w - 1)
        p = np.asarray(pose, np.float64)
        dw = d[rows][:, cols]
        if sparse is not None and cfg.tracks:
            sv, su = np.nonzero(sparse[i] > 0)
            tv = np.minimum((sv * hw / H).astype(np.int64), hw - 1)
            tu = np.minimum((su * ww / W).astype(np.int64), ww - 1)
            free = dw[tv, tu] == 0
            dw = dw.copy()
            dw[tv[free], tu[free]] = sparse[i][sv[free], su[free]]
        out.append(
            ViewData(
                rgb=rgb,
                gray=gray(rgb),
                K=scale_K(K, ww / W, hw / H),
                pose=p,
                depth=dw,
                depth_full=d,
                K_full=scale_K(K, w / W, h / H),
            )
        )
    return out


def neighbours(views: list[ViewData], k: int) -> list[list[int]]:
    """Per view the k others overlapping it most (by their readings), topped up with the
    nearest cameras looking the same way where readings are too few to tell."""
    order = overlap_order(
        [v.depth_full for v in views], [v.K_full for v in views], [v.pose for v in views]
    )
    centres = np.stack([v.pose[:3, 3] for v in views])
    axes = np.stack([v.pose[:3, 2] for v in views])
    out = []
    for i, o in enumerate(order):
        pick = list(o[:k])
        if len(pick) < k:
            dist = np.linalg.norm(centres - centres[i], axis=1) + (1 - axes @ axes[i])
            for j in np.argsort(dist, kind="stable"):
                if j != i and j not in pick and len(pick) < k:
                    pick.append(int(j))
        out.append(pick)
    return out


def at_size(img: np.ndarray, like: np.ndarray) -> np.ndarray:
    """img [H, W, C] sampled (nearest pixel centre) at like's h x w."""
    H, W = img.shape[:2]
    h, w = like.shape[:2]
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    return img[rows][:, cols]

"""Training views: pixels as flat tensors, their rays with targets, the depth points."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from stages.common.camera import Intrinsics, depth_to_points
from stages.common.capture import UNKNOWN, Capture, heldout_views
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label
from stages.common.radiance.rays import camera_rays


@dataclass
class Views:
    """Per-view pixels as flat tensors (row-major, H W of each view)."""

    stems: list[str]
    rgb: list[Tensor]  # [HW, 3] in [0, 1]
    depth: list[Tensor | None]  # [HW] z-depth metres, 0 = missing
    label: list[Tensor | None]  # [HW] class index into class_ids, -1 = ignored
    class_ids: list[int]


def load_views(cap: Capture, use_labels: bool) -> Views:
    """Read images, depth (capture units -> metres) and labels (ids -> contiguous indices)."""
    class_ids = sorted(cap.classes) if (use_labels and cap.has_labels and cap.classes) else []
    lut = np.full(65536, -1, np.int64)
    for i, c in enumerate(class_ids):
        if c != UNKNOWN:
            lut[c] = i
    v = Views([], [], [], [], class_ids)
    for f in cap.frames:
        img = read_image(f.image)
        if img.shape[:2] != (f.intrinsics.height, f.intrinsics.width):
            raise BlunfError(
                f"{f.image}: image is {img.shape[1]}x{img.shape[0]}, intrinsics say "
                f"{f.intrinsics.width}x{f.intrinsics.height}"
            )
        v.stems.append(f.stem)
        v.rgb.append(torch.from_numpy(img.reshape(-1, 3).astype(np.float32) / 255.0))
        d = None
        if f.depth is not None:
            dm = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
            if dm.shape != img.shape[:2]:
                raise BlunfError(f"{f.depth}: depth size {dm.shape} differs from its image")
            d = torch.from_numpy(dm.reshape(-1))
        v.depth.append(d)
        lab = None
        if class_ids and f.label is not None:
            lm = read_label(f.label)
            if lm.shape != img.shape[:2]:
                raise BlunfError(f"{f.label}: label size {lm.shape} differs from its image")
            lab = torch.from_numpy(lut[np.clip(lm, 0, 65535)].reshape(-1))
        v.label.append(lab)
    return v


def binned(cap: Capture, views: Views, k: int) -> tuple[Capture, Views]:
    """`cap` and its `views` at 1/k resolution, k x k pixel blocks (rows and columns beyond
    the whole blocks dropped, as the stereo sweep bins them): a block's mean colour, the
    nearest of its depth readings (0 = none), its centre pixel's label; each frame's
    intrinsics those of the binned image (stereo.scaled_K)."""
    frames, out = [], Views(list(views.stems), [], [], [], views.class_ids)
    for i, f in enumerate(cap.frames):
        k_ = f.intrinsics
        h, w = k_.height // k, k_.width // k
        if h < 1 or w < 1:
            raise BlunfError(f"{f.image}: {k_.width}x{k_.height} has no {k}x{k} block")
        hw = (k_.height, k_.width)
        out.rgb.append(_blocks(views.rgb[i], hw, k).mean(dim=(1, 3)).reshape(-1, 3))
        d = views.depth[i]
        if d is not None:
            b = _blocks(d, hw, k)
            near = torch.where(b > 0, b, torch.inf).amin(dim=(1, 3)).reshape(-1)
            d = torch.where(torch.isfinite(near), near, 0.0)
        out.depth.append(d)
        lab = views.label[i]
        if lab is not None:
            lab = _blocks(lab, hw, k)[:, k // 2, :, k // 2, 0].reshape(-1)
        out.label.append(lab)
        intr = Intrinsics(
            k_.fx / k, k_.fy / k, (k_.cx + 0.5) / k - 0.5, (k_.cy + 0.5) / k - 0.5, w, h, k_.dist
        )
        frames.append(replace(f, intrinsics=intr))
    return cap.with_frames(frames), out


def _blocks(t: Tensor, hw: tuple[int, int], k: int) -> Tensor:
    """A view's flat pixels [H * W, ...] as whole k x k blocks [H // k, k, W // k, k, C]."""
    h, w = hw[0] // k, hw[1] // k
    img = t.view(hw[0], hw[1], -1)[: h * k, : w * k]
    return img.reshape(h, k, w, k, img.shape[-1])


def split(n: int, every: int) -> tuple[list[int], list[int]]:
    """(training, held-out) view indices: index % every == every // 2 is held out."""
    held = heldout_views(n, every)
    return [i for i in range(n) if i not in held], held


def depth_points(cap: Capture, views: Views, idx: list[int], stride: int) -> np.ndarray:
    """World points [N, 3] of the depth maps of views `idx` at a pixel stride."""
    pts = []
    for i in idx:
        d = views.depth[i]
        if d is None:
            continue
        f = cap.frames[i]
        h, w = f.intrinsics.height, f.intrinsics.width
        p, _ = depth_to_points(d.view(h, w).numpy(), f.intrinsics.K, np.asarray(f.pose), stride)
        pts.append(p)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def depth_coverage(views: Views, idx: list[int]) -> float:
    """Fraction of the pixels of views `idx` with a depth reading (0 without depth)."""
    n = sum(len(views.rgb[i]) for i in idx)
    k = sum(int((d > 0).sum()) for i in idx if (d := views.depth[i]) is not None)
    return k / max(1, n)


def seed_points(cap: Capture, views: Views, idx: list[int]) -> Iterator[np.ndarray]:
    """World points [N, 3] of every valid depth pixel, one view of `idx` at a time."""
    for i in idx:
        pts = depth_points(cap, views, [i], 1)
        if len(pts):
            yield pts


@dataclass
class Rays:
    """Flat rays of several views, with their targets."""

    origins: Tensor  # [N, 3]
    dirs: Tensor  # [N, 3] unit
    rgb: Tensor  # [N, 3]
    t_depth: Tensor | None  # [N] ray distance of the depth reading, 0 = missing
    label: Tensor | None  # [N] class index, -1 = ignored
    # [N] ray distance at which the ray passes a nearer reading of a neighbouring pixel (a
    # silhouette beside it), 0 = none; see `nearer_neighbour`
    t_edge: Tensor | None = None
    with_depth: Tensor = field(init=False)  # [M] indices of the rays with a depth reading
    edges: Tensor = field(init=False)  # [K] indices of the rays with t_edge > 0

    def __post_init__(self) -> None:
        # found once: SfM tracks cover ~2 % of the pixels, so the depth losses draw from
        # these indices rather than from all pixels (98 % of those draws would be wasted)
        none = torch.empty(0, dtype=torch.long)
        t = self.t_depth
        self.with_depth = none if t is None else (t > 0).nonzero()[:, 0]
        self.edges = none if self.t_edge is None else (self.t_edge > 0).nonzero()[:, 0]


def nearer_neighbour(depth: np.ndarray, radius: int, gap: float) -> np.ndarray:
    """Per pixel, the nearest z-depth within `radius` pixels when it is more than `gap` metres
    nearer than the pixel's own reading, else 0. depth [H, W] metres (0 = missing) -> [H, W].

    Such a pixel lies beside a silhouette: its ray passes the nearer surface at about that
    depth and, the reading says, misses it. A grey erosion (scipy's minimum filter over a
    square window) finds the neighbour; missing readings never count as nearer.
    """
    z = np.where(depth > 0, depth, np.inf).astype(np.float32)
    near = ndimage.minimum_filter(z, size=2 * radius + 1, mode="nearest")
    edge = (depth > 0) & np.isfinite(near) & (near < depth - gap)
    return np.where(edge, near, 0.0).astype(np.float32)


def gather_rays(
    cap: Capture, views: Views, idx: list[int], edge_radius: int = 0, edge_gap: float = 0.1
) -> Rays:
    """All pixels of views `idx` as rays; depth only when every one of them has depth.
    With `edge_radius` > 0 (dense depth), the rays beside a nearer reading get `t_edge`
    (`nearer_neighbour` with that radius and gap)."""
    o: list[Tensor] = []
    d: list[Tensor] = []
    c: list[Tensor] = []
    t: list[Tensor] = []
    te: list[Tensor] = []
    lab: list[Tensor] = []
    with_depth = all(views.depth[i] is not None for i in idx)
    with_label = all(views.label[i] is not None for i in idx) and bool(views.class_ids)
    for i in idx:
        f = cap.frames[i]
        oi, di, zs = camera_rays(np.asarray(f.pose), f.intrinsics)
        o.append(oi)
        d.append(di)
        c.append(views.rgb[i])
        depth_i, label_i = views.depth[i], views.label[i]
        if with_depth:
            assert depth_i is not None  # with_depth: every view of idx has depth
            t.append(depth_i / zs)
            if edge_radius > 0:
                h, w = f.intrinsics.height, f.intrinsics.width
                near = nearer_neighbour(depth_i.numpy().reshape(h, w), edge_radius, edge_gap)
                te.append(torch.from_numpy(near.reshape(-1)) / zs)
        if with_label:
            assert label_i is not None  # with_label: every view of idx has labels
            lab.append(label_i)
    return Rays(
        torch.cat(o),
        torch.cat(d),
        torch.cat(c),
        torch.cat(t) if with_depth else None,
        torch.cat(lab) if with_label else None,
        torch.cat(te) if te else None,
    )

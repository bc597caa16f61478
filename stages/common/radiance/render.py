"""Volume rendering of a field given as functions: rays -> colour, depth, opacity, classes.

`render_rays` marches (marching.py), queries the field once per sample batch and composites
(compositing.py). Because the field enters only through `FieldFns`, another stage can wrap
them (zero the density inside a box, recolour a region) without touching the training code.
`render_field` / `render_view` / `top_view_labels` render a trained `RadianceField` with its
scene box, occupancy grid, step and pruning.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TypedDict

import numpy as np
import torch
from torch import Tensor

from stages.common.blueprint import Grid
from stages.common.camera import Intrinsics
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.common.radiance.compositing import RenderOut, accumulate, accumulate_blocks, finish
from stages.common.radiance.field import FieldFns, RadianceField
from stages.common.radiance.marching import early_stop, march
from stages.common.radiance.occupancy import Occupancy
from stages.common.radiance.rays import camera_rays, ray_box


@dataclass(frozen=True)
class RenderOptions:
    """How `render_rays` samples and composites."""

    near: float | Tensor = 0.0  # scalar or [R]; far < near is treated as far = near
    far: float | Tensor = 1.0  # scalar or [R]
    step: float = 0.01  # marching step (metres)
    occupancy: Occupancy | None = None  # None: every point may hold density
    perturb: bool = False  # jitter each sample inside its interval (training), else middle
    gen: torch.Generator | None = None  # draws of the jitter
    background: Tensor | None = None  # [3] colour added with weight 1 - acc (default black)
    prune_eps: float = 1e-4  # skip samples after transmittance < this (first pass, no grad)
    return_samples: bool = False  # also return ray [N], t [N], weights [N] of the samples
    # colour each ray once, at its expected depth, instead of compositing the colours of its
    # samples (sharp for a depth-supervised field, whose density is a thin shell: off-surface
    # samples would blend colours the field never fitted)
    surface_color: bool = False
    color: bool = True  # False: no colour asked of the field (rgb black but the background)


def render_rays(origins: Tensor, dirs: Tensor, field: FieldFns, opts: RenderOptions) -> RenderOut:
    """Render rays origins, dirs [R, 3] (unit directions, t in metres) through `field`.

    Returns rgb [R, 3], depth [R] (expected ray distance t, = far where acc = 0), acc [R],
    semantics [R, K] logits (None when the field gives none); with return_samples also
    ray [N], t [N], weights [N].
    """
    if opts.surface_color and opts.color:
        out = render_rays(
            origins, dirs, field, replace(opts, surface_color=False, color=False, background=None)
        )
        hit = (out["acc"] > 1e-6).nonzero().squeeze(1)
        rgb = torch.zeros(len(origins), 3)
        if len(hit):
            x = origins[hit] + out["depth"][hit, None] * dirs[hit]
            c = field.query(x, dirs[hit]).rgb
            assert c is not None  # asked with directions
            rgb = rgb.index_put((hit,), out["acc"][hit, None] * c)
        if opts.background is not None:
            rgb = rgb + (1.0 - out["acc"])[:, None] * opts.background
        out["rgb"] = rgb
        return out
    s = march(origins, dirs, opts.near, opts.far, opts.step, opts.occupancy, opts.gen, opts.perturb)
    d = dirs if opts.color else None
    if opts.prune_eps > 0 and len(s.x) and not torch.is_grad_enabled():
        sums = accumulate_blocks(field.query, d, s, opts.prune_eps)
        return finish(sums, s.near, s.far, opts.background, opts.return_samples)
    if opts.prune_eps > 0 and len(s.x):
        s = s.take(early_stop(field.sigma, s, opts.prune_eps))
    f = field.query(s.x, None if d is None else d[s.ray])  # no sample: an empty query
    rgb = f.rgb if f.rgb is not None else torch.zeros(len(s.x), 3)  # [N, 3]
    sums = accumulate(s, f.sigma, rgb, f.logits, False)
    return finish(sums, s.near, s.far, opts.background, opts.return_samples)


@dataclass(frozen=True)
class FieldRender:
    """How `render_field` renders a trained field's rays (beyond its own box and grid)."""

    near: float | None = None  # metres; None: the field's sampling.near
    far: Tensor | None = None  # [R] metres: cuts rays shorter than the box
    perturb: bool = False  # jittered samples (training)
    gen: torch.Generator | None = None
    prune: bool = True  # False: no transmittance pre-pass (every sample keeps its gradient)
    return_samples: bool = False
    surface_color: bool | None = None  # None: as the field was trained
    color: bool = True  # False: depth and opacity only


def render_field(
    field: RadianceField,
    origins: Tensor,
    dirs: Tensor,
    fns: FieldFns,
    how: FieldRender = FieldRender(),  # noqa: B008 (frozen: never changed)
) -> RenderOut:
    """`render_rays` of `fns` (the field's own, or an edited one) inside the field's scene
    box, with its occupancy grid, step and pruning."""
    t_in, t_out = ray_box(origins, dirs, field.lo, field.hi)
    if how.far is not None:
        t_out = torch.minimum(t_out, how.far)
    n = field.sampling.near if how.near is None else how.near
    opts = RenderOptions(
        near=t_in.clamp(min=n),
        far=t_out,
        step=field.step,
        occupancy=field.occupancy,
        perturb=how.perturb,
        gen=how.gen,
        prune_eps=field.sampling.prune_eps if how.prune else 0.0,
        return_samples=how.return_samples,
        surface_color=field.surface_color if how.surface_color is None else how.surface_color,
        color=how.color,
    )
    return render_rays(origins, dirs, fns, opts)


class ViewOut(TypedDict):
    """What `render_view` returns (a plain dict at run time)."""

    rgb: np.ndarray  # [H, W, 3] in [0, 1]
    depth: np.ndarray  # [H, W] z-depth (metres)
    acc: np.ndarray  # [H, W]
    semantics: np.ndarray | None  # [H, W] uint8 class ids; None without a semantic head


@torch.no_grad()
def render_view(
    field: RadianceField,
    pose: np.ndarray,
    intr: Intrinsics,
    chunk: int = 16384,
    color: bool = True,
    pixels: np.ndarray | None = None,
) -> ViewOut:
    """Render a full view: rgb [H, W, 3] in [0, 1], depth [H, W] (z along the optical axis,
    metres), acc [H, W], semantics [H, W] uint8 class ids (255 where acc < acc_threshold)
    or None when the field has no semantic head. `color` False: depth and opacity only
    (rgb black, semantics None), without the colour queries (~40 % of the time). `pixels`
    (bool [H, W]): only those are rendered, the others are 0 (no opacity: unknown class)."""
    o, d, zs = camera_rays(pose, intr)
    h, w = intr.height, intr.width
    if pixels is not None:
        if pixels.shape != (h, w):
            raise BlunfError(f"render_view: pixel mask of {pixels.shape} for a {h}x{w} view")
        sel = torch.from_numpy(np.flatnonzero(pixels))
        o, d, zs = o[sel], d[sel], zs[sel]
    fns = field.fns(semantics=color)
    how = FieldRender(surface_color=None if color else False, color=color)
    parts: dict[str, list[Tensor]] = {"rgb": [], "depth": [], "acc": [], "sem": []}
    for i in range(0, len(o), chunk):
        out = render_field(field, o[i : i + chunk], d[i : i + chunk], fns, how)
        parts["rgb"].append(out["rgb"])
        parts["depth"].append(out["depth"] * zs[i : i + chunk])
        parts["acc"].append(out["acc"])
        if out["semantics"] is not None:
            parts["sem"].append(out["semantics"].argmax(dim=1))

    def whole(t: list[Tensor], *shape: int) -> np.ndarray:
        """The rendered values [N, ...] in a full view [H, W, ...] (0 where not rendered)."""
        x = torch.cat(t) if t else torch.zeros((0, *shape))
        if pixels is None:
            return x.reshape(h, w, *shape).numpy()
        full = torch.zeros((h * w, *shape), dtype=x.dtype)
        full[sel] = x
        return full.reshape(h, w, *shape).numpy()

    acc = whole(parts["acc"])
    sem = None
    if parts["sem"]:
        ids = np.asarray(field.class_ids, np.uint8)[whole(parts["sem"]).reshape(-1)]
        sem = np.where(acc.reshape(-1) >= field.sampling.acc_threshold, ids, UNKNOWN)
        sem = sem.astype(np.uint8).reshape(h, w)
    return {
        "rgb": np.clip(whole(parts["rgb"], 3), 0, 1),
        "depth": whole(parts["depth"]),
        "acc": acc,
        "semantics": sem,
    }


@torch.no_grad()
def top_view_labels(
    field: RadianceField, grid: Grid, heights: list[float], chunk: int = 16384
) -> dict[float, np.ndarray]:
    """The NeRF top-view baseline: per height, one vertical ray down from each cell centre.

    A cell's label is the semantic argmax at the ray's highest-weight sample (its first
    surface); 255 where the ray's opacity is below acc_threshold. Returns {height: uint8
    [H, W]} (row 0 = highest y, as the grid).
    """
    if field.sem_head is None:
        raise BlunfError("NeRF top view: the model was trained without labels")
    xy = torch.from_numpy(grid.centers().reshape(-1, 2).astype(np.float32))  # [HW, 2]
    ids = np.asarray(field.class_ids, np.uint8)
    # the labels need the weights only: no colour, no logits while marching
    fns = field.fns(semantics=False)
    how = FieldRender(near=0.0, return_samples=True, surface_color=False, color=False)
    out: dict[float, np.ndarray] = {}
    for h in heights:
        labels = np.full(len(xy), UNKNOWN, np.uint8)
        for i in range(0, len(xy), chunk):
            p = xy[i : i + chunk]
            o = torch.cat([p, torch.full((len(p), 1), float(h))], dim=1)
            d = torch.tensor([0.0, 0.0, -1.0]).expand(len(p), 3)
            res = render_field(field, o, d, fns, how)
            ray, t, w = res["ray"], res["t"], res["weights"]
            wmax = torch.zeros(len(p)).scatter_reduce(0, ray, w, "amax")
            top = w >= wmax[ray]
            t_top = torch.full((len(p),), float("inf")).scatter_reduce(0, ray[top], t[top], "amin")
            hit = (res["acc"] >= field.sampling.acc_threshold) & torch.isfinite(t_top)
            if hit.any():
                x = o[hit] + t_top[hit, None] * d[hit]
                cls = field.logits(x).argmax(dim=1).numpy()
                labels[i : i + chunk][hit.numpy()] = ids[cls]
        out[float(h)] = labels.reshape(grid.shape)
    return out

"""Rendering with edits: the NeRF renderer fed with the wrapped field, plus selection masks.

A selection's mask in a view is the accumulated weight of the ray samples inside its extent
(thresholded by the caller, 0.5 by default). Masks are rendered on the field they are given:
render them with no edits (the unedited scene) so a removed object still has its mask.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from stages.common.camera import Intrinsics
from stages.common.radiance.compositing import RenderOut
from stages.common.radiance.field import FieldFns, RadianceField
from stages.common.radiance.rays import camera_rays
from stages.common.radiance.render import FieldRender, RenderOptions, render_field, render_rays
from stages.edit.ops import FieldEdit, fill_ground, wrap_field
from stages.edit.select import Extent


@torch.no_grad()
def render_rays_edited(
    origins: Tensor,
    dirs: Tensor,
    field: FieldFns,
    opts: RenderOptions,
    edits: Sequence[FieldEdit] = (),
    masks: Sequence[Extent] = (),
) -> dict[str, Tensor]:
    """`render_rays` on the field with `edits` applied.

    Args:
        origins, dirs: [R, 3] world rays (unit directions). field, opts: as `render_rays`
            (with opts.surface_color the edited colour is read at the expected depth).
        masks: extents whose per-ray weight to return.
    Returns:
        rgb [R, 3], depth [R] (ray distance), acc [R], and masks [M, R]: the weight of each
        ray's samples inside each of `masks`.
    """
    opts = replace(opts, return_samples=bool(masks))
    out = render_rays(origins, dirs, wrap_field(field, edits), opts)
    res = _with_masks(out, origins, dirs, masks)
    res["rgb"], res["acc"] = fill_ground(edits, origins, dirs, res["rgb"], res["acc"])
    return res


def _with_masks(
    out: RenderOut, origins: Tensor, dirs: Tensor, masks: Sequence[Extent]
) -> dict[str, Tensor]:
    """rgb, depth, acc of a render, and masks [M, R]: the weight of each ray's samples inside
    each of `masks` (the render must have returned its samples when there are masks)."""
    res: dict[str, Tensor] = {"rgb": out["rgb"], "depth": out["depth"], "acc": out["acc"]}
    r = len(origins)
    if masks:
        ray, t, w = out["ray"], out["t"], out["weights"]  # [N] each
        x = origins[ray] + t[:, None] * dirs[ray]  # [N, 3] the samples' positions
        res["masks"] = torch.stack(
            [torch.zeros(r).index_add(0, ray, w * torch.as_tensor(e.contains(x))) for e in masks]
        )
    else:
        res["masks"] = torch.zeros(0, r)
    return res


@torch.no_grad()
def render_view_edited(
    model: RadianceField,
    pose: np.ndarray,
    intr: Intrinsics,
    edits: Sequence[FieldEdit] = (),
    chunk: int = 16384,
    masks: Sequence[Extent] = (),
) -> dict[str, np.ndarray]:
    """A full view of the edited field, as `stages.common.radiance.render.render_view`
    renders it (the field's box, near plane, occupancy grid, step, pruning and colouring).

    Returns rgb [H, W, 3] in [0, 1], depth [H, W] (z along the optical axis, metres),
    acc [H, W] and masks [M, H, W] (weight inside each of `masks`).
    """
    o, d, zs = camera_rays(pose, intr)
    fns = wrap_field(model.fns(semantics=False), edits)
    how = FieldRender(return_samples=bool(masks))
    parts: dict[str, list[Tensor]] = {"rgb": [], "depth": [], "acc": [], "masks": []}
    for i in range(0, len(o), chunk):
        oc, dc = o[i : i + chunk], d[i : i + chunk]
        out = _with_masks(render_field(model, oc, dc, fns, how), oc, dc, masks)
        out["rgb"], out["acc"] = fill_ground(edits, oc, dc, out["rgb"], out["acc"])
        parts["rgb"].append(out["rgb"])
        parts["depth"].append(out["depth"] * zs[i : i + chunk])
        parts["acc"].append(out["acc"])
        parts["masks"].append(out["masks"])
    h, w = intr.height, intr.width
    return {
        "rgb": torch.cat(parts["rgb"]).view(h, w, 3).clamp(0, 1).numpy(),
        "depth": torch.cat(parts["depth"]).view(h, w).numpy(),
        "acc": torch.cat(parts["acc"]).view(h, w).numpy(),
        "masks": torch.cat(parts["masks"], dim=1).view(len(masks), h, w).numpy(),
    }


def orbit_poses(
    center: tuple[float, float, float], radius: float, height: float, frames: int
) -> np.ndarray:
    """Cameras on a horizontal circle at z = height around `center`, each looking at it.

    Returns [F, 4, 4] camera-to-world (OpenCV axes), the first camera at +x of the centre,
    going counter-clockwise seen from above.
    """
    c = np.asarray(center, np.float64)
    poses = []
    for k in range(frames):
        a = 2.0 * math.pi * k / frames
        pos = np.array([c[0] + radius * math.cos(a), c[1] + radius * math.sin(a), height])
        poses.append(look_at(pos, c))
    return np.stack(poses)


def look_at(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] at `pos` looking at `target`, image x horizontal (z up)."""
    fwd = np.asarray(target, np.float64) - np.asarray(pos, np.float64)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: pick x as right
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, fwd], axis=1)
    pose[:3, 3] = pos
    return pose

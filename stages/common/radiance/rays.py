"""Rays: through a pinhole camera's pixels, and where they cross the scene box."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from stages.common.camera import Intrinsics


def camera_rays(pose: np.ndarray, intr: Intrinsics) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through every pixel centre (integer u, v). Returns origins [HW, 3], unit dirs
    [HW, 3] and z_scale [HW] (z-depth = ray distance * z_scale), row-major."""
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    d_cam = np.stack(
        [(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1
    ).reshape(-1, 3)  # [HW, 3]
    norm = np.linalg.norm(d_cam, axis=1)
    dirs = (d_cam / norm[:, None]) @ np.asarray(pose)[:3, :3].T
    origins = np.broadcast_to(np.asarray(pose)[:3, 3], dirs.shape)
    return (
        torch.from_numpy(np.ascontiguousarray(origins, np.float32)),
        torch.from_numpy(dirs.astype(np.float32)),
        torch.from_numpy((1.0 / norm).astype(np.float32)),
    )


def ray_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test: (t_enter [R], t_exit [R]); t_exit < t_enter when the ray misses the box."""
    d = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    a = (lo - origins) / d
    b = (hi - origins) / d
    return torch.minimum(a, b).amax(dim=1), torch.maximum(a, b).amin(dim=1)

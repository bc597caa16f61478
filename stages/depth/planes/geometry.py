"""Plane depth along pixel rays, plane validity and plane-induced homographies."""

from __future__ import annotations

import numpy as np

from stages.common.classes import FLOOR_NAME
from stages.depth.planes.hypotheses import FURNITURE_KINDS, Plane

MIN_DEPTH = 0.05  # metres: a plane closer than this along a ray is not a surface seen
MIN_COS = 0.08  # |cos| between ray and plane normal below this: grazing, depth unstable
FLOOR_TOL = 0.05  # metres a plane point may lie below the floor plane


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of the same camera with the image scaled by (sx, sy) (pixel centres at
    integers, as `Intrinsics.scaled`)."""
    k = np.array(K, np.float64)
    k[0, 0] *= sx
    k[1, 1] *= sy
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return k


def rays(uv: np.ndarray, K: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World directions [N, 3] of pixels uv [N, 2] with unit z in the camera (so that the
    point at z-depth t is centre + t * ray)."""
    x = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], -1) @ np.asarray(pose, np.float64)[:3, :3].T


def plane_depth(r: np.ndarray, centre: np.ndarray, planes: list[Plane]) -> np.ndarray:
    """z-depth [P, N] of each plane along rays r [N, 3] from centre; 0 where the plane is
    behind, grazing or nearer than MIN_DEPTH."""
    if not planes:
        return np.zeros((0, len(r)))
    n = np.stack([p.normal for p in planes])  # [P, 3]
    d = np.array([p.offset for p in planes])  # [P]
    den = n @ r.T  # [P, N]
    num = (d - n @ centre)[:, None]
    rn = np.linalg.norm(r, axis=1)[None]
    ok = np.abs(den) > MIN_COS * np.maximum(rn, 1e-12)
    t = num / np.where(ok, den, 1.0)
    return np.where(ok & (t > MIN_DEPTH), t, 0.0)


def plane_valid(
    t: np.ndarray,
    r: np.ndarray,
    centre: np.ndarray,
    planes: list[Plane],
    margin: float | tuple[float, float],
    ceiling: float | None,
) -> np.ndarray:
    """[P, N] True where plane p's point along ray n is a possible surface: in front of the
    camera, not below the floor nor above the ceiling, within `margin` of its inliers' box
    and of its inliers' cells where it has them (margin: one for all, or (floor, wall and
    ceiling; top and front))."""
    ok = t > 0
    m2 = margin if isinstance(margin, tuple) else (margin, margin)
    floor = next((p for p in planes if p.kind == FLOOR_NAME), None)
    up, base = (floor.normal, floor.offset) if floor else (np.array([0.0, 0.0, 1.0]), 0.0)
    for k, p in enumerate(planes):
        x = centre + t[k][:, None] * r  # [N, 3]
        m = m2[1] if p.kind in FURNITURE_KINDS else m2[0]
        inside = np.all((x >= p.lo - m) & (x <= p.hi + m), axis=1)
        if p.cells is not None:  # and within `m` of the cells its inliers fill
            inside[inside] = p.cells.near(x[inside], m)
        height = x @ up - base  # above the floor plane
        z_ok = height >= -FLOOR_TOL
        if ceiling is not None:
            z_ok &= height <= ceiling - base + FLOOR_TOL
        ok[k] &= inside & z_ok
    return ok


def homographies(
    K_ref: np.ndarray,
    pose_ref: np.ndarray,
    K_nb: np.ndarray,
    pose_nb: np.ndarray,
    planes: list[Plane],
) -> np.ndarray:
    """[P, 3, 3] maps from the reference view's pixels to the neighbour's induced by each
    plane: H = K_n (R + t n_c^T / d_c) K_r^-1 (n_c . X = d_c the plane in the reference
    camera, R, t the reference-to-neighbour motion). A plane through the camera centre
    (d_c ~ 0) gets the identity's rotation part only (it is invalid there anyway)."""
    R_r, c_r = pose_ref[:3, :3], pose_ref[:3, 3]
    R_n, c_n = pose_nb[:3, :3], pose_nb[:3, 3]
    R = R_n.T @ R_r
    t = R_n.T @ (c_r - c_n)
    Ki = np.linalg.inv(K_ref)
    out = np.zeros((len(planes), 3, 3))
    for k, p in enumerate(planes):
        n_c = R_r.T @ p.normal
        d_c = p.offset - p.normal @ c_r
        d_c = d_c if abs(d_c) > 1e-6 else 1e-6
        out[k] = K_nb @ (R + np.outer(t, n_c) / d_c) @ Ki
    return out

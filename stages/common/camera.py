"""Pinhole cameras and the projection Π between pixels with depth and world points.

Conventions: camera-to-world 4x4 poses, OpenCV camera axes (x right, y down, z forward),
world in metres with z up. Written in numpy (a few matrix products) because every caller
holds numpy arrays; kornia's equivalents would only add torch round trips.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, with optional OpenCV distortion (k1, k2, p1, p2[, k3])."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise BlunfError(f"intrinsics: focal lengths must be finite and > 0, got {vals}")
        if self.width <= 0 or self.height <= 0:
            raise BlunfError(f"intrinsics: image size must be > 0, got {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """[3, 3] float64 calibration matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float64)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution. Pixel centres are integers here, so the
        principal point scales about the image's corner at (-0.5, -0.5). At its own size,
        itself (the round trip of cx through the corner would move it by a rounding)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        cx, cy = (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        return Intrinsics(self.fx * sx, self.fy * sy, cx, cy, width, height, self.dist)

    def to_json(self) -> dict:
        d = {k: getattr(self, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}
        if self.dist:
            d["dist"] = list(self.dist)
        return d

    @staticmethod
    def from_json(d: dict, where: str = "intrinsics") -> Intrinsics:
        try:
            return Intrinsics(
                float(d["fx"]),
                float(d["fy"]),
                float(d["cx"]),
                float(d["cy"]),
                int(d["width"]),
                int(d["height"]),
                tuple(float(x) for x in d.get("dist", ())),
            )
        except KeyError as e:
            raise BlunfError(f"{where}: missing field {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            raise BlunfError(f"{where}: bad value ({e})") from None
        except BlunfError as e:
            raise BlunfError(f"{where}: {e}") from None


def check_pose(pose: np.ndarray, where: str) -> np.ndarray:
    """Validate a 4x4 camera-to-world rigid (or similarity) transform. Returns float64 [4, 4]."""
    try:
        p = np.asarray(pose, np.float64)
    except (TypeError, ValueError):  # ragged nesting, strings
        raise BlunfError(f"{where}: pose must be a finite 4x4 matrix of numbers") from None
    if p.shape != (4, 4) or not np.all(np.isfinite(p)):
        raise BlunfError(f"{where}: pose must be a finite 4x4 matrix")
    if not np.allclose(p[3], [0, 0, 0, 1], atol=1e-6):
        raise BlunfError(f"{where}: pose last row must be [0, 0, 0, 1]")
    r = p[:3, :3]
    s = np.cbrt(np.linalg.det(r))
    if not s > 1e-9 or not np.allclose(r.T @ r / s**2, np.eye(3), atol=1e-3):
        raise BlunfError(f"{where}: pose rotation is not orthonormal")
    return p


def pixel_grid(width: int, height: int, stride: int = 1) -> np.ndarray:
    """Pixel centres (u, v) of a strided grid, starting at stride // 2. Returns [H', W', 2]."""
    u = np.arange(stride // 2, width, stride, dtype=np.float64)
    v = np.arange(stride // 2, height, stride, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv], axis=-1)


def unproject(
    uv: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    c2w: np.ndarray,
    origin: np.ndarray | None = None,
) -> np.ndarray:
    """Π: pixels with depth (z along the optical axis, metres) to world points.

    Args:
        uv: [N, 2] pixel coordinates (u right, v down; integer = pixel centre).
        depth: [N] depth in metres.
        K: [3, 3] intrinsics. c2w: [4, 4] camera-to-world.
        origin: [3] when given, the points come as float32 offsets from it (half the time of
            float64 world points, and no precision lost far from the world's origin).
    Returns:
        [N, 3] world points (float64), or their float32 offsets from `origin`.
    """
    if origin is not None:
        d32 = np.asarray(depth, np.float32)
        pl = np.empty((len(d32), 3), np.float32)  # camera frame
        pl[:, 0] = (uv[:, 0] - K[0, 2]) / K[0, 0]
        pl[:, 1] = (uv[:, 1] - K[1, 2]) / K[1, 1]
        pl[:, :2] *= d32[:, None]
        pl[:, 2] = d32
        rot = np.asarray(c2w[:3, :3], np.float32)
        return pl @ rot.T + np.asarray(c2w[:3, 3] - origin, np.float32)
    uv = np.asarray(uv, np.float64)
    d = np.asarray(depth, np.float64)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    pc = np.stack([x * d, y * d, d], axis=-1)  # [N, 3] camera frame
    return pc @ c2w[:3, :3].T + c2w[:3, 3]


def distorted(
    x: np.ndarray, y: np.ndarray, dist: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised camera coordinates through the OpenCV k1, k2, p1, p2[, k3] model (as they
    are when `dist` is empty or all zero)."""
    if not any(dist):
        return x, y
    k1, k2, p1, p2, k3 = (tuple(dist) + (0.0,) * 5)[:5]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (
        x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def undistort_pixels(uv: np.ndarray, intr: Intrinsics, iters: int = 20) -> np.ndarray:
    """Distorted pixels [N, 2] to ideal pinhole pixels (OpenCV k1, k2, p1, p2[, k3] model);
    `uv` itself when `intr` has no distortion."""
    if not any(intr.dist):
        return np.asarray(uv, np.float64)
    k1, k2, p1, p2, k3 = (tuple(intr.dist) + (0.0,) * 5)[:5]
    xd = (uv[:, 0] - intr.cx) / intr.fx
    yd = (uv[:, 1] - intr.cy) / intr.fy
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):  # fixed point x = (xd - tangential(x)) / radial(x)
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = (xd - dx) / rad, (yd - dy) / rad
    return np.stack([x * intr.fx + intr.cx, y * intr.fy + intr.cy], axis=-1)


def project(
    points: np.ndarray, K: np.ndarray, c2w: np.ndarray, dist: tuple[float, ...] = ()
) -> tuple[np.ndarray, np.ndarray]:
    """Π⁻¹: world points to pixels, through the lens distortion `dist` when it has any.
    Returns (uv [N, 2], depth [N]); depth <= 0 is behind."""
    w2c = np.linalg.inv(c2w)
    pc = np.asarray(points, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
    z = pc[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    if any(dist):
        x, y = distorted(pc[:, 0] / safe, pc[:, 1] / safe, dist)
        return np.stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1), z
    u = K[0, 0] * pc[:, 0] / safe + K[0, 2]
    v = K[1, 1] * pc[:, 1] / safe + K[1, 2]
    return np.stack([u, v], axis=-1), z


def depth_at(
    pts: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    c2w: np.ndarray,
    dist: tuple[float, ...] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """(reading of `depth` at the nearest pixel to each point's projection, through the lens
    distortion `dist`, 0 when outside the view or behind it; the point's z in that view) for
    world points pts [N, 3]."""
    uv, z = project(pts, K, c2w, dist)
    h, w = depth.shape
    u = np.rint(uv[:, 0])
    v = np.rint(uv[:, 1])
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.zeros(len(pts), np.float64)
    d[inside] = depth[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    return d, z


def depth_to_points(
    depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """All valid pixels of a depth map to world points.

    Returns (points [N, 3] float64, flat pixel indices [N] into the strided grid).
    """
    h, w = depth.shape
    uv = pixel_grid(w, h, stride).reshape(-1, 2)
    d = depth[stride // 2 :: stride, stride // 2 :: stride].reshape(-1)
    keep = np.flatnonzero(np.isfinite(d) & (d > 0))
    return unproject(uv[keep], d[keep], K, c2w), keep


def x_axes_square(x_axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit direction most nearly square to every camera's x axis [C, 3], sign free; the
    RMS component of the axes along their three principal directions, largest first [3]).

    A camera held with no roll has its x axis (OpenCV: image right) horizontal whatever its
    pitch, so for level cameras the direction is the world's up and the last RMS the sine of
    their RMS roll; the middle one says how far the axes turn (near 0 when every camera faces
    one way, and the up is then free about them). Used for the metric scale's up
    (stages/poses/scale.py) and the align stage's (stages/align/planes.py).
    """
    x = np.asarray(x_axes, np.float64).reshape(-1, 3)
    # the eigenvectors of the axes' scatter (ascending), as the metric scale has always
    # read them: an SVD of the axes gives the same direction to the last bits only, and
    # the kitchen's plan moves by half a point with its scale's 15th digit
    vals, vecs = np.linalg.eigh(x.T @ x)
    rms = np.sqrt(np.clip(vals[::-1], 0.0, None) / max(len(x), 1))
    return vecs[:, 0], rms

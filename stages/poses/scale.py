"""Metric scale of an up-to-scale reconstruction, from depth maps or from one known length.

Every function returns (scale, facts): multiplying SfM lengths by `scale` gives metres, and
`facts` (JSON-ready) says how the number was found, for sfm.json.
"""

from __future__ import annotations

import numpy as np

from stages.common.errors import BlunfError

FLOOR_PERCENTILE = 2.0  # camera_height: the floor is this low percentile of point heights


def depth_ratios(
    uv: np.ndarray, z: np.ndarray, depth: np.ndarray, image_wh: tuple[int, int]
) -> np.ndarray:
    """Metric depth over SfM depth at one image's observed keypoints.

    Args:
        uv: [N, 2] keypoints in pixels of the image (integer = pixel centre).
        z: [N] the observed 3D points' depths along the optical axis, SfM units.
        depth: [h, w] depth map in metres (0 = missing); may be smaller or larger than the image.
        image_wh: (width, height) of the image the keypoints belong to.
    Returns:
        [M] ratios for the keypoints with a valid reading and z > 0 (M <= N).
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    z = np.asarray(z, np.float64).reshape(-1)
    h, w = depth.shape
    # Pixel u covers [u - 0.5, u + 0.5): shift to edge coordinates, rescale, take the cell.
    col = np.floor((uv[:, 0] + 0.5) * w / image_wh[0]).astype(np.int64)
    row = np.floor((uv[:, 1] + 0.5) * h / image_wh[1]).astype(np.int64)
    keep = (col >= 0) & (col < w) & (row >= 0) & (row < h) & (z > 0)
    d = depth[row[keep], col[keep]].astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    return d[valid] / z[keep][valid]


def scale_from_depth(ratios: list[np.ndarray]) -> tuple[float, dict]:
    """Robust scale: the median of all images' depth ratios (see `depth_ratios`)."""
    per_image = [r for r in ratios if r.size]
    if not per_image:
        raise BlunfError(
            "sfm: scale from depth: no sparse point falls on a valid depth reading "
            "(set poses.scale_from to distance, camera_height or none)"
        )
    r = np.concatenate(per_image)  # [M]
    s = float(np.median(r))
    medians = np.array([np.median(x) for x in per_image])  # [C']
    return s, {
        "method": "depth",
        "how": "median over all registered images of depth-map reading / SfM depth at the "
        "keypoints of observed sparse points (valid readings only)",
        "ratios": int(r.size),
        "images": len(per_image),
        # Median absolute deviation of the ratios, relative to the scale (0 = all agree).
        "spread_rel_mad": float(np.median(np.abs(r / s - 1.0))),
        "per_image_median_min": float(medians.min() / s),
        "per_image_median_max": float(medians.max() / s),
    }


def scale_from_distance(
    first: np.ndarray, last: np.ndarray, known_m: float, stems: tuple[str, str]
) -> tuple[float, dict]:
    """Scale making the distance between two camera centres [3] equal `known_m` metres."""
    d = float(np.linalg.norm(np.asarray(last, np.float64) - np.asarray(first, np.float64)))
    if not d > 1e-9:
        raise BlunfError(
            f"sfm: scale from distance: frames {stems[0]!r} and {stems[1]!r} have the same "
            "camera centre; poses.known_distance cannot fix the scale"
        )
    return known_m / d, {
        "method": "distance",
        "how": f"camera centres of the first and last frames ({stems[0]}, {stems[1]}) are "
        f"{known_m} m apart (poses.known_distance)",
        "sfm_distance": d,
    }


def scale_from_camera_height(
    centers: np.ndarray, y_axes: np.ndarray, points: np.ndarray, height_m: float
) -> tuple[float, dict]:
    """Scale making the cameras' median height above the floor equal `height_m` metres.

    Args:
        centers: [C, 3] camera centres. y_axes: [C, 3] cameras' y axes (image down) in the world.
        points: [N, 3] sparse points; the floor is their FLOOR_PERCENTILE height along "up".
    """
    y = np.asarray(y_axes, np.float64).mean(axis=0)
    if np.linalg.norm(y) < 1e-6 or len(points) == 0:
        raise BlunfError(
            "sfm: scale from camera_height: cannot tell up from the cameras or no sparse points"
        )
    up = -y / np.linalg.norm(y)  # [3]
    floor = float(np.percentile(np.asarray(points, np.float64) @ up, FLOOR_PERCENTILE))
    above = float(np.median(np.asarray(centers, np.float64) @ up - floor))
    if not above > 1e-9:
        raise BlunfError(
            "sfm: scale from camera_height: the cameras are not above the lowest sparse points"
        )
    return height_m / above, {
        "method": "camera_height",
        "how": f"cameras' median height above the floor is {height_m} m (poses.camera_height); "
        "assumes the cameras were held upright (up = minus their mean image-down axis) and "
        f"the floor is the {FLOOR_PERCENTILE:g}th percentile of sparse point heights",
        "sfm_height": above,
    }

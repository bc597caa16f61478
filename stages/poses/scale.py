"""Metric scale of an up-to-scale reconstruction, from depth maps or from one known length.

Every function returns (scale, facts): multiplying SfM lengths by `scale` gives metres, and
`facts` (JSON-ready) says how the number was found, for sfm.json.
"""

from __future__ import annotations

import numpy as np

from stages.common.camera import x_axes_square
from stages.common.errors import BlunfError

FLOOR_PERCENTILE = 2.0  # camera_height: the floor is this low percentile of point heights
#                         when no horizontal surface piles up points below the cameras
HEIGHT_BIN = 0.02  # floor / ceiling search: bin of the height histogram, as a fraction of the
#                    99th percentile of the points' distances below the cameras
PEAK_FRAC = 0.02  # ... a surface holds this fraction of the points on its side (3 bins)
BELOW_FLOOR_MAX = 0.1  # a floor has at most this fraction of the points below the cameras
#                       lying more than FLOOR_MARGIN further down (none can be seen through
#                       it): measured 0.2 % Replica office, 2.6 % 7-Scenes kitchen, 0.1 % the
#                       textured procedural room; 34 % when a smooth floor gives SfM few points
#                       and the chair seats pile up more (blunf synth --realism honest)
FLOOR_MARGIN = 0.05  # ... relative to the floor's depth below the cameras
X_SPAN = 0.05  # up from the x axes needs their second eigenvalue this fraction of the first
PRIOR_CAMERA_HEIGHT = 1.45  # metres: median height of a hand-held camera above the floor
PRIOR_CAMERA_SPREAD = 0.1  # its relative spread (1 sigma). Measured medians: 1.39 m (7-Scenes
#                           kitchen, hand-held Kinect), 1.43 (synthetic rooms), 1.76 (Replica
#                           office renders: a virtual camera higher than people hold a phone)
PRIOR_ROOM_HEIGHT = 2.6  # metres: floor to ceiling of a room (2.4-2.8 in most homes, offices)
PRIOR_ROOM_SPREAD = 0.07  # its relative spread (1 sigma)
ROOM_OVER_CAMERA = (1.4, 2.6)  # a ceiling counts when floor-to-ceiling / camera height is here


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


def up_from_cameras(x_axes: np.ndarray, y_axes: np.ndarray) -> tuple[np.ndarray, str]:
    """The world's up from the cameras' axes [C, 3] (x = image right, y = image down).

    A hand-held camera is rolled little, so its x axis is nearly horizontal whichever way it
    pitches: up is the direction most nearly orthogonal to every x axis (the smallest
    eigenvector of sum x x^T), on the side of minus the mean image-down axis. The mean
    image-down axis alone tilts by the cameras' pitch (23 degrees on a 7-Scenes kitchen
    looking down at its counters; 4 degrees with the x axes). When the x axes span no plane
    (cameras all facing one way) that mean is all there is. Returns (unit up [3], how).
    """
    x = np.asarray(x_axes, np.float64).reshape(-1, 3)
    y0 = -np.asarray(y_axes, np.float64).reshape(-1, 3).mean(axis=0)
    if np.linalg.norm(y0) < 1e-6:
        raise BlunfError("sfm: metric scale: cannot tell up from the cameras (mean axes cancel)")
    y0 /= np.linalg.norm(y0)
    normal, rms = x_axes_square(x)
    if rms[1] ** 2 < X_SPAN * rms[0] ** 2:  # x axes nearly parallel: pitch not observable
        return y0, "minus the cameras' mean image-down axis (their x axes span no plane)"
    up = normal * (1.0 if normal @ y0 >= 0 else -1.0)
    return up, "normal of the cameras' x axes (hand-held cameras are rolled little)"


def _peak(h: np.ndarray, bin_w: float, frac: float) -> float | None:
    """The farthest (largest h) horizontal surface among heights h [N] (> 0, distance below or
    above the cameras): the largest-h bin whose 3-bin window holds `frac` of them and stands
    out of its neighbourhood (twice the median window within 10 bins), climbed to its local
    peak; the median height within 1.5 bins of it. None when no window qualifies."""
    if h.size < 20:
        return None
    idx = np.floor(h / bin_w).astype(np.int64)
    counts = np.bincount(idx, minlength=3)  # [B]
    support = np.convolve(counts, np.ones(3, np.int64), mode="same")  # [B]
    pad = np.pad(support, 10, mode="constant")
    win = np.lib.stride_tricks.sliding_window_view(pad, 21)  # [B, 21]
    ok = (support >= frac * h.size) & (support >= 2 * np.median(win, axis=1))
    cand = np.flatnonzero(ok)
    if not cand.size:
        return None
    i = int(cand[-1])
    while i > 0 and support[i - 1] > support[i]:
        i -= 1
    centre = (i + 0.5) * bin_w
    return float(np.median(h[np.abs(h - centre) <= 1.5 * bin_w]))


def floor_and_ceiling(
    centers: np.ndarray, up: np.ndarray, points: np.ndarray
) -> tuple[float | None, float | None]:
    """(floor's depth below, ceiling's height above) the cameras' median height, in the
    points' units (None when not found). The floor is the lowest horizontal surface that
    piles up points (see _peak: counters and tables lie higher, stray points below the floor
    never pile up), the ceiling the highest above the cameras; heights are binned in
    HEIGHT_BIN of the 99th percentile of the points' distances below the cameras. A pile with
    more than BELOW_FLOOR_MAX of the points under it is no floor (None)."""
    h = np.asarray(points, np.float64).reshape(-1, 3) @ up  # [N]
    cam = float(np.median(np.asarray(centers, np.float64) @ up))
    below, above = cam - h[h < cam], h[h > cam] - cam
    if below.size < 20:
        return None, None
    bin_w = HEIGHT_BIN * float(np.percentile(below, 99))
    floor = _peak(below, bin_w, PEAK_FRAC)
    if floor is not None and np.mean(below > floor * (1 + FLOOR_MARGIN)) > BELOW_FLOOR_MAX:
        floor = None  # seats or table tops: the floor lies further down
    ceiling = _peak(above, bin_w, PEAK_FRAC) if above.size >= 20 else None
    return floor, ceiling


def floor_depth(centers: np.ndarray, up: np.ndarray, points: np.ndarray) -> tuple[float, str]:
    """(the floor's depth below the cameras' median height, how it was found): the lowest
    horizontal surface the points pile up on (floor_and_ceiling), else the FLOOR_PERCENTILE
    lowest point heights (a floor with too little texture for SfM to pile points on)."""
    floor, _ = floor_and_ceiling(centers, up, points)
    if floor is not None:
        return floor, "the lowest horizontal surface the sparse points pile up on"
    h = np.asarray(points, np.float64).reshape(-1, 3) @ up
    if h.size < 20:
        return 0.0, "too few sparse points"
    floor = float(np.median(np.asarray(centers) @ up) - np.percentile(h, FLOOR_PERCENTILE))
    return floor, f"the lowest {FLOOR_PERCENTILE:g} % of point heights (no floor found)"


def scale_from_camera_height(
    centers: np.ndarray,
    x_axes: np.ndarray,
    y_axes: np.ndarray,
    points: np.ndarray,
    height_m: float,
) -> tuple[float, dict]:
    """Scale making the cameras' median height above the floor equal `height_m` metres.

    Args:
        centers: [C, 3] camera centres. x_axes, y_axes: [C, 3] cameras' x (image right) and
            y (image down) axes in the world. points: [N, 3] sparse points.
    """
    up, up_how = up_from_cameras(x_axes, y_axes)
    floor, how_floor = floor_depth(centers, up, points)
    if not floor > 1e-9:
        raise BlunfError(
            "sfm: scale from camera_height: the cameras are not above the lowest sparse points"
        )
    return height_m / floor, {
        "method": "camera_height",
        "how": f"cameras' median height above the floor is {height_m} m (poses.camera_height); "
        f"up: {up_how}; floor: {how_floor}",
        "sfm_height": floor,
    }


def scale_from_priors(
    centers: np.ndarray, x_axes: np.ndarray, y_axes: np.ndarray, points: np.ndarray
) -> tuple[float, dict]:
    """Metric scale with no length given: the cameras' median height above the floor is
    taken to be how high people hold a phone (PRIOR_CAMERA_HEIGHT, relative spread
    PRIOR_CAMERA_SPREAD) and, when the ceiling is seen, the floor-to-ceiling height a room's
    (PRIOR_ROOM_HEIGHT, PRIOR_ROOM_SPREAD); the two are combined in log scale, each weighted
    by the inverse square of its spread. Arguments as scale_from_camera_height.
    Facts: scale, source ("camera_height_prior", "+ceiling"), uncertainty_rel (1 sigma).
    """
    up, up_how = up_from_cameras(x_axes, y_axes)
    _, ceiling = floor_and_ceiling(centers, up, points)
    floor, how_floor = floor_depth(centers, up, points)
    if not floor > 1e-9:
        raise BlunfError(
            "sfm: metric scale: no floor found among the sparse points; set poses.camera_height "
            "or poses.known_distance"
        )
    cues = {"camera_height": (PRIOR_CAMERA_HEIGHT / floor, PRIOR_CAMERA_SPREAD)}
    room = None
    if ceiling is not None:
        room = floor + ceiling
        # a ceiling only when the room it makes is plausible against the camera height: upper
        # cabinets and shelf tops above the cameras are lower than that
        if ROOM_OVER_CAMERA[0] <= room / floor <= ROOM_OVER_CAMERA[1]:
            cues["room_height"] = (PRIOR_ROOM_HEIGHT / room, PRIOR_ROOM_SPREAD)
    w = {k: 1.0 / sd**2 for k, (_, sd) in cues.items()}
    log_s = sum(w[k] * np.log(s) for k, (s, _) in cues.items()) / sum(w.values())
    scale = float(np.exp(log_s))
    return scale, {
        "method": "priors",
        "source": "+".join(cues),
        "how": f"cameras' median height above the floor taken as {PRIOR_CAMERA_HEIGHT} m "
        f"(hand-held, +-{PRIOR_CAMERA_SPREAD:.0%})"
        + (
            f" and floor to ceiling as {PRIOR_ROOM_HEIGHT} m (+-{PRIOR_ROOM_SPREAD:.0%})"
            if "room_height" in cues
            else " (no ceiling seen)"
        )
        + f"; up: {up_how}; floor: {how_floor}",
        "uncertainty_rel": float(1.0 / np.sqrt(sum(w.values()))),
        "per_cue": {k: float(s) for k, (s, _) in cues.items()},
        "camera_height_m": float(floor * scale),
        "room_height_m": float(room * scale)
        if room is not None and "room_height" in cues
        else None,
    }

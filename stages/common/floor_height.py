"""The floor and ceiling among sparse points (SfM tracks): the heights they pile up at.

Shared by the poses stage (metric scale from the cameras' height above the floor) and the
align stage (the floor of a photos-only capture, whose sparse points give few floor normals).
"""

from __future__ import annotations

import numpy as np

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

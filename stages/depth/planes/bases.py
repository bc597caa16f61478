"""Walls that stereo reads nothing on, from the line where they meet the floor.

A plain painted wall gives stereo nothing to match, and often no SfM track either, so no
histogram peak of the points shows it (`hypotheses`), and the outermost vertical plane the
points do show (a cabinet's front, a bed's side) was taken for the wall: the honest
procedural room's walls were filled 0.5-1.2 m inside the room. The wall's foot is still
seen: where the floor meets it runs an image edge (floor and wall differ in colour or
shading), and on the floor plane, which the points do give, that edge is a line along the
wall. Every Canny edge pixel (of any CIELAB channel: a beige floor and a grey wall of one
brightness) is moved to its sub-pixel peak and cast onto the floor plane; it votes for the
offset of a line along a wall axis there when its edge runs along that line's image
direction, the wall's side of it (up the image) is plain, and a reading on its other side,
if any, lies on the floor. A line on the floor lands at one offset from every view; an
edge above the floor lands at a different one from each, so the votes are counted in views
that put a line's worth of pixels (LINE_PX) at an offset. A wall lies beyond every camera:
its foot is the outermost peak on that side held by enough views. This is the floor-wall
boundary of single-view indoor reconstruction (Delage, Lee and Ng, CVPR 2006; Lee, Hebert
and Kanade, CVPR 2009), voted over the views instead of read from one. `find_planes` keeps
a foot only where it is the room's outermost surface on its side and no wall stereo read
lies before it (`hypotheses._foot_walls`): a plain sofa back's top edge against a wall
votes as a foot would.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates, sobel, uniform_filter
from skimage.color import rgb2lab
from skimage.feature import canny

from stages.common.camera import pixel_grid, project
from stages.common.classes import FLOOR_NAME
from stages.depth.planes.config import PlanesConfig
from stages.depth.planes.geometry import plane_depth, rays
from stages.depth.planes.hypotheses import Plane

BIN = 0.02  # metres: offset histogram bin
SIGMA = 1.5  # pixels: Canny's smoothing at the working size
ALIGN_DEG = 15.0  # an edge runs along a floor line when its direction is within this of it
REACH = 12.0  # metres: farther floor points are too grazing to place a line
BEYOND = 0.3  # metres: a wall's foot lies at least this far beyond every camera centre
PATCH = 7  # pixels: the window of the texture measure beside an edge
PLAIN = 2.5  # CIELAB spread under which the wall's side of an edge is plain
EDGE_LOW, EDGE_HIGH = 2.0, 4.0  # Canny's hysteresis thresholds, CIELAB units
LINE_PX = 8  # edge pixels a view's foot line needs at one offset (scattered texture has fewer)
MAX_YAW_DEG = 3.0  # degrees a foot's line may turn from its room axis
YAW_STEP_DEG = 0.5  # ... tried in steps of this; a turn is taken when its foot holds
YAW_GAIN = 0.25  # this share more views than the axis's (and 2 at least)
SHARE = 0.5  # ... and holds at least this share of the views of its side's strongest peak
ON_FLOOR = 0.05  # relative: a reading within this of the floor plane's depth lies on it


def feet_finder(views: list, cfg: PlanesConfig) -> Callable[..., list]:
    """`find_planes`'s `feet` over the views (ViewData at the working size): wall_feet with
    at least cfg.feet_views of them (3 at the fewest)."""
    least = max(3, int(round(cfg.feet_views * len(views))))

    def feet(up: np.ndarray, floor: float, axes: list) -> list:
        rgbs, Ks, poses = [v.rgb for v in views], [v.K for v in views], [v.pose for v in views]
        return wall_feet(rgbs, [v.depth for v in views], Ks, poses, up, floor, axes, least)

    return feet


def wall_feet(
    rgbs: list[np.ndarray],
    depths: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    up: np.ndarray,
    floor: float,
    axes: list[np.ndarray],
    min_views: int,
) -> list[tuple[np.ndarray, float, int]]:
    """Walls from their feet on the floor plane up . X = floor.

    Args:
        rgbs: per view [h, w, 3] image in 0..1 (the working size).
        Ks, poses: the views' intrinsics at that size and camera-to-world poses.
        up: the floor's unit normal; axes: the two wall directions (unit, horizontal).
        min_views: the fewest views whose edges must put a foot at one offset.
        depths: per view [h, w] stereo z-depth at that size (0 = none): a reading on the
            floor's side of a foot (down the image) must lie on the floor (the top edge of
            a sofa against a plain wall has the sofa below it, and lands a few views at one
            offset beyond the wall).
    Returns:
        (normal facing out of the room, offset, views) per wall found: at most one on each
        side of each axis, the outermost peak beyond every camera holding min_views and
        SHARE of its side's strongest.
    """
    if not poses:
        return []
    up = np.asarray(up, np.float64)
    Ks = [np.asarray(K, np.float64) for K in Ks]
    poses = [np.asarray(p, np.float64) for p in poses]
    centres = np.stack([p[:3, 3] for p in poses])
    # each view's edge pixels that may be a foot, whatever the axis; then per axis those
    # running along it
    cands = [
        _candidates(_edges(np.clip(np.asarray(c, np.float64), 0, 1)), z, K, pose, up, floor)
        for c, z, K, pose in zip(rgbs, depths, Ks, poses, strict=True)
    ]
    out = []
    sin_max = np.sin(np.radians(ALIGN_DEG))
    for a in axes:
        # the wall stands on the floor: its normal is the axis made perpendicular to up
        a = np.asarray(a, np.float64) - (np.asarray(a, np.float64) @ up) * up
        a /= max(float(np.linalg.norm(a)), 1e-12)
        along = np.cross(up, a)
        along /= max(float(np.linalg.norm(along)), 1e-12)
        votes = [
            _along(x, g, K, pose, along, sin_max)
            for (x, g), K, pose in zip(cands, Ks, poses, strict=True)
        ]
        votes = [v for v in votes if len(v)]
        if not votes:
            continue
        for sign in (1.0, -1.0):
            # the room's axis may lie a degree or two off a wall no point shows, and a foot
            # line then spreads over many bins: each yaw within MAX_YAW_DEG is tried
            # a turned axis must hold clearly more views than the axis itself (with a few
            # views, a turned band can gather one or two more by chance)
            best = None
            steps = np.arange(-MAX_YAW_DEG, MAX_YAW_DEG + 1e-9, YAW_STEP_DEG)
            for yaw in np.radians(sorted(steps, key=abs)):
                n = np.cos(yaw) * a + np.sin(yaw) * along
                got = _peak(votes, centres, n, sign, min_views)
                if got is None:
                    continue
                if (
                    best is None
                    or got[1:] > best[1][1:]
                    and (yaw == 0 or got[1] >= best[1][1] + max(2, YAW_GAIN * best[1][1]))
                ):
                    best = (n, got)
            if best is None:
                continue
            n, off = _line(np.concatenate(votes), best[0], up, best[1][0])
            out.append((sign * n, sign * off, best[1][1]))
    return out


def _peak(
    votes: list[np.ndarray], centres: np.ndarray, n: np.ndarray, sign: float, min_views: int
) -> tuple[float, int, int] | None:
    """(offset along n, views, pixels) of the foot on the `sign` side of the cameras along
    n: the outermost peak beyond them holding min_views and SHARE of the side's strongest,
    with its views and its votes within a bin either side."""
    offs = centres @ n
    edge = offs.max() if sign > 0 else offs.min()
    lo = float(offs.min()) - REACH
    nbin = int(np.ceil((offs.max() - offs.min() + 2 * REACH) / BIN)) + 1
    views = np.zeros(nbin, np.int64)
    pixels = np.zeros(nbin, np.int64)
    for x in votes:
        b = np.clip(((x @ n - lo) / BIN).astype(np.int64), 0, nbin - 1)
        # a foot is a line: LINE_PX of its pixels within a bin either side (an edge pixel
        # off by one row lands a few cm nearer or farther on a far floor)
        count = np.convolve(np.bincount(b, minlength=nbin), np.ones(3), mode="same")
        views += count >= LINE_PX
        pixels += count.astype(np.int64)
    centre = lo + (np.arange(nbin) + 0.5) * BIN
    side = sign * (centre - edge) >= BEYOND
    if not side.any():
        return None
    best = int(views[side].max())
    if best < min_views:
        return None
    keep = side & (views >= max(min_views, SHARE * best))
    # peaks: the views there at least those of the bins either side
    peak = keep & (views >= np.roll(views, 1)) & (views >= np.roll(views, -1))
    idx = np.flatnonzero(peak)
    if len(idx) == 0:
        return None
    k = idx[np.argmax(sign * centre[idx])]
    return float(centre[k]), int(views[k]), int(pixels[k])


def _line(x: np.ndarray, a: np.ndarray, up: np.ndarray, d0: float) -> tuple[np.ndarray, float]:
    """The wall's normal and offset from its foot's votes x [N, 3] (floor points): a line
    fitted on the floor to the votes within a bin and a half of it, three times from the
    axis a at offset d0, its normal kept within MAX_YAW_DEG of a (the room's axes come
    from the points' normals and can lie a degree or two off a wall no point shows: 1.3
    degrees spread the honest room's foot over 14 cm along its 6 m)."""
    n, d = a, d0
    cos_max = np.cos(np.radians(MAX_YAW_DEG))
    for _ in range(3):
        near = x[np.abs(x @ n - d) <= 1.5 * BIN]
        if len(near) < 2:
            break
        q = near - near.mean(0)
        q -= (q @ up)[:, None] * up  # on the floor
        _, _, vt = np.linalg.svd(q, full_matrices=False)
        m = np.cross(up, vt[0])  # across the line's main direction
        m /= max(float(np.linalg.norm(m)), 1e-12)
        m = m if m @ a >= 0 else -m
        n = m if m @ a >= cos_max else a
        d = float(np.median(near @ n))
    return n, d


def _candidates(
    view_edges: tuple[np.ndarray, ...],
    depth: np.ndarray,
    K: np.ndarray,
    pose: np.ndarray,
    up: np.ndarray,
    floor: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(floor points [N, 3], image gradients [N, 2]) of this view's edge pixels that may be
    a wall's foot, whatever the wall's axis: cast onto the floor within REACH, the wall's
    side of the edge (up the image) plain, and a reading on its other side, if any, on the
    floor. view_edges: `_edges` of the view."""
    edges, gx, gy, spread = view_edges
    h, w = edges.shape
    none = (np.zeros((0, 3)), np.zeros((0, 2)))
    if not edges.any():
        return none
    uv = pixel_grid(w, h).reshape(h, w, 2)[edges].astype(np.float64)
    g = np.stack([gx[edges], gy[edges]], -1)
    uv = _subpixel(uv, g, np.hypot(gx, gy))
    ground = [Plane(up, floor, FLOOR_NAME, up, up, 0)]  # plane_depth reads normal and offset
    c = pose[:3, 3]
    r = rays(uv, K, pose)
    t = plane_depth(r, c, ground)[0]
    x = c + t[:, None] * r
    ok = (t > 0) & (np.linalg.norm(x - c, axis=1) <= REACH) & (np.linalg.norm(g, axis=1) > 1e-9)
    x, uv, g = x[ok], uv[ok], g[ok]
    # the wall's side of its foot (up the wall in the image) is plain: a line in the floor's
    # texture or along a textured object's base has texture on both sides
    q0, z0 = project(x, K, pose)
    q2, z2 = project(x + 0.1 * up, K, pose)
    dv = q2 - q0
    dv /= np.maximum(np.linalg.norm(dv, axis=1), 1e-9)[:, None]
    step = (PATCH // 2 + 2) * dv
    s = np.round(uv + step).astype(np.int64)
    inside = (s[:, 0] >= 0) & (s[:, 0] < w) & (s[:, 1] >= 0) & (s[:, 1] < h)
    plain = np.zeros(len(s), bool)
    plain[inside] = spread[s[inside, 1], s[inside, 0]] <= PLAIN
    # and a reading on its other side (down the image) lies on the floor
    f_ = np.clip(np.round(uv - step).astype(np.int64), 0, [w - 1, h - 1])
    z = depth[f_[:, 1], f_[:, 0]]
    tf = plane_depth(rays(f_.astype(np.float64), K, pose), c, ground)[0]
    plain &= (z <= 0) | (np.abs(z - tf) <= ON_FLOOR * np.maximum(tf, 1e-6))
    keep = (z0 > 1e-6) & (z2 > 1e-6) & plain
    return x[keep], g[keep]


def _along(
    x: np.ndarray, g: np.ndarray, K: np.ndarray, pose: np.ndarray, along: np.ndarray, sin_max: float
) -> np.ndarray:
    """The floor points x whose edge (gradient g) runs within asin(sin_max) of the image
    direction of the floor line through them in direction `along`."""
    q0, z0 = project(x, K, pose)
    q1, z1 = project(x + 0.05 * along, K, pose)
    du = q1 - q0
    dn = np.linalg.norm(du, axis=1)
    gn = np.linalg.norm(g, axis=1)
    # the gradient runs across an edge: along the line, its share is the angle's sine
    across = np.abs(np.sum(g * du, axis=1)) <= sin_max * gn * dn
    return x[(z0 > 1e-6) & (z1 > 1e-6) & (dn > 1e-9) & across]


def _subpixel(uv: np.ndarray, g: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Edge pixels uv [N, 2] moved to the peak of the gradient magnitude `mag` across the edge
    (a parabola through it a pixel either side along their gradients g [N, 2]). Canny keeps one
    of the two pixels a step lies between, the same one along a whole line, and half a
    pixel on a far floor is several cm: on procedural rooms at 160 px the feet lay 3-7 cm
    beyond the walls without it."""
    g = g / np.maximum(np.linalg.norm(g, axis=1), 1e-12)[:, None]
    at = [
        map_coordinates(mag, [q[:, 1], q[:, 0]], order=1, mode="nearest")
        for q in (uv - g, uv, uv + g)
    ]
    m0, m1, m2 = at
    den = m0 - 2 * m1 + m2
    shift = np.where(den < -1e-12, 0.5 * (m0 - m2) / np.where(den < -1e-12, den, -1.0), 0.0)
    return uv + np.clip(shift, -0.5, 0.5)[:, None] * g


def _edges(rgb: np.ndarray) -> tuple[np.ndarray, ...]:
    """Canny edges of any of the CIELAB channels (a wall and a floor of one brightness still
    differ in hue), the gradient of the channel changing most at each pixel, the local
    spread (the largest channel's standard deviation over PATCH pixels)."""
    lab = rgb2lab(rgb)
    edges = np.zeros(lab.shape[:2], bool)
    gx = np.zeros(lab.shape[:2])
    gy = np.zeros(lab.shape[:2])
    spread = np.zeros(lab.shape[:2])
    for ch in range(3):
        c = np.asarray(lab[..., ch], np.float64)
        edges |= canny(c, sigma=SIGMA, low_threshold=EDGE_LOW, high_threshold=EDGE_HIGH)
        g = gaussian_filter(c, SIGMA)
        cx, cy = sobel(g, axis=1), sobel(g, axis=0)
        more = np.hypot(cx, cy) > np.hypot(gx, gy)
        gx = np.where(more, cx, gx)
        gy = np.where(more, cy, gy)
        var = uniform_filter(c**2, PATCH) - uniform_filter(c, PATCH) ** 2
        spread = np.maximum(spread, np.sqrt(np.maximum(var, 0)))
    return edges, gx, gy, spread

"""Manhattan yaw from the images' straight edges: the room's horizontal vanishing directions.

A photos-only capture's depth at align time is SfM's tracks: a few thousand points whose
normals, fitted to their 16 nearest neighbours, scatter by degrees. Yet every image shows the
room's horizontal lines sharply: the counter's edge, the cabinet tops, the wall's foot. An
edge pixel at u with edge direction t (square to the image gradient) spans with the camera
centre the interpretation plane of its 3D line; its normal n = K⁻¹u x K⁻¹(u + t), turned into
the z-up world. A horizontal line lies in that plane and in the horizontal: its direction is
n x z. These directions, folded modulo 90 degrees, pile up at the room's wall directions as
the walls' normals do, and `manhattan.find_yaw` reads them the same way (Manhattan-world
vanishing points with known camera rotations; Coughlan & Yuille, ICCV 1999; Košecká & Zhang,
ECCV 2002).

Two kinds of edge pixel are left out:
- a vertical line's plane holds the up axis (|n_z| ~ 0): n x z is then the plane's own
  horizontal direction, a vote for wherever the line stands, not for a wall's direction;
- an edge near the horizon line (|n_z| ~ 1) fixes its direction poorly: a pixel of error in
  t turns n x z by tens of degrees.
No learned line detector: gradients (scipy.ndimage) and the cameras the poses stage found.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.common.camera import undistort_pixels
from stages.common.capture import Capture
from stages.common.io import gray, read_image

WORK_SIDE = 640  # images are read at most this wide (edges of a room are long: no loss)
BLUR_SIGMA = 1.0  # pixels: Gaussian before the Sobel gradients (sensor noise)
EDGE_SHARE = 0.10  # the strongest this share of each image's gradients are the edge pixels
MIN_GRADIENT = 16.0  # ... if above this Sobel magnitude (grey levels; a sharp step of 4 grey
#                      levels gives about 16 after the blur): flat images give no edges
ORIENTATIONS = 8  # edge pixels are grouped by gradient orientation in bins of 180/8 degrees
#                   (twice, the second binning shifted by half a bin, so that a line whose
#                   orientation sits on a bin boundary is still whole in one of them)
MIN_LENGTH = 20.0  # pixels (at WORK_SIDE): shorter segments are texture, not the room's lines
MAX_WIDTH = 0.15  # a segment's width / length at most this (straight, not a blob)
PIXELS_PER_VOTE = 4.0  # a segment votes once per this many pixels of its length
MIN_EDGE_VOTES = 500  # fewer votes than this: the images show too few of the room's lines to
#                       read the yaw from (the honest procedural room: 115, from a handful of
#                       segments 15 degrees off its walls; the kitchen 19 899, the office 17 349)
MIN_PLANE_TILT = 0.2  # |n_z| above this: not a vertical line's plane (see the module doc)
MAX_PLANE_TILT = 0.97  # |n_z| below this: not an edge along the horizon line


def segments(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight edge segments of a grey image [h, w] (float, 0-255): (centres [S, 2] as
    (u, v), unit directions [S, 2], lengths [S]) in its pixels.

    The edge pixels of one orientation that touch form a segment's support (the region
    growing of LSD, von Gioi et al., PAMI 2010, without its a-contrario test); its direction
    is the major axis of the pixels' positions. Per-pixel gradient directions would do
    without the grouping, but on a sharp, aliased edge they lean toward the image axes
    (a 17 degree turn read as 16.0 on a rendered room); the pixels' positions do not.
    No OpenCV here for its LSD: a labelling and a few bincounts (scipy) do it."""
    g = ndimage.gaussian_filter(gray, BLUR_SIGMA)
    gx, gy = ndimage.sobel(g, 1), ndimage.sobel(g, 0)
    mag = np.hypot(gx, gy)
    edge = mag > max(float(np.quantile(mag, 1.0 - EDGE_SHARE)), MIN_GRADIENT)
    ang = np.mod(np.arctan2(gy, gx), np.pi) * (ORIENTATIONS / np.pi)  # [h, w] in [0, 8)
    out = []
    for shift in (0.0, 0.5):
        bins = np.floor(ang + shift).astype(np.int64) % ORIENTATIONS
        for b in range(ORIENTATIONS):
            lab, n = ndimage.label(edge & (bins == b), structure=np.ones((3, 3)))
            if n == 0:
                continue
            out.append(_axes(lab, n))
    seg = np.concatenate(out) if out else np.zeros((0, 5))
    return seg[:, :2], seg[:, 2:4], seg[:, 4]


def _axes(lab: np.ndarray, n: int) -> np.ndarray:
    """[S, 5] rows (centre u, v, direction u, v, length) of the labelled regions 1..n of
    `lab` [h, w] that are long and thin enough to be segments."""
    v, u = np.nonzero(lab)
    k = lab[v, u]
    cnt = np.maximum(np.bincount(k, minlength=n + 1)[1:], 1).astype(np.float64)  # [n]
    uf, vf = u.astype(np.float64), v.astype(np.float64)
    mu, mv, muu, mvv, muv = (
        np.bincount(k, x, minlength=n + 1)[1:] / cnt for x in (uf, vf, uf * uf, vf * vf, uf * vf)
    )
    cuu, cvv, cuv = muu - mu * mu, mvv - mv * mv, muv - mu * mv
    # major and minor axes of each region's 2x2 covariance, in closed form
    half = np.sqrt(((cuu - cvv) / 2) ** 2 + cuv**2)
    big, small = (cuu + cvv) / 2 + half, np.maximum((cuu + cvv) / 2 - half, 0.0)
    theta = 0.5 * np.arctan2(2 * cuv, cuu - cvv)
    length = np.sqrt(12.0 * big)  # a uniform spread of length L has variance L^2 / 12
    ok = (
        (cnt >= MIN_LENGTH) & (length >= MIN_LENGTH) & (np.sqrt(12.0 * small) <= MAX_WIDTH * length)
    )
    return np.column_stack([mu, mv, np.cos(theta), np.sin(theta), length])[ok]


def edge_directions(cap: Capture, frames: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Horizontal unit directions [N, 3] of the straight edges of `frames` (indices into
    cap.frames), one per PIXELS_PER_VOTE of each segment's length, in the world turned by
    R (input world -> z up)."""
    out = [np.zeros((0, 3))]
    for i in frames:
        f = cap.frames[int(i)]
        img = read_image(f.image)  # [H, W, 3] uint8
        h, w = img.shape[:2]
        intr = f.intrinsics
        if (w, h) != (intr.width, intr.height):
            intr = intr.scaled(w, h)
        step = max(1, int(np.ceil(w / WORK_SIDE)))
        # step x step blocks averaged: block j spans pixels j step .. j step + step - 1
        blocks = img[: h // step * step, : w // step * step].astype(np.float32)
        blocks = blocks.reshape(h // step, step, w // step, step, 3).mean(axis=(1, 3))
        c, t, length = segments(gray(blocks))
        if not len(c):
            continue
        # the ends in full-size pixels (a block's centre: j step + (step - 1) / 2), pinhole
        ends = [(c + s * t * length[:, None] / 2.0) * step + (step - 1) / 2.0 for s in (-1, 1)]
        p = undistort_pixels(np.concatenate(ends), intr)  # [2S, 2] pinhole pixels
        ray = np.column_stack([(p - (intr.cx, intr.cy)) / (intr.fx, intr.fy), np.ones(len(p))])
        ray = ray.reshape(2, len(c), 3)  # the two ends of each segment, z = 1
        n = np.cross(ray[0], ray[1])  # [S, 3] interpretation planes' normals, camera frame
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        nw = n @ (R @ np.asarray(f.pose, np.float64)[:3, :3]).T  # [S, 3] z-up world
        keep = (np.abs(nw[:, 2]) > MIN_PLANE_TILT) & (np.abs(nw[:, 2]) < MAX_PLANE_TILT)
        d = np.cross(nw[keep], [0.0, 0.0, 1.0])  # [m, 3] horizontal, |d| = sqrt(1 - n_z^2)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        votes = np.maximum(1, np.round(length[keep] / PIXELS_PER_VOTE)).astype(np.int64)
        out.append(np.repeat(d, votes, axis=0))
    return np.concatenate(out)

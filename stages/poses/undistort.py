"""Photos made pinhole where SfM found their lens distortion, as COLMAP undistorts before
its dense stereo.

SfM estimates one radial coefficient per camera (calib.py's SIMPLE_RADIAL, k1) when the
intrinsics are not given or disagree with the photos. The stages after it read a frame as
a pinhole camera: the plane sweep warps views by homographies, the plane fill by plane
homographies, fusion and the fields cast straight rays. A frame that kept its k1 was read
by them as pinhole and by the project stage through its distortion. With poses.undistort
(off by default: docs/figures.md#poses-undistort) each such frame takes instead an
undistorted copy of its photo (kornia's `undistort_image`: bilinear, the same
focal and principal point, pixel centres on integers as in camera.py) and intrinsics
without distortion, so that every stage reads the same rays. Its sensor depth, if any, is
then registered to that pinhole camera (stated.register_depth).

A lens whose model moves no pixel by MIN_SHIFT_PX is left as it is: resampling would blur
the photo more than the model moves it (a procedural room's renders are pinhole; SfM gives
the default room's 60 photos a k1 of -1e-4).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.calibration import undistort_image

from stages.common.camera import Intrinsics, distorted
from stages.common.io import read_image, write_image

MIN_SHIFT_PX = 0.5  # a lens model moving no border pixel this far is left as it is


def largest_shift_px(intr: Intrinsics) -> float:
    """How far (pixels) the lens model moves the pixels of the image's border from where a
    pinhole camera sees them: the largest over its corners and edge midpoints (radial
    models move the corners most). 0 for no distortion."""
    if not any(intr.dist):
        return 0.0
    w, h = intr.width - 1, intr.height - 1
    u = np.array([0, w, 0, w, w / 2, w / 2, 0, w], np.float64)
    v = np.array([0, 0, h, h, 0, h, h / 2, h / 2], np.float64)
    x, y = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    xd, yd = distorted(x, y, intr.dist)
    return float(np.max(np.hypot((xd - x) * intr.fx, (yd - y) * intr.fy)))


def undistorted_copy(src: Path, intr: Intrinsics, dst: Path) -> Intrinsics:
    """Write the photo `src` of the camera `intr` as the same camera without its distortion
    sees it to `dst` (a .png: lossless, the sweep matches its pixels); returns that pinhole
    camera. Pixels the lens did not see (the corners of a pincushion lens) are black."""
    rgb = read_image(src)  # [H, W, 3] uint8
    h, w = rgb.shape[:2]
    k = intr.scaled(w, h)
    img = torch.tensor(rgb).permute(2, 0, 1)[None].float()  # [1, 3, H, W]; a copy (read-only)
    K = torch.tensor(k.K, dtype=torch.float32)  # [3, 3]
    coeffs = tuple(k.dist) + (0.0,) * (4 - len(k.dist))  # kornia takes 4, 5, 8, ... of them
    dist = torch.tensor(coeffs, dtype=torch.float32)
    with torch.no_grad():
        out = undistort_image(img, K, dist)  # [1, 3, H, W]
    got = out[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()
    dst.parent.mkdir(parents=True, exist_ok=True)
    write_image(dst, got)
    return replace(intr, dist=())

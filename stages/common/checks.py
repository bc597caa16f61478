"""Checks on what a capture gives: frame names that collide, intrinsics no camera has.

Readers of every layout call these before building frames, so a bad input is refused with a
one-line message naming the file or value at fault.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics
from stages.common.errors import BlunfError

FOV_DEG = (10.0, 170.0)  # plausible field of view of a camera, each image axis (degrees)
MAX_PIXEL_ASPECT = 2.0  # fy / fx within [1/this, this] (anamorphic at most 2:1)
PP_MARGIN = 0.25  # principal point at most this fraction of the image size outside it


def check_unique_stems(named: list[tuple[str, Path]]) -> None:
    """Refuse two files that would become frames of one name (images/0003.png and
    images/0003.jpg would share one depth map, label map and pose)."""
    seen: dict[str, Path] = {}
    for stem, p in named:
        if stem in seen:
            raise BlunfError(
                f"{seen[stem]} and {p}: two images of one frame name {stem!r} "
                "(they would share its depth, labels and pose); keep one"
            )
        seen[stem] = p


def check_intrinsics(intr: Intrinsics, where: str) -> None:
    """Refuse intrinsics no camera has: a field of view outside FOV_DEG (e.g. fx = 1e308, which
    would leave fusion nothing to fuse), pixels far from square, or a principal point
    outside the image by more than PP_MARGIN of its size."""
    lo, hi = FOV_DEG
    axes = (
        ("horizontal", "fx", intr.fx, "width", intr.width),
        ("vertical", "fy", intr.fy, "height", intr.height),
    )
    for axis, f_name, f, side, px in axes:
        deg = float(np.degrees(2 * np.arctan2(px / 2, f)))
        if not lo <= deg <= hi:
            raise BlunfError(
                f"{where}: {axis} field of view {deg:.3g} degrees ({f_name} = {f:.6g} px "
                f"for {side} {px}) is not a camera's (want {lo:g}-{hi:g} degrees)"
            )
    aspect = intr.fy / intr.fx
    if not 1 / MAX_PIXEL_ASPECT <= aspect <= MAX_PIXEL_ASPECT:
        raise BlunfError(
            f"{where}: fy / fx = {aspect:.3g} (fx = {intr.fx:.6g}, fy = {intr.fy:.6g}): pixels "
            f"that far from square are not a camera's (want {1 / MAX_PIXEL_ASPECT:g}-"
            f"{MAX_PIXEL_ASPECT:g})"
        )
    for c, px, name in ((intr.cx, intr.width, "cx"), (intr.cy, intr.height, "cy")):
        if not -PP_MARGIN * px <= c <= (1 + PP_MARGIN) * px:
            raise BlunfError(
                f"{where}: principal point {name} = {c:.6g} px lies far outside the image "
                f"(size {intr.width}x{intr.height})"
            )

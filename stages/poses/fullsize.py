"""SfM on the capture's full-size images while every other stage works on downscaled ones.

Ingest downscales the frames to its working size (ingest.max_side, photo_max_side) and names
the full-size file in `Frame.original`. SIFT finds more features, better placed, on it (read
at most poses.full_size_max_side long), and the poses do not depend on the resolution.
`sfm_frames` gives the frames as SfM sees them (the full-size images, their intrinsics scaled
up); `to_working_size` scales the model's cameras and keypoints back down, so that everything
after mapping (self-calibrated intrinsics, sparse depth, the metric scale from depth, the
written model) is in the pixels of the images the later stages read.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.common.capture import Frame
from stages.common.errors import BlunfError
from stages.common.io import image_size

log = logging.getLogger(__name__)

ASPECT_TOL = 0.02  # relative aspect-ratio difference beyond which an original is not the image


def sfm_frames(frames: tuple[Frame, ...], full: bool) -> tuple[Frame, ...]:
    """The frames SfM reads: with `full`, each downscaled frame's original image with its
    intrinsics scaled to the original's size; the working images otherwise (or when an
    original's shape is not the working image's, e.g. turned by its EXIF orientation)."""
    if not full:
        return frames
    out = []
    for f in frames:
        if f.original is None:
            out.append(f)
            continue
        src = Path(f.original)
        if not src.is_file():
            raise BlunfError(
                f"{src}: full-size image of frame {f.stem!r} not found "
                "(poses.full_size_images=false reads the downscaled one)"
            )
        w, h = image_size(src)
        k = f.intrinsics
        if abs((w / h) / (k.width / k.height) - 1.0) > ASPECT_TOL:
            log.warning(
                "sfm: %s is %dx%d, not the shape of its downscaled %dx%d: SfM reads the latter",
                src,
                w,
                h,
                k.width,
                k.height,
            )
            out.append(f)
            continue
        out.append(replace(f, image=src, intrinsics=k.scaled(w, h)))
    return tuple(out)


def max_side(cfg_max: int, cap: int, seen: tuple[Frame, ...], working: tuple[Frame, ...]) -> int:
    """SIFT's longest image side: max_image_size, lowered to `cap` (poses.full_size_max_side,
    never below a working size) when SfM reads some original."""
    if cap <= 0 or all(a.image == b.image for a, b in zip(seen, working, strict=True)):
        return cfg_max
    return min(cfg_max, max(cap, *(max(_size(f)) for f in working)))


def facts(seen: tuple[Frame, ...], working: tuple[Frame, ...]) -> dict:
    """What sfm.json says of the images SfM read: their sizes and the working sizes."""

    def sizes(frames: tuple[Frame, ...]) -> list[list[int]]:
        return [list(s) for s in sorted({_size(f) for f in frames})]

    full = sum(a.image != b.image for a, b in zip(seen, working, strict=True))
    return {"full_size": full, "sizes": sizes(seen), "working": sizes(working)}


def _size(f: Frame) -> tuple[int, int]:
    return f.intrinsics.width, f.intrinsics.height


def to_working_size(
    rec: pycolmap.Reconstruction, names: list[str], frames: tuple[Frame, ...]
) -> None:
    """Rescale in place the cameras (focal, principal point) and the keypoints of the model's
    images to their frames' working size. names: COLMAP image name of each frame."""
    sizes = {name: _size(f) for name, f in zip(names, frames, strict=True)}
    target: dict[int, tuple[int, int]] = {}  # camera id -> working size
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        wh = sizes[im.name]
        if wh == (cam.width, cam.height):
            continue
        if target.setdefault(im.camera_id, wh) != wh:
            raise BlunfError(
                f"sfm: camera {im.camera_id} has images of two working sizes "
                f"{target[im.camera_id]} and {wh}: set poses.full_size_images=false"
            )
    for cid, (w, h) in target.items():
        cam = rec.cameras[cid]
        s = np.array([w / cam.width, h / cam.height])
        cam.rescale(w, h)  # COLMAP's corner-at-0 pixels: every coordinate scales by s
        for im in rec.images.values():
            if im.camera_id == cid:
                for p in im.points2D:
                    p.xy = p.xy * s
    if target:
        rec.update_point_3d_errors()  # reprojection errors in working pixels

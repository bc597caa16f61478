"""Intrinsics of photos that come without any: from EXIF when it says, else a prior.

A photo's EXIF gives the focal length as its 35 mm-film equivalent (`FocalLengthIn35mmFilm`,
defined on the frame's diagonal: f_px = f35 / 43.27 mm x the image diagonal in pixels) or
in millimetres on the sensor (`FocalLength`), which needs the sensor's pixel pitch
(`FocalPlaneXResolution` and its unit). Either is a prior that SfM refines. Without EXIF the
prior is COLMAP's: f = 1.2 x the longer side. The principal point is the image centre.
Photos are grouped into cameras by device (EXIF Make and Model) and image size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from PIL import Image

from stages.common.camera import Intrinsics
from stages.common.errors import BlunfError
from stages.common.io import IMAGE_ERRORS

PRIOR_FACTOR = 1.2  # focal prior / longer image side without EXIF (COLMAP's default)
FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm: the 35 mm frame's diagonal
# f / longer side outside this range (a field of view over 127 or under 9.5 degrees across
# the longer side) is not a phone or camera photo's: the EXIF value is refused as nonsense
FOCAL_RATIO_RANGE = (0.25, 6.0)
MIN_PER_CAMERA = 3  # a camera (device, size) without given intrinsics needs this many photos

# EXIF tags (numbers from the EXIF 2.3 standard)
MAKE, MODEL, EXIF_IFD = 0x010F, 0x0110, 0x8769
FOCAL_LENGTH, FOCAL_35MM = 0x920A, 0xA405
FOCAL_PLANE_XRES, FOCAL_PLANE_UNIT = 0xA20E, 0xA210
PIXEL_X_DIMENSION = 0xA002
UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit -> millimetres


@dataclass(frozen=True)
class Guess:
    """What one photo's file says about its camera."""

    intrinsics: Intrinsics
    calib: str  # "exif" or "prior"
    camera: str  # device and image size: photos of one camera share it
    how: str  # the focal's source in words


def _num(v: object) -> float | None:
    """An EXIF rational or number as a float; None when absent, zero (= unknown) or bad."""
    if v is None:
        return None
    try:
        x = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan
    return None if x == 0 else x


def _text(v: object) -> str:
    if isinstance(v, bytes):
        v = v.decode("ascii", "replace")
    return " ".join(str(v).replace("\x00", " ").split()) if v is not None else ""


def focal_from_exif(
    path: Path, exif: dict[int, object], w: int, h: int
) -> tuple[float, str] | None:
    """Focal length in pixels (and its source in words) from EXIF tags, or None when EXIF
    does not give it. Nonsense values (negative, not a number, or a field of view no camera
    has) raise."""
    f35 = _num(exif.get(FOCAL_35MM))
    f_mm = _num(exif.get(FOCAL_LENGTH))
    xres = _num(exif.get(FOCAL_PLANE_XRES))
    unit = exif.get(FOCAL_PLANE_UNIT, 2)
    full_w = _num(exif.get(PIXEL_X_DIMENSION)) or float(w)
    got: tuple[float, str] | None = None
    if f35 is not None:
        got = f35 / FILM_DIAGONAL_MM * math.hypot(w, h), f"EXIF 35 mm-equivalent {f35:g} mm"
        bad = f"35 mm-equivalent focal length {f35:g} mm"
    elif f_mm is not None and xres is not None and unit in UNIT_MM:
        # pixels per mm on the sensor, at the EXIF's pixel width, rescaled to this file's
        px_per_mm = xres / UNIT_MM[unit]  # type: ignore[index]
        got = f_mm * px_per_mm * w / full_w, f"EXIF focal length {f_mm:g} mm and sensor pitch"
        bad = f"focal length {f_mm:g} mm at {xres:g} px per focal-plane unit"
    if got is None:
        if f_mm is not None and not (f_mm > 0 and math.isfinite(f_mm)):
            raise BlunfError(f"{path}: EXIF focal length {f_mm} mm makes no sense")
        return None
    ratio = got[0] / max(w, h)
    lo, hi = FOCAL_RATIO_RANGE
    if not (math.isfinite(ratio) and lo <= ratio <= hi):
        raise BlunfError(
            f"{path}: EXIF {bad} makes no sense ({got[0]:.4g} px for a {w}x{h} image; "
            "give intrinsics in cameras.json)"
        )
    return got


def read_exif(path: Path) -> tuple[int, int, dict[int, object]]:
    """(width, height, EXIF tags of IFD0 and the Exif IFD) of an image file, header only."""
    try:
        with Image.open(path) as img:
            w, h = img.size
            ex = img.getexif()
            tags: dict[int, object] = dict(ex)
            tags.update(ex.get_ifd(EXIF_IFD))
    except FileNotFoundError:
        raise BlunfError(f"{path}: file not found") from None
    except IMAGE_ERRORS as e:
        raise BlunfError(f"{path}: not a readable image ({e.__class__.__name__})") from None
    return w, h, tags


def guess(path: Path) -> Guess:
    """Intrinsics of one photo from its EXIF, else the prior."""
    w, h, exif = read_exif(path)
    device = " ".join(s for s in (_text(exif.get(MAKE)), _text(exif.get(MODEL))) if s)
    camera = f"{device or 'unknown device'} {w}x{h}"
    got = focal_from_exif(path, exif, w, h)
    if got is None:
        f, calib, how = PRIOR_FACTOR * max(w, h), "prior", f"{PRIOR_FACTOR} x the longer side"
    else:
        (f, how), calib = got, "exif"
    intr = Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    return Guess(intr, calib, camera, how)


def guess_all(images: list[Path]) -> list[tuple[Intrinsics, str, str]]:
    """(intrinsics, calib, camera) of each photo. Photos of one camera (device and size)
    share the intrinsics of its first photo that EXIF calibrates (else the prior). A camera
    with fewer than MIN_PER_CAMERA photos cannot be calibrated: photos of several sizes
    need intrinsics in cameras.json."""
    gs = [guess(p) for p in images]
    by_cam: dict[str, list[int]] = {}
    for i, g in enumerate(gs):
        by_cam.setdefault(g.camera, []).append(i)
    if len(by_cam) > 1:
        for cam, idx in by_cam.items():
            if len(idx) < MIN_PER_CAMERA:
                sizes = sorted({g.camera for g in gs})
                raise BlunfError(
                    f"{images[idx[0]]}: only {len(idx)} photo(s) of camera {cam!r} among "
                    f"{len(images)} ({len(sizes)} cameras: device and size); photos of several "
                    "sizes need intrinsics in cameras.json, or leave the odd ones out"
                )
    out: list[tuple[Intrinsics, str, str]] = [(g.intrinsics, g.calib, g.camera) for g in gs]
    for idx in by_cam.values():
        first = next((i for i in idx if gs[i].calib == "exif"), idx[0])
        for i in idx:
            out[i] = (gs[first].intrinsics, gs[first].calib, gs[i].camera)
    return out

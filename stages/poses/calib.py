"""Self-calibration in SfM for frames whose intrinsics were not given (photos, video).

One SIMPLE_RADIAL camera (f, cx, cy, k1) per physical camera (`Frame.camera`: device and
image size). Its focal starts from the EXIF value, marked as a prior COLMAP trusts for the
two-view geometry, or from 1.2 x the longer side (COLMAP's default, no prior). Bundle
adjustment refines the focal and k1; the principal point stays at the image centre.
The estimate is weak when few views register or the cameras barely move against the
scene's depth: that is reported rather than hidden.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.common.camera import Intrinsics
from stages.common.capture import Frame
from stages.common.errors import BlunfError
from stages.common.io import image_size

log = logging.getLogger(__name__)

KNOWN = ("given", "self-calibrated")  # Frame.calib values SfM keeps fixed
PRIOR_FACTOR = 1.2  # focal / longer side without EXIF (as stages/ingest/exif.py)
WEAK_MIN_VIEWS = 10  # fewer registered views of a camera than this: weak
WEAK_MIN_BASELINE = 0.3  # camera centres' spread / median scene depth under this: weak
WEAK_PRIOR_CHANGE = 0.1  # estimate off the EXIF prior by more than this fraction: doubtful


def unknown(frames: tuple[Frame, ...]) -> bool:
    """Whether some frame's intrinsics are a guess for SfM to estimate."""
    return any(f.calib not in KNOWN for f in frames)


def extract(
    frames: tuple[Frame, ...],
    names: list[str],
    db: Path,
    img_dir: Path,
    eo: pycolmap.FeatureExtractionOptions,
) -> dict:
    """SIFT features into the database with one SIMPLE_RADIAL camera per physical camera."""
    groups: dict[tuple[str, int, int], list[int]] = {}
    for i, f in enumerate(frames):
        w, h = image_size(f.image)
        if (f.intrinsics.width, f.intrinsics.height) != (w, h):
            raise BlunfError(
                f"{f.image}: image is {w}x{h} but its intrinsics say "
                f"{f.intrinsics.width}x{f.intrinsics.height}"
            )
        groups.setdefault((f.camera or f.calib, w, h), []).append(i)
    cams = []
    for (cam, w, h), idx in groups.items():
        f0 = frames[idx[0]]
        ro = pycolmap.ImageReaderOptions()
        ro.camera_model = "SIMPLE_RADIAL"
        ro.default_focal_length_factor = PRIOR_FACTOR
        prior = f0.calib != "prior"  # EXIF, or a given camera estimated along with the others
        if prior:
            k = f0.intrinsics
            ro.camera_params = ",".join(repr(v) for v in (k.fx, k.cx + 0.5, k.cy + 0.5, 0.0))
        group = [names[i] for i in idx]
        pycolmap.extract_features(
            db, img_dir, group, pycolmap.CameraMode.SINGLE, ro, eo, pycolmap.Device.cpu
        )
        cams.append(
            {
                "camera": cam,
                "images": len(idx),
                "size": [w, h],
                "prior_source": f0.calib,
                "prior_fx": f0.intrinsics.fx if prior else PRIOR_FACTOR * max(w, h),
            }
        )
    return {"fixed": False, "model": "SIMPLE_RADIAL", "cameras": len(groups), "prior": cams}


def intrinsics_of(cam: pycolmap.Camera) -> Intrinsics:
    """Project intrinsics of a SIMPLE_RADIAL camera (principal point moved by -0.5)."""
    f, cx, cy, k = (float(v) for v in cam.params)
    return Intrinsics(f, f, cx - 0.5, cy - 0.5, int(cam.width), int(cam.height), (k, 0.0, 0.0, 0.0))


def report(
    rec: pycolmap.Reconstruction, frames: tuple[Frame, ...], image_ids: dict[int, int]
) -> dict:
    """What SfM estimated per camera against its prior, and why it may be weak.

    image_ids: index of each registered frame -> its COLMAP image id."""
    by_cam: dict[int, list[int]] = {}
    for i, iid in image_ids.items():
        by_cam.setdefault(rec.image(iid).camera_id, []).append(i)
    cams, weak = [], []
    for cid, idx in sorted(by_cam.items()):
        est = intrinsics_of(rec.camera(cid))
        f0 = frames[idx[0]]
        prior = (
            f0.intrinsics.fx if f0.calib != "prior" else PRIOR_FACTOR * max(est.width, est.height)
        )
        ims = [rec.image(image_ids[i]) for i in idx]
        spread = baseline_ratio(rec, ims)
        name = f0.camera or f0.calib
        change = est.fx / prior - 1.0
        c: dict = {
            "camera": name,
            "prior_source": f0.calib,
            "prior_fx": prior,
            "fx": est.fx,
            "cx": est.cx,
            "cy": est.cy,
            "k1": est.dist[0],
            "size": [est.width, est.height],
            "change": change,
            "registered": len(idx),
            "baseline_ratio": spread,
        }
        why = []
        if len(idx) < WEAK_MIN_VIEWS:
            why.append(f"only {len(idx)} registered views (< {WEAK_MIN_VIEWS})")
        if spread < WEAK_MIN_BASELINE:
            why.append(
                f"short baselines (camera spread {spread:.2f} x the scene depth "
                f"< {WEAK_MIN_BASELINE})"
            )
        if f0.calib == "exif" and abs(change) > WEAK_PRIOR_CHANGE:
            why.append(f"focal {100 * change:+.0f} % off its EXIF value")
        if why:
            c["weak"] = why
            weak.append(f"camera {name!r}: " + "; ".join(why))
        cams.append(c)
    out: dict = {"source": "self-calibrated", "cameras": cams}
    if weak:
        out["weak"] = weak
        for w in weak:
            log.warning("sfm: weak self-calibration, %s: intrinsics and poses may be off", w)
    return out


def baseline_ratio(rec: pycolmap.Reconstruction, ims: list[pycolmap.Image]) -> float:
    """Spread of the camera centres (largest distance from their mean) over the median depth
    of the points they see: small when the photos were taken from about one spot."""
    if len(ims) < 2:
        return 0.0
    centres = np.array([im.projection_center() for im in ims])  # [C, 3]
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    depths = []
    for im in ims:
        ids = [p.point3D_id for p in im.get_observation_points2D()]
        if not ids:
            continue
        xyz = np.array([rec.points3D[j].xyz for j in ids]).reshape(-1, 3)  # [N, 3]
        w2c = im.cam_from_world().matrix()  # [3, 4]
        depths.append(xyz @ w2c[2, :3] + w2c[2, 3])
    if not depths:
        return 0.0
    d = float(np.median(np.concatenate(depths)))
    return spread / d if d > 0 else 0.0

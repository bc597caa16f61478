"""Stated intrinsics checked by bundle adjustment (`poses.self_calibrate = "auto"`).

A capture that states its intrinsics may state the wrong camera's: the 7-Scenes kitchen's
one K (focal 585 px) is its depth camera's, its colour camera's focal is ~526 px. SfM maps
with the stated intrinsics fixed; then one bundle adjustment of a copy of the model with
the focal length free (principal point and distortion held) gives the focal the photos ask
for. When it differs from the stated one by more than `poses.stated_focal_tolerance`, the
photos are mapped again with the focal and k1 estimated (calib.py's SIMPLE_RADIAL camera,
starting from the refined focal), and the frames take the estimate; else the stated
intrinsics stay and the model is the fixed one, untouched.

Measured change of the refined focal against the stated (a model mapped at the stated K):
  demo room (synthetic, exact K)        +0.04 / +0.08 % (fx / fy)
  Replica office0 (rendered, exact K)   -0.06 / -0.03 %
  7-Scenes kitchen (depth camera's K)   -6.2 / -6.1 % (the full re-mapping reaches 526.5,
                                        -10 %: tracks made under the wrong focal hold the
                                        first adjustment back)
The principal point is held at the stated one: freed as well it moves by 0.04 px (demo),
0.6 px (office) and 3.4 px (kitchen, cy) while the focal stays within 0.2 % of the
focal-only estimate, so the photos barely constrain it and moving it would only add noise.

A sensor depth map is registered to its frame's intrinsics (one K per frame): when they
change, the map is resampled into the new camera (same centre and axes, so a pixel keeps
its z; nearest reading, no blending across edges), so depth and colour keep sharing pixels.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.common.camera import Intrinsics
from stages.common.io import read_depth, write_depth_npy

log = logging.getLogger(__name__)

PASSES = 2  # bundle adjustments of the check (the second changes the focal by < 0.01 %)


def check(rec: pycolmap.Reconstruction, tolerance: float) -> dict:
    """The focal each camera of `rec` (mapped at its stated intrinsics) settles at in a
    bundle adjustment of a copy with the focal free. Returns {"cameras": [{"camera_id",
    "stated_f", "refined_f", "change"}], "adopt": any |change| > tolerance}."""
    r = pycolmap.Reconstruction(rec)
    o = pycolmap.BundleAdjustmentOptions()
    o.refine_focal_length = True
    o.refine_principal_point = False
    o.refine_extra_params = False
    o.ceres.solver_options.num_threads = 1  # a fixed order of sums: the same photos, same focal
    o.print_summary = False
    # The adjuster itself, as pycolmap.bundle_adjustment sets it up (every registered image,
    # two cameras fixing the gauge: the same focal to the last bit) without that wrapper's
    # heading and timer, which glog prints whatever its minloglevel.
    c = pycolmap.BundleAdjustmentConfig()
    for i in sorted(r.reg_image_ids()):
        c.add_image(i)
    c.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    for _ in range(PASSES):
        pycolmap.create_default_bundle_adjuster(o, c, r).solve()
    cams = []
    for cid in sorted(rec.cameras):
        before = float(rec.camera(cid).mean_focal_length())
        after = float(r.camera(cid).mean_focal_length())
        cams.append(
            {
                "camera_id": int(cid),
                "stated_f": before,
                "refined_f": after,
                "change": after / before - 1.0,
            }
        )
    adopt = any(abs(c["change"]) > tolerance for c in cams)
    return {"cameras": cams, "adopt": adopt, "tolerance": tolerance}


def to_self_calibration(db: Path, found: dict) -> None:
    """Every camera of the database made a SIMPLE_RADIAL one (f, cx, cy, k1) for SfM to
    estimate, its focal the refined one where `found` (check's) has it, else the stated
    one scaled by the cameras' mean change; principal point and k1 as stated."""
    refined = {c["camera_id"]: c["refined_f"] / c["stated_f"] for c in found["cameras"]}
    mean = float(np.mean(list(refined.values()))) if refined else 1.0
    d = pycolmap.Database.open(db)
    try:
        for cam in d.read_all_cameras():
            f = float(cam.mean_focal_length()) * refined.get(cam.camera_id, mean)
            k1 = float(cam.params[4]) if cam.model_name in ("OPENCV", "FULL_OPENCV") else 0.0
            new = pycolmap.Camera.create_from_model_name(
                cam.camera_id, "SIMPLE_RADIAL", f, cam.width, cam.height
            )
            new.params = [f, cam.principal_point_x, cam.principal_point_y, k1]
            new.has_prior_focal_length = True
            d.update_camera(new)
    finally:
        d.close()


def facts(stated: Intrinsics, found: dict, adopted: Intrinsics | None) -> dict:
    """sfm.json "intrinsics" of an auto run: stated, refined, adopted and why."""
    worst = max(found["cameras"], key=lambda c: abs(c["change"]))
    tol = found["tolerance"]
    change = worst["change"]
    out: dict = {
        "source": "self-calibrated" if adopted is not None else "given",
        "check": "auto",
        "stated": stated.to_json(),
        "refined_f": stated.fx * (1.0 + change),  # the check's focal, at the working size
        "refined_change": change,
        "tolerance": tol,
        "cameras": found["cameras"],
    }
    if adopted is None:
        out["adopted"] = "stated"
        out["reason"] = (
            f"bundle adjustment moves the stated focal by {100 * change:+.2f} % "
            f"(within {100 * tol:.0f} %): kept"
        )
        return out
    out["adopted"] = adopted.to_json()
    out["reason"] = (
        f"bundle adjustment moves the stated focal {stated.fx:.1f} px by {100 * change:+.1f} % "
        f"(beyond {100 * tol:.0f} %): the photos were mapped again with the focal estimated, "
        f"{adopted.fx:.1f} px ({100 * (adopted.fx / stated.fx - 1):+.1f} %)"
    )
    return out


def register_depth(
    src: Path,
    old: Intrinsics,
    new: Intrinsics,
    out: Path,
    scale: float,
    invalid: tuple[int, ...],
) -> None:
    """Write `src` (a depth map of the camera `old`) as seen by the camera `new` at the same
    place (metres, .npy, the map's own size; 0 where `new` sees beyond `old`'s image).
    Pinhole mapping, as the rest of the project reads depth (distortion is not applied)."""
    d = read_depth(src, scale, invalid)
    h, w = d.shape
    a, b = old.scaled(w, h), new.scaled(w, h)
    u = (np.arange(w) - b.cx) * (a.fx / b.fx) + a.cx  # [w] column in the old map
    v = (np.arange(h) - b.cy) * (a.fy / b.fy) + a.cy  # [h]
    cu, cv = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
    okc, okr = (cu >= 0) & (cu < w), (cv >= 0) & (cv < h)
    got = d[np.clip(cv, 0, h - 1)][:, np.clip(cu, 0, w - 1)]
    got[~okr] = 0.0
    got[:, ~okc] = 0.0
    write_depth_npy(out, got)

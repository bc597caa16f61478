"""Does the model agree with the matches it was built from?

Every verified pair's inlier matches satisfy their own two-view geometry. A model built from
them must satisfy them too: the epipolar geometry of the two cameras' model poses holds for
nearly all of a pair's inliers. When a stretch of the walk is registered turned or moved
(an incremental mapper can attach it through weak, nearly panoramic pairs and then reject
the matches that contradict it as outliers), its pairs with the rest of the walk contradict
the model, while the reprojection error, measured only on the matches the model kept, stays
small. The 3-room procedural home from 480 photos: the incremental model held views
0181-0379 turned 62 degrees; 124 of its 3592 verified pairs contradicted it (view pairs
0040-0187 with 315 inliers at 206 px from their epipolar lines), none of the ground truth's
(docs/scale.md#where-a-model-breaks).

The check is the Sampson distance (Hartley & Zisserman, eq. 11.9) of each inlier match to
the model's epipolar geometry, in pixels of the mean focal length. pycolmap keeps each
pair's inliers in the database but offers no check of a model against them, so it is here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.poses.matching import MIN_INLIERS

FIT_PX = 4.0  # an inlier fits the model within this Sampson distance (pixels)
FIT_SHARE = 0.5  # a pair contradicts the model when fewer of its inliers than this fit
STRONG = 50  # a contradicted pair with at least this many inliers counts towards a warning
WARN_PAIRS = 3  # warn (and in mapper "auto", map again) from this many strong contradictions
WORST = 5  # contradicted pairs listed in sfm.json


def sampson_px(
    x1: np.ndarray, x2: np.ndarray, cam1_from_world: np.ndarray, cam2_from_world: np.ndarray
) -> np.ndarray:
    """Sampson distance [N] of normalised image points x1, x2 [N, 2] (z = 1 rays) to the
    epipolar geometry of two [3, 4] world-to-camera poses; in normalised units. Two cameras
    at one centre: the distance of x2 to x1 carried by the rotation."""
    r1, t1 = cam1_from_world[:, :3], cam1_from_world[:, 3]
    r2, t2 = cam2_from_world[:, :3], cam2_from_world[:, 3]
    rot = r2 @ r1.T  # cam2_from_cam1
    t = t2 - rot @ t1
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    base = float(np.linalg.norm(t))
    if base < 1e-12:  # no baseline: the points map by the rotation alone
        y = h1 @ rot.T
        z = np.where(np.abs(y[:, 2:]) > 1e-12, y[:, 2:], 1e-12)
        return np.linalg.norm(y[:, :2] / z - x2, axis=1)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) / base
    e = tx @ rot
    ex1 = h1 @ e.T  # epipolar lines in image 2
    etx2 = h2 @ e  # and in image 1
    num = np.sum(h2 * ex1, axis=1) ** 2
    den = ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-24))


def check(rec: pycolmap.Reconstruction, db: Path, stems: dict[str, str]) -> dict:
    """The model `rec` against every verified pair (>= MIN_INLIERS inliers) of the database
    `db` whose two images it registered. stems: COLMAP image name -> frame stem.

    Returns {"pairs_checked", "pairs_contradicted", "strong_contradicted",
    "contradicted": [{"views": "a-b", "inliers", "fit", "median_px"}, ...] (at most WORST:
    the strong ones first, the farthest off first), "agrees": bool}."""
    posed = {im.name: im for im in rec.images.values() if im.has_pose}
    d = pycolmap.Database.open(db)
    try:
        names = {im.image_id: im.name for im in d.read_all_images()}
        pair_ids, geoms = d.read_two_view_geometries()
        keypoints: dict[int, np.ndarray] = {}
        checked, bad = 0, []
        for pid, g in zip(pair_ids, geoms, strict=True):
            m = np.asarray(g.inlier_matches).reshape(-1, 2)
            a, b = pycolmap.pair_id_to_image_pair(pid)
            if len(m) < MIN_INLIERS or names[a] not in posed or names[b] not in posed:
                continue
            for i in (a, b):
                if i not in keypoints:
                    keypoints[i] = np.asarray(d.read_keypoints(i))[:, :2].astype(np.float64)
            ia, ib = posed[names[a]], posed[names[b]]
            cam_a, cam_b = rec.camera(ia.camera_id), rec.camera(ib.camera_id)
            x1 = cam_a.cam_from_img(keypoints[a][m[:, 0]])
            x2 = cam_b.cam_from_img(keypoints[b][m[:, 1]])
            f = 0.5 * (cam_a.mean_focal_length() + cam_b.mean_focal_length())
            dist = f * sampson_px(
                x1, x2, ia.cam_from_world().matrix(), ib.cam_from_world().matrix()
            )
            checked += 1
            fit = float(np.mean(dist < FIT_PX))
            if fit < FIT_SHARE:
                views = "-".join(sorted((stems[names[a]], stems[names[b]])))
                bad.append((len(m), views, fit, float(np.median(dist))))
    finally:
        d.close()
    bad.sort(key=lambda r: (r[0] < STRONG, -r[3], r[1]))  # strong ones first, farthest off
    strong = sum(k >= STRONG for k, *_ in bad)
    return {
        "pairs_checked": checked,
        "pairs_contradicted": len(bad),
        "strong_contradicted": strong,
        "contradicted": [
            {"views": v, "inliers": k, "fit": round(fit, 3), "median_px": round(px, 1)}
            for k, v, fit, px in bad[:WORST]
        ],
        "agrees": strong < WARN_PAIRS,
    }


def counts(facts: dict) -> dict:
    """The two counts of a `check` (what the other mapper's model is summed up by)."""
    return {k: facts[k] for k in ("pairs_contradicted", "strong_contradicted")}


def warning(facts: dict) -> str:
    """One line for the report when the model contradicts its own matches."""
    worst = ", ".join(
        f"{c['views']} ({c['inliers']} inliers, {c['median_px']:.0f} px off)"
        for c in facts["contradicted"][:3]
    )
    if "global" in facts:  # mapper auto tried the global mapper, and it did no better
        g = facts["global"]
        hint = (
            f"the global mapper's model contradicts {g['strong_contradicted']}"
            if isinstance(g, dict)
            else "the global mapper made no model"
        )
    else:
        hint = "poses.mapper=global may place it"
    return (
        f"the model contradicts {facts['strong_contradicted']} of its {facts['pairs_checked']} "
        f"matched view pairs (e.g. {worst}): part of the walk is misplaced in it; {hint}"
    )

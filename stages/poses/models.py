"""What SfM made of the photos: which photos each model holds, which it left out, and the
warnings a reader of the report needs (photos of two places, or many photos dropped); and
what the kept model's points say: each photo's sparse depth and the model's metric scale.

SfM keeps only its largest model; when the photos fall into several models (two rooms, or
one room photographed in two parts that do not overlap) the others are silently lost, and
with `poses.min_registered_frac` lowered the run goes on with half the capture.
"""

from __future__ import annotations

import logging

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.common.camera import Intrinsics, project
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth
from stages.poses import scale as scale_mod
from stages.poses.config import PosesConfig

log = logging.getLogger(__name__)

SPLIT_MIN_IMAGES = 3  # a second model holding at least this many photos is warned about
DROPPED_WARN_FRAC = 0.2  # warn when more than this fraction of the photos is left out
MAX_SPANS = 20  # frame spans listed per group (the report stays small); the rest counted


def spans(indices: list[int], stems: list[str]) -> list[str]:
    """Runs of consecutive capture indices as "first..last (n)" (a lone frame by its stem),
    at most MAX_SPANS of them, then "+ k more frames"."""
    out: list[str] = []
    idx = sorted(indices)
    i = 0
    while i < len(idx):
        j = i
        while j + 1 < len(idx) and idx[j + 1] == idx[j] + 1:
            j += 1
        a, b = stems[idx[i]], stems[idx[j]]
        out.append(a if i == j else f"{a}..{b} ({j - i + 1})")
        i = j + 1
    if len(out) > MAX_SPANS:
        rest = sum(_count(s) for s in out[MAX_SPANS:])
        out = [*out[:MAX_SPANS], f"+ {rest} more frames"]
    return out


def _count(span: str) -> int:
    return int(span.rsplit("(", 1)[1].rstrip(")")) if span.endswith(")") else 1


def describe(models: list[list[int]], stems: list[str], mapper: str = "incremental") -> dict:
    """Facts for sfm.json about the models SfM made.

    Args:
        models: per model, the capture indices of the photos it registered; the first is
            the model kept (the largest).
        stems: the capture's frame stems, in capture order.
        mapper: the mapper that made them; a split left by the incremental mapper is told
            that the global mapper may join it (it needs no triangulated points to cross a
            weak link in the walk, but places the joined parts less precisely:
            docs/figures.md#poses-mapper).
    Returns:
        {"groups": [{"frames": n, "spans": [...], "kept": bool}, ...],
         "left_out": spans of the photos in no kept model, "warnings": [one line, ...]}
    """
    n = len(stems)
    groups = [
        {"frames": len(m), "spans": spans(m, stems), "kept": k == 0} for k, m in enumerate(models)
    ]
    kept = set(models[0]) if models else set()
    left = [i for i in range(n) if i not in kept]
    in_other = sorted({i for m in models[1:] for i in m} - kept)
    warnings = []
    big = [m for m in models if len(m) >= SPLIT_MIN_IMAGES]
    if len(big) > 1:
        parts = "; ".join(", ".join(spans(m, stems)) for m in big)
        warnings.append(
            f"SfM made {len(big)} models it could not join ({parts}): the photos may show "
            f"different places, or parts that no photo links; only the largest "
            f"({len(models[0])} photos) is used"
            + ("" if mapper == "global" else "; poses.mapper=global may join them")
        )
    if n and len(left) > DROPPED_WARN_FRAC * n:
        warnings.append(
            f"{len(left)} of {n} photos ({100 * len(left) / n:.0f} %) are left out of the "
            f"model ({len(in_other)} in other models, {len(left) - len(in_other)} in none): "
            f"{', '.join(spans(left, stems))}"
        )
    for w in warnings:
        log.warning("sfm: %s", w)
    return {"groups": groups, "left_out": spans(left, stems), "warnings": warnings}


def track_pixels(
    rec: pycolmap.Reconstruction, im: pycolmap.Image, intr: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """(pixel [N, 2], integer centres; z-depth [N]) of the image's triangulated keypoints in
    the frame's camera `intr`: where they were detected, or, when the frame was made pinhole
    (undistort.py: `intr` has no distortion, SfM's camera has), where that pinhole camera
    sees their points."""
    obs = im.get_observation_points2D()
    xyz = np.array([rec.points3D[p.point3D_id].xyz for p in obs]).reshape(-1, 3)
    w2c = im.cam_from_world().matrix()  # [3, 4]
    z = xyz @ w2c[2, :3] + w2c[2, 3]  # [N]
    cam = rec.camera(im.camera_id)
    lens = any(cam.params[i] != 0 for i in cam.extra_params_idxs())  # SfM's distortion
    if any(intr.dist) or not lens:
        return np.array([p.xy for p in obs], np.float64).reshape(-1, 2) - 0.5, z
    c2w = np.linalg.inv(np.vstack([w2c, [0.0, 0.0, 0.0, 1.0]]))  # [4, 4]
    return project(xyz, intr.K, c2w)[0], z  # behind the camera: dropped by callers (z > 0)


def sparse_depth(rec: pycolmap.Reconstruction, im: pycolmap.Image, intr: Intrinsics) -> np.ndarray:
    """z-depth (metres) of the image's triangulated keypoints at their nearest pixel
    (track_pixels), 0 elsewhere; the nearest point wins where two fall in one pixel.
    Returns float32 [H, W]."""
    d = np.zeros((intr.height, intr.width), np.float32)
    if not im.num_points3D:
        return d
    xy, z = track_pixels(rec, im, intr)
    u, v = np.round(xy[:, 0]).astype(int), np.round(xy[:, 1]).astype(int)
    ok = (z > 0) & (u >= 0) & (v >= 0) & (u < intr.width) & (v < intr.height)
    order = np.argsort(-z[ok])  # far first, so nearer points overwrite
    d[v[ok][order], u[ok][order]] = z[ok][order]
    return d


def metric_scale(
    cfg: PosesConfig, cap: Capture, rec: pycolmap.Reconstruction, ids: list[int], kept: list[int]
) -> tuple[float, dict]:
    """Metric scale of the model (see scale.py), chosen by cfg.scale_from.

    `kept` are the registered frames' indices in the capture, `ids` their COLMAP image ids.
    """
    how = cfg.scale_from
    if how == "auto" and not cap.has_depth:  # a given length first, else the priors
        how = "camera_height" if cfg.camera_height else "priors"
        how = "distance" if cfg.known_distance and not cfg.camera_height else how
    ims = [rec.image(i) for i in ids]  # registered images, in capture order
    if how in ("auto", "depth"):
        if not cap.has_depth:
            missing = next(f.stem for f in cap.frames if f.depth is None)
            raise BlunfError(f"poses.scale_from=depth: frame {missing!r} has no depth map")
        ratios = []
        for im, i in zip(ims, kept, strict=True):
            f = cap.frames[i]
            xy, z = track_pixels(rec, im, f.intrinsics)  # [N, 2], [N]
            depth = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)  # type: ignore[arg-type]
            cam = rec.camera(im.camera_id)
            wh = (int(cam.width), int(cam.height))
            ratios.append(scale_mod.depth_ratios(xy, z, depth, wh))
        return scale_mod.scale_from_depth(ratios)
    if how == "distance":
        first, last = cap.frames[0].stem, cap.frames[-1].stem
        if kept[0] != 0 or kept[-1] != len(cap.frames) - 1:
            raise BlunfError(
                f"poses.scale_from=distance: the first ({first!r}) and last ({last!r}) frames "
                "must both register to use poses.known_distance"
            )
        c0, c1 = ims[0].projection_center(), ims[-1].projection_center()
        return scale_mod.scale_from_distance(c0, c1, float(cfg.known_distance or 0), (first, last))
    if how in ("camera_height", "priors"):
        centers = np.array([im.projection_center() for im in ims])  # [C, 3]
        # rows 0 and 1 of world-to-camera rotation = the camera's x and y axes in the world
        rots = np.array([im.cam_from_world().rotation.matrix() for im in ims])  # [C, 3, 3]
        points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)  # [N, 3]
        if how == "priors" and cfg.scale_from == "auto":
            try:
                return scale_mod.scale_from_priors(centers, rots[:, 0], rots[:, 1], points)
            except BlunfError as e:  # auto: as before the priors, SfM units with a warning
                log.warning("%s; poses stay in arbitrary SfM units", e)
                return 1.0, {"method": "none", "how": f"scale_from=auto: {e}; SfM units"}
        if how == "priors":
            return scale_mod.scale_from_priors(centers, rots[:, 0], rots[:, 1], points)
        return scale_mod.scale_from_camera_height(
            centers, rots[:, 0], rots[:, 1], points, float(cfg.camera_height or 0)
        )
    return 1.0, {"method": "none", "how": "no metric scale: SfM units (arbitrary)"}

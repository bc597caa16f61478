"""What the align implementations share: depth samples with normals, rotations, the floor.

Not an implementation itself (the registry in `__init__` lists those): `gravity`, `floor`
and `auto` call these helpers, then `finish` writes the aligned frames and align.json.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import open3d as o3d

from stages.align.config import AlignConfig, AlignInputs, AlignOutputs
from stages.align.manhattan import heading_turn, rot_z
from stages.common.camera import check_pose, depth_to_points, x_axes_square
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth, write_json

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])
UNDER_FLOOR_MAX = 0.05  # sparse points: a floor has at most this fraction of the points below
#                         the cameras lying under it (see _sparse_floor): 10 % under the
#                         counter tops of the photos-only 7-Scenes kitchen; 0.1-2.6 % under
#                         true floors (as measured for the poses stage's metric scale)
FLOOR_MARGIN = 0.05  # ... lying under it by more than this fraction of its depth below them
FLOOR_PERCENTILE = 2.0  # ... then the floor is the median of this lowest percent of them
#                         (the poses stage's metric scale takes the same lowest 2 %)


def load(inputs: AlignInputs) -> Capture:
    """The input capture; every frame must have a finite rigid pose."""
    cap = Capture.load(inputs.frames)
    if not cap.frames:
        raise BlunfError(f"align: {inputs.frames} has no frames")
    for f in cap.frames:
        if f.pose is None:
            raise BlunfError(
                f"align: frame {f.stem!r} of {inputs.frames} has no pose (run the poses stage)"
            )
        check_pose(f.pose, f"align: frame {f.stem!r} of {inputs.frames}")
    return cap


@dataclass(frozen=True)
class Samples:
    """Depth points of a few frames in the input world, with their normals."""

    points: np.ndarray  # [N, 3] world points, metres
    normals: np.ndarray  # [N, 3] unit normals (sign arbitrary)
    frames: int  # frames sampled
    stride: int = 1  # the smallest pixel stride used (see sample_stride)
    sparse: bool = False  # some depth map was sparse (SfM tracks of a photos-only capture)


def sample(cap: Capture, cfg: AlignConfig, where: Path) -> Samples:
    """Back-project `cfg.frames_used` evenly spaced depth maps (every `sample_stride` pixel).

    Normals are estimated within each frame (k nearest neighbours), so a small pose error
    between frames does not blur them.
    """
    with_depth = [f for f in cap.frames if f.depth is not None]
    no_depth = BlunfError(
        f"align: no depth to find the floor in {where}; give depth or set align.impl=none"
    )
    if not with_depth:
        raise no_depth
    n_used = min(cfg.frames_used, len(with_depth))
    idx = np.unique(np.linspace(0, len(with_depth) - 1, n_used).round().astype(int))
    pts, nrm, strides, sparse = [], [], [], False
    for i in idx:
        f = with_depth[i]
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)  # [H, W] metres, 0 = none
        intr = f.intrinsics
        if d.shape != (intr.height, intr.width):
            intr = intr.scaled(d.shape[1], d.shape[0])
        # sparse depth (SfM tracks, photos only): every reading counts
        dense = (d > 0).mean() >= 0.5
        stride = sample_stride(d.shape, cfg) if dense else 1
        sparse |= not dense
        strides.append(stride)
        p, _ = depth_to_points(d, intr.K, np.asarray(f.pose), stride)  # [n, 3]
        if len(p) <= cfg.normal_neighbours:
            continue
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(cfg.normal_neighbours))
        pts.append(p)
        nrm.append(np.asarray(pc.normals))
    if not pts:
        raise no_depth
    return Samples(np.concatenate(pts), np.concatenate(nrm), len(idx), min(strides), sparse)


def sample_stride(shape: tuple[int, ...], cfg: AlignConfig) -> int:
    """The pixel stride for a depth map of shape (H, W): `cfg.stride`, lowered (to 1 at
    worst) so that the map gives at least `cfg.min_samples` samples."""
    h, w = shape[0], shape[1]
    fit = int(np.sqrt(h * w / cfg.min_samples))  # (h / s) (w / s) >= min_samples
    return max(1, min(cfg.stride, fit))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The minimal rotation taking direction `a` onto direction `b`. Returns [3, 3]."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:  # opposite: half turn about an axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions, degrees."""
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


MIN_TURN_DEG = 20.0  # level_up: the cameras' x axes must turn through at least this much


def cameras_up(poses: np.ndarray) -> np.ndarray:
    """Mean of the cameras' up axes (-y in OpenCV convention) over poses [C, 4, 4]. [3]."""
    u = -poses[:, :3, 1].mean(axis=0)
    n = np.linalg.norm(u)
    return u / n if n > 1e-9 else UP.copy()


def level_up(poses: np.ndarray, max_roll_deg: float) -> tuple[np.ndarray | None, dict]:
    """(up or None, facts): the direction square to every camera's x axis over poses
    [C, 4, 4] (x_axes_square), when the cameras were held level (COLMAP's
    model_orientation_aligner reads gravity from the images' orientations on the same
    assumption): trusted only when the axes are level to within max_roll_deg RMS and turn
    through at least MIN_TURN_DEG. A handheld capture rolls a few degrees (the 7-Scenes
    kitchen: 5.3 RMS) and is not read this way; a tripod, a gimbal or a rendered walk is.
    facts: the RMS roll and turn in degrees (None with fewer than 3 cameras)."""
    if len(poses) < 3 or max_roll_deg <= 0:
        return None, {"level_roll_deg": None, "level_turn_deg": None}
    up, rms = x_axes_square(np.asarray(poses, np.float64)[:, :3, 0])
    roll, turn = np.degrees(np.arcsin(np.clip(rms[[2, 1]], 0.0, 1.0)))
    facts = {"level_roll_deg": round(float(roll), 3), "level_turn_deg": round(float(turn), 1)}
    if roll > max_roll_deg or turn < MIN_TURN_DEG:
        return None, facts
    return (up if up @ cameras_up(poses) >= 0 else -up), facts


def dominant_up(normals: np.ndarray, up0: np.ndarray, cfg: AlignConfig) -> np.ndarray | None:
    """The common normal of the horizontal surfaces (floor, tables, counters), near `up0`.

    Starts from the normals within `up_cone_deg` of `up0` and narrows the cone to
    `max_tilt_deg` around the current estimate: the principal direction of the selected
    normals (sign-free). Returns a unit [3] on the side of `up0`, or None without support.
    """
    u = up0
    cones = np.concatenate(
        [np.linspace(cfg.up_cone_deg, cfg.max_tilt_deg, 5), [cfg.max_tilt_deg] * 3]
    )
    for cone in cones:
        sel = np.abs(normals @ u) >= np.cos(np.radians(cone))
        if sel.sum() < 3:
            return None
        n = normals[sel]  # [M, 3]
        _, vecs = np.linalg.eigh(n.T @ n)
        u = vecs[:, -1] * (1.0 if vecs[:, -1] @ up0 >= 0 else -1.0)
    return u if angle_deg(u, up0) <= cfg.up_cone_deg else None


@dataclass(frozen=True)
class Floor:
    """The floor found among points in a z-up frame."""

    z: float  # height of the floor, metres
    normal: np.ndarray | None  # [3] unit normal fitted to the floor inliers (z >= 0), if any
    inlier_fraction: float  # fraction of all sampled points within plane_dist of the floor
    note: str  # how the floor was found when it was not the normal way, else ""


def find_floor(
    points: np.ndarray,
    normals: np.ndarray,
    cam_z: np.ndarray,
    cfg: AlignConfig,
    sparse: bool = False,
) -> Floor:
    """The lowest large horizontal plane below the cameras.

    Args:
        points: [N, 3] points in a frame whose z is (roughly) up. normals: [N, 3].
        cam_z: [C] camera centre heights in that frame.
    Horizontal points (normal within `max_tilt_deg` of z) below the median camera height are
    binned by height (`plane_dist` bins, summed over 3 neighbouring bins); the lowest bin
    holding `min_floor_fraction` of them, climbed to its local peak, is the floor. Counters
    and tables are higher, the ceiling is above the cameras, and scattered noise below the
    floor never piles up into such a peak.

    With `sparse` points (SfM tracks, photos only) a textureless floor may give few points
    and no up-facing normals while counter tops give many: when more than UNDER_FLOOR_MAX of
    the points below the cameras lie under the plane found (none can be seen through a
    floor), the floor is where all of them pile up lowest, whatever their normals
    (_sparse_floor, as the poses stage's metric scale does). Dense depth: unchanged.
    """
    z = points[:, 2]
    horiz = np.abs(normals[:, 2]) >= np.cos(np.radians(cfg.max_tilt_deg))
    zh = z[horiz & (z < np.median(cam_z))]  # [M]
    floor_z, note = None, ""
    if zh.size >= 3:
        lo, step = float(zh.min()), cfg.plane_dist
        # [B]; at least 3 bins, else the 'same' convolution below is longer than counts
        counts = np.bincount(np.floor((zh - lo) / step).astype(np.int64), minlength=3)
        support = np.convolve(counts, np.ones(3, np.int64), mode="same")  # [B]
        cand = np.flatnonzero(support >= cfg.min_floor_fraction * zh.size)
        if cand.size:
            i = int(cand[0])
            while i + 1 < support.size and support[i + 1] >= support[i]:
                i += 1
            centre = lo + (i + 0.5) * step
            floor_z = float(np.median(zh[np.abs(zh - centre) <= 1.5 * step]))
    if sparse and floor_z is not None:
        floor_z, note = _sparse_floor(z, cam_z, floor_z)
    if floor_z is None:
        floor_z = float(np.percentile(z, 1))
        note = (
            f"no horizontal surface below the cameras holds {cfg.min_floor_fraction:.0%} of the "
            "horizontal points; floor put at the 1st percentile of point heights"
        )
    inl = np.abs(z - floor_z) <= cfg.plane_dist  # [N]
    return Floor(
        floor_z, _plane_normal(points[inl & horiz], cfg.plane_dist), float(inl.mean()), note
    )


def _sparse_floor(z: np.ndarray, cam_z: np.ndarray, floor_z: float) -> tuple[float, str]:
    """(floor height, note) for sparse point heights z [N] given the horizontal plane at
    floor_z: kept unless more than UNDER_FLOOR_MAX of the points below the cameras (heights
    cam_z [C]) lie more than FLOOR_MARGIN of its depth under it. Then the floor is the median
    of the lowest FLOOR_PERCENTILE % of the points below the cameras: a textureless floor
    gives SfM a thin, spread pile (its percentile alone is the pile's top), and a pile
    search finds a lower counter or shelf first (7-Scenes kitchen: 0.5 m above the floor)."""
    cam = float(np.median(cam_z))
    below = z[z < cam]  # [M]
    if below.size < 20 or not floor_z < cam:
        return floor_z, ""
    under = float(np.mean(below < floor_z - FLOOR_MARGIN * (cam - floor_z)))
    if under <= UNDER_FLOOR_MAX:
        return floor_z, ""
    low = below[below <= np.percentile(below, FLOOR_PERCENTILE)]
    return float(np.median(low)), (
        f"{under:.0%} of the points below the cameras lie under the horizontal plane at "
        f"{floor_z:.2f} m (no floor): floor from the lowest {FLOOR_PERCENTILE:g} % of them"
    )


def _plane_normal(p: np.ndarray, spread: float) -> np.ndarray | None:
    """Least-squares plane normal of points [M, 3] (towards +z); None when they span no plane."""
    if len(p) < 10:
        return None
    q = p - p.mean(axis=0)
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    if s[1] / np.sqrt(len(p)) < spread:  # collinear or tiny: no reliable tilt
        return None
    n = vt[2]
    return n if n[2] >= 0 else -n


def finish(
    cap: Capture,
    out: Path,
    R: np.ndarray,
    floor_z: float | None,
    info: dict,
    free_yaw: bool = False,
) -> AlignOutputs:
    """Apply T to every pose; write frames.json and align.json. With `free_yaw` the turn
    about z is then set by the first camera (manhattan.heading_turn).

    T turns the world by R about the vertical through the mean camera centre c, then shifts
    the floor to z = 0: T x = R (x - c) + c, with z lowered by floor_z (the floor height after
    R). Turning about the origin instead would swing a room 10 km out by metres for a
    fraction of a degree; about c, the room stays where its cameras are.
    """
    if not np.all(np.isfinite(R)) or (floor_z is not None and not np.isfinite(floor_z)):
        raise BlunfError(
            f"align: no floor found in {cap.root} (no usable depth points); check the depth "
            "maps or set align.impl=none"
        )
    if free_yaw:
        turn = heading_turn(R, np.asarray(cap.frames[0].pose), bool(info.get("squared")))
        info = {**info, "heading_turn_deg": turn}
        if turn is not None:
            R = rot_z(turn) @ R
    c = cap.poses()[:, :3, 3].mean(axis=0)  # [3] mean camera centre
    T = np.eye(4)
    T[:3, :3] = R
    T[:2, 3] = (c - R @ c)[:2]
    T[2, 3] = -(floor_z or 0.0)
    frames = [replace(f, pose=T @ np.asarray(f.pose)) for f in cap.frames]
    gravity = None
    if cap.gravity is not None:
        g = R @ np.asarray(cap.gravity, np.float64)
        gravity = (float(g[0]), float(g[1]), float(g[2]))
    outs = AlignOutputs.at(out)
    # T turns about the mean camera centre and puts the floor at z = 0: a far capture's
    # offset (ingest's recentring) stays the same in x and y, none in z
    origin = (cap.origin[0], cap.origin[1], 0.0)
    replace(cap.with_frames(frames), gravity=gravity, origin=origin).save(outs.frames)
    facts = {"T": T.tolist(), "floor_z_before": floor_z, **info}
    write_json(outs.align, facts)
    log.info(
        "align: %s, floor at %s m before the shift; %s",
        info.get("method"),
        None if floor_z is None else round(floor_z, 3),
        info.get("notes") or "no notes",
    )
    return outs


def describe(
    method: str,
    up_from: str,
    notes: list[str],
    s: Samples,
    fl: Floor,
    cam_dev: float,
    yaw: dict,
    t0: float,
) -> dict:
    """align.json's description of a solve (shared by the gravity and floor impls)."""
    return {
        "method": method,
        "inlier_fraction": fl.inlier_fraction,
        "up_from": up_from,
        "notes": "; ".join(notes),
        "frames_used": s.frames,
        "stride": s.stride,
        "points": len(s.points),
        # how far the fitted floor plane leans from the up axis (a check of both), degrees
        "floor_tilt_deg": None if fl.normal is None else angle_deg(fl.normal, UP),
        "cameras_up_deg": cam_dev,
        **yaw,
        "seconds": round(time.perf_counter() - t0, 3),
    }

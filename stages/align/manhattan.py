"""Manhattan yaw: turn the up-aligned world about z so the main wall directions lie on x and y.

Walls, cabinet fronts and furniture sides have near-horizontal normals. Their azimuths θ,
folded modulo 90 degrees (ψ = 4θ on the circle; the sign of a normal drops out too), pile up
at the room's dominant direction θ0. Turning the world by -θ0 + k 90 degrees puts the walls
on the axes; of those four turns the smallest is taken, so an already square world is kept.

When the input world's yaw is arbitrary (SfM's world, which differs from run to run), the
smallest turn is not the same on every run: `heading_turn` then picks the turn from the
first camera instead, so the plan of one capture always comes out in one frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from stages.align.config import AlignConfig
from stages.align.lines import MIN_EDGE_VOTES, edge_directions
from stages.common.capture import Capture
from stages.common.errors import BlunfError

log = logging.getLogger(__name__)

MIN_NORMALS = 100  # fewer near-horizontal normals than this: no walls seen, yaw kept
BINS = 360  # histogram of ψ = 4θ: 1 degree bins of ψ (0.25 degree of θ)
SMOOTH_BINS = 8  # the histogram is summed over ± this many bins (± 2 degrees of θ)
HALF_WIDTH_DEG = 5.0  # refinement: normals within this azimuth of the mode (fold included)
REFINE_STEPS = 10  # median-shift steps of the mode (exact data: converges in 1-2)


@dataclass(frozen=True)
class Yaw:
    """The Manhattan yaw found in a set of normals."""

    yaw_deg: float | None  # turn about +z to apply, degrees in [-45, 45); None = keep the yaw
    confidence: float  # |mean exp(4iθ)| over the near-horizontal normals (1 = all square)
    normals: int  # near-horizontal normals used
    note: str  # why the yaw is kept, else ""


def find_yaw(
    normals: np.ndarray,
    cfg: AlignConfig,
    min_confidence: float | None = None,
    min_count: int = MIN_NORMALS,
) -> Yaw:
    """The smallest turn about +z that puts the dominant wall direction on the axes.

    Args:
        normals: [N, 3] unit normals (sign arbitrary) in a frame whose z is up (or the
            horizontal directions of lines: the fold modulo 90 degrees makes them alike).
        min_confidence: the resultant below which the yaw is kept
            (cfg.manhattan_min_confidence when None).
        min_count: fewer near-horizontal normals than this: no walls seen, the yaw is kept.
    The mode of ψ = 4θ is found on a smoothed histogram (robust to furniture at other
    angles), then refined by the median of the normals within `HALF_WIDTH_DEG` of it (a mean
    there is pulled by furniture turned a few degrees to one side).
    """
    horiz = np.abs(normals[:, 2]) <= np.sin(np.radians(cfg.max_tilt_deg))
    n = normals[horiz]  # [M, 3]
    if len(n) < min_count:
        return Yaw(
            None,
            0.0,
            len(n),
            f"manhattan: {len(n)} near-vertical surface points (< {min_count}), no walls "
            "seen; yaw kept",
        )
    psi = np.mod(4.0 * np.arctan2(n[:, 1], n[:, 0]), 2.0 * np.pi)  # [M]
    conf = float(np.abs(np.exp(1j * psi).mean()))
    least, name = (
        (cfg.manhattan_min_confidence, "manhattan_min_confidence")
        if min_confidence is None
        else (min_confidence, "lines_min_confidence")
    )
    if conf < least:
        return Yaw(
            None,
            conf,
            len(n),
            f"manhattan: wall normals show no dominant direction (resultant {conf:.2f} < "
            f"{name} {least}); yaw kept",
        )
    hist = np.bincount((psi * (BINS / (2.0 * np.pi))).astype(np.int64) % BINS, minlength=BINS)
    smooth = sum(np.roll(hist, s) for s in range(-SMOOTH_BINS, SMOOTH_BINS + 1))  # [BINS]
    psi0 = (int(np.argmax(smooth)) + 0.5) * (2.0 * np.pi / BINS)
    for _ in range(REFINE_STEPS):
        d = np.angle(np.exp(1j * (psi - psi0)))  # [M] in (-pi, pi]
        step = float(np.median(d[np.abs(d) <= 4.0 * np.radians(HALF_WIDTH_DEG)]))
        psi0 += step
        if abs(step) < 1e-12:
            break
    theta0 = float(np.angle(np.exp(1j * psi0))) / 4.0  # (-45, 45] degrees, in radians
    return Yaw(-float(np.degrees(theta0)), conf, len(n), "")


def rot_z(deg: float) -> np.ndarray:
    """Rotation by `deg` degrees about +z. Returns [3, 3]."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def edges_yaw(cap: Capture, R: np.ndarray, cfg: AlignConfig) -> Yaw:
    """The Manhattan yaw the horizontal edges of `cfg.frames_used` evenly spaced photos read
    through R (input world -> z up), at `cfg.lines_min_confidence` and MIN_EDGE_VOTES; its
    `normals` counts the edges' votes."""
    idx = np.unique(np.linspace(0, len(cap.frames) - 1, cfg.frames_used).round().astype(int))
    return find_yaw(edge_directions(cap, idx, R), cfg, cfg.lines_min_confidence, MIN_EDGE_VOTES)


def square_up(
    R: np.ndarray,
    normals: np.ndarray,
    cfg: AlignConfig,
    cap: Capture | None = None,
    sparse: bool = True,
) -> tuple[np.ndarray, dict, str]:
    """(Rz @ R, facts for align.json, note) with Rz the Manhattan yaw seen through R (input
    world -> z up): from the images' horizontal edges (lines.py) when `cfg.yaw_from` allows
    and they show the room's directions, else from the normals [N, 3] of the depth points.
    Rz = I when `cfg.manhattan` is off or no walls.

    cap: the capture whose photos' edges are read. "auto" reads them only when the normals
    come from `sparse` depth (SfM's tracks, whose normals scatter by degrees); dense depth's
    normals agree with the edges within 0.2 degrees on the kitchen and the office, and the
    photos are not read. "lines" reads them in any case."""
    if not cfg.manhattan:
        off = {"yaw_deg": 0.0, "manhattan_confidence": None, "wall_normals": None}
        return R, {**off, "squared": False}, ""
    y = find_yaw(normals @ R.T, cfg)
    facts: dict[str, object] = {
        "yaw_deg": 0.0 if y.yaw_deg is None else y.yaw_deg,
        "manhattan_confidence": y.confidence,
        "wall_normals": y.normals,
        "yaw_from": "normals",
    }
    if cap is not None and (cfg.yaw_from == "lines" or (cfg.yaw_from == "auto" and sparse)):
        e = edges_yaw(cap, R, cfg)
        facts |= {
            "lines_yaw_deg": e.yaw_deg,
            "lines_confidence": e.confidence,
            "edge_votes": e.normals,
            "normals_yaw_deg": y.yaw_deg,
        }
        if e.yaw_deg is not None:
            y = e
            facts |= {"yaw_deg": e.yaw_deg, "yaw_from": "lines"}
        elif cfg.yaw_from == "lines":
            raise BlunfError(
                f"align.yaw_from=lines: the edges of {cap.root}'s images show no room "
                f"directions ({e.note}); use auto or normals"
            )
    facts["squared"] = y.yaw_deg is not None  # the walls now lie on x and y
    if y.yaw_deg is None:
        log.info("align: %s", y.note)
        return R, facts, y.note
    return rot_z(y.yaw_deg) @ R, facts, ""


def heading_turn(R: np.ndarray, first_pose: np.ndarray, squared: bool) -> float | None:
    """Turn about +z (degrees) after R that fixes the plan's frame by the first camera: its
    viewing direction (on the floor) ends up within 45 degrees of +y ("the first photo looks
    north") by a quarter turn when the world was squared to the walls, exactly on +y when it
    was not. None when that camera looks straight up or down (no heading)."""
    f = R @ np.asarray(first_pose, np.float64)[:3, 2]  # optical axis, z up
    if np.hypot(f[0], f[1]) < 1e-3:
        return None
    az = float(np.degrees(np.arctan2(f[1], f[0])))  # (-180, 180]
    if not squared:
        return 90.0 - az
    return 90.0 * float(np.round((90.0 - az) / 90.0)) % 360.0

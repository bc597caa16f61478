"""Align without gravity: the floor plane's normal becomes +z and the floor z = 0 (then the
Manhattan yaw, see manhattan.py).

The cameras' mean up axis (-y in OpenCV convention) only guides the search: cameras that
look down at a counter tilt it by tens of degrees. The up direction is the common normal
of the horizontal surfaces near it, then refined by fitting a plane to the floor inliers.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from stages.align.config import AlignConfig, AlignInputs, AlignOutputs
from stages.align.manhattan import square_up
from stages.align.planes import (
    UP,
    Floor,
    angle_deg,
    cameras_up,
    describe,
    dominant_up,
    find_floor,
    finish,
    level_up,
    load,
    rotation_between,
    sample,
)
from stages.common.capture import Capture

log = logging.getLogger(__name__)

REFINE_STEPS = 5  # floor-plane refits of the rotation (exact data: converges in 2)
CONVERGED_DEG = 0.01  # stop refitting when the floor normal is this close to +z


def solve(cap: Capture, cfg: AlignConfig, where: Path) -> tuple[np.ndarray, float, dict]:
    """(R [3, 3], floor height after R, facts) from the floor plane found in the depth."""
    t0 = time.perf_counter()
    s = sample(cap, cfg, where)
    poses = cap.poses()  # [C, 4, 4]
    centres = poses[:, :3, 3]  # [C, 3]
    up0 = cameras_up(poses)
    notes = []
    u = dominant_up(s.normals, up0, cfg)
    up_from = "normals"  # of the horizontal surfaces
    if u is None:
        u, up_from = up0, "cameras"
        notes.append(f"no horizontal surfaces within {cfg.up_cone_deg} deg of the cameras' up")
    R = rotation_between(u, UP)

    def floor_at(R: np.ndarray) -> Floor:
        return find_floor(s.points @ R.T, s.normals @ R.T, (centres @ R.T)[:, 2], cfg, s.sparse)

    for _ in range(REFINE_STEPS):
        fl = floor_at(R)
        if fl.normal is None or angle_deg(fl.normal, UP) < CONVERGED_DEG:
            break
        R = rotation_between(fl.normal, UP) @ R
        up_from = "floor"
    fl = floor_at(R)
    if fl.normal is not None:
        up_from = "floor"
    level, level_facts = level_up(poses, cfg.level_roll_deg)
    if up_from != "floor" and level is not None:
        # no floor to fit: the normals of a plain room's few SfM points lean (the honest
        # procedural room's by 4.7 degrees, its cameras' x axes 0.03). The level cameras'
        # up is kept as it is: a plane fitted now would be to the few points that failed
        # to make a floor before (on the tests' room with no floor, an edge 0.8 degrees off)
        notes.append(
            f"no floor plane with the up from the {up_from}; the cameras are level (RMS roll "
            f"{level_facts['level_roll_deg']:.2f} deg): up square to their x axes"
        )
        R, up_from = rotation_between(level, UP), "level cameras"
        fl = floor_at(R)
    if fl.normal is None and up_from not in ("floor", "level cameras"):
        notes.append(f"too few floor inliers to fit the floor plane; up from the {up_from}")
    if fl.note:
        notes.append(fl.note)
    cam_dev = angle_deg(R @ up0, UP)
    if cam_dev > cfg.up_cone_deg:
        notes.append(f"up is {cam_dev:.0f} deg from the cameras' mean up (> up_cone_deg)")
    # about z: keeps the floor height and tilt
    R, yaw, note = square_up(R, s.normals, cfg, cap, s.sparse)
    notes += [note] if note else []
    info = describe("floor", up_from, notes, s, fl, cam_dev, yaw, t0) | level_facts
    return R, fl.z, info


def run(cfg: AlignConfig, inputs: AlignInputs, out: Path) -> AlignOutputs:
    """Rotate the floor normal onto +z and shift the floor to z = 0 (no gravity needed)."""
    log.debug("align floor: %s", cfg)  # the full config: meta.json
    cap = load(inputs)
    R, floor_z, info = solve(cap, cfg, inputs.frames)
    return finish(cap, out, R, floor_z, info, inputs.free_yaw)

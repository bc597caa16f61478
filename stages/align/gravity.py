"""Align with the capture's gravity vector: rotate it onto -z, then put the floor at z = 0."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from stages.align.config import AlignConfig, AlignInputs, AlignOutputs
from stages.align.manhattan import square_up
from stages.align.planes import (
    UP,
    angle_deg,
    cameras_up,
    describe,
    find_floor,
    finish,
    load,
    rotation_between,
    sample,
)
from stages.common.capture import Capture
from stages.common.errors import BlunfError

log = logging.getLogger(__name__)


def solve(cap: Capture, cfg: AlignConfig, where: Path) -> tuple[np.ndarray, float, dict]:
    """(R [3, 3], floor height after R, facts). R is the minimal rotation of gravity onto -z,
    then the Manhattan yaw when `cfg.manhattan` (else the input world's yaw is kept); the
    floor is searched among the depth points."""
    if cap.gravity is None:
        raise BlunfError(f"align: {where} has no gravity vector; set align.impl=floor or auto")
    t0 = time.perf_counter()
    R = rotation_between(np.asarray(cap.gravity, np.float64), -UP)
    s = sample(cap, cfg, where)
    poses = cap.poses()  # [C, 4, 4]
    cam_z = (poses[:, :3, 3] @ R.T)[:, 2]  # [C]
    fl = find_floor(s.points @ R.T, s.normals @ R.T, cam_z, cfg, s.sparse)
    cam_dev = angle_deg(R @ cameras_up(poses), UP)
    notes = [fl.note] if fl.note else []
    R, yaw, note = square_up(R, s.normals, cfg, cap, s.sparse)
    notes += [note] if note else []
    if cam_dev > 90.0:  # hand-held cameras are not upside down on average
        notes.append(f"the cameras' mean up is {cam_dev:.0f} deg from -gravity: check its sign")
        log.warning("align: %s", notes[-1])
    info = describe("gravity", "gravity", notes, s, fl, cam_dev, yaw, t0)
    return R, fl.z, info


def run(cfg: AlignConfig, inputs: AlignInputs, out: Path) -> AlignOutputs:
    """Rotate the capture's gravity onto (0, 0, -1) and shift the floor to z = 0."""
    log.debug("align gravity: %s", cfg)  # the full config: meta.json
    cap = load(inputs)
    R, floor_z, info = solve(cap, cfg, inputs.frames)
    return finish(cap, out, R, floor_z, info, inputs.free_yaw)

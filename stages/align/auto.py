"""Align with gravity when the capture gives it, else with the floor plane."""

from __future__ import annotations

import logging
from pathlib import Path

from stages.align import floor, gravity
from stages.align.config import AlignConfig, AlignInputs, AlignOutputs
from stages.align.planes import finish, load

log = logging.getLogger(__name__)


def run(cfg: AlignConfig, inputs: AlignInputs, out: Path) -> AlignOutputs:
    """`gravity` when the capture has a gravity vector, else `floor`; the choice is noted."""
    log.debug("align auto: %s", cfg)  # the full config: meta.json
    cap = load(inputs)
    if cap.gravity is not None:
        R, floor_z, info = gravity.solve(cap, cfg, inputs.frames)
        why = "auto: the capture gives gravity"
    else:
        R, floor_z, info = floor.solve(cap, cfg, inputs.frames)
        why = "auto: no gravity in the capture, floor plane used"
    info["notes"] = "; ".join(n for n in (why, info["notes"]) if n)
    return finish(cap, out, R, floor_z, info, inputs.free_yaw)

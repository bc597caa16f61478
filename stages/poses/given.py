"""Poses given by the capture: copied through unchanged (the pipeline usually skips the stage)."""

from __future__ import annotations

import logging
from pathlib import Path

from stages.common.camera import check_pose
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import write_json
from stages.poses.config import PosesConfig, PosesInputs, PosesOutputs

log = logging.getLogger(__name__)


def run(cfg: PosesConfig, inputs: PosesInputs, out: Path) -> PosesOutputs:
    """Check that every frame has a pose and write the capture back unchanged."""
    log.debug("poses: given (%s)", cfg)
    cap = Capture.load(inputs.frames)
    if not cap.frames:
        raise BlunfError(f"{inputs.frames}: the capture has no frames")
    missing = [f.stem for f in cap.frames if f.pose is None]
    if missing:
        raise BlunfError(
            f"{inputs.frames}: poses.impl=given but frame {missing[0]!r} has no pose "
            f"({len(missing)} of {len(cap.frames)} missing); use poses.impl=sfm"
        )
    for f in cap.frames:
        check_pose(f.pose, f"{inputs.frames} pose of {f.stem}")  # type: ignore[arg-type]
    outs = PosesOutputs.at(out)
    cap.save(outs.frames)
    n = len(cap.frames)
    write_json(outs.sfm, {"impl": "given", "registered": n, "total": n, "unregistered": []})
    return outs

"""What the benches read of a finished run folder (besides its report.json)."""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_json


def run_poses(run: Path) -> dict[str, np.ndarray]:
    """stem -> [4, 4] camera-to-world pose in the frame of the run's plan (the align stage's)."""
    found = sorted(glob.glob(str(Path(run) / "align" / "*" / "frames.json")))
    if not found:
        raise BlunfError(f"{run}: no align/*/frames.json (not a finished run folder)")
    cap = Capture.load(Path(max(found, key=lambda p: Path(p).stat().st_mtime)))
    return {f.stem: np.asarray(f.pose, np.float64) for f in cap.frames if f.pose is not None}


def stage_file(run: Path, stage: str, name: str) -> Path | None:
    """run/stage/<key>/name of the key report.json names (else the newest), None when none."""
    run = Path(run)
    found = []
    report = run / "report.json"
    if report.is_file():
        for s in read_json(report).get("stages", []):
            if s.get("name") == stage and s.get("key"):
                found.append(run / stage / s["key"] / name)
    found = [p for p in found if p.is_file()] or sorted(
        (Path(p) for p in glob.glob(str(run / stage / "*" / name))),
        key=lambda p: p.stat().st_mtime,
    )
    return found[-1] if found else None

"""Checks that need the capture's frames: run right after ingest (cheap, cached), before any
expensive stage, so that a bad edit spec or label map fails in seconds, not after training."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.common.capture import UNKNOWN, Capture
from stages.common.errors import BlunfError
from stages.common.io import read_label
from stages.edit import EditSpec
from stages.edit.spec import check_views


def check_capture(cap: Capture, spec: EditSpec | None, memo: Path) -> None:
    """The edit spec's views against the frame count; label ids against the class table.

    Reading every label map takes ~0.1 s a frame (Replica's): `memo` (a dotfile in the ingest
    entry) records that the maps of this ingest output passed, so a rerun does not read
    them again."""
    if spec is not None:
        check_views(spec, len(cap.frames))
    if memo.exists():
        return
    check_label_ids(cap)
    memo.touch()


def check_label_ids(cap: Capture) -> None:
    """Every id in the label maps names a class of the capture's table (or is ignored, or 255).
    A capture without a class table compares ids as they are: nothing to check."""
    if not cap.classes:
        return
    known = set(cap.classes) | set(cap.ignore) | {UNKNOWN}
    root = Path(cap.root)
    table = root / "labels.json" if (root / "labels.json").is_file() else None
    for f in cap.frames:
        if f.label is None:
            continue
        ids = np.unique(read_label(f.label))
        bad = [int(i) for i in ids if int(i) not in known]
        if bad:
            src = root / "labels" / f"{f.stem}.png"  # the capture's file, not a resized copy
            where = src if src.is_file() else f.label
            names = ", ".join(f"{k}: {v}" for k, v in sorted(cap.classes.items()))
            raise BlunfError(
                f"{where}: label id {bad[0]} is not in "
                f"{table or 'the capture class table'} ({names})"
            )

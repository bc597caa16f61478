"""Checks that need the capture's frames: run right after ingest (cheap, cached), before any
expensive stage, so that a bad edit spec or label map fails in seconds, not after training."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stages.common.capture import UNKNOWN, Capture
from stages.common.classes import HEIGHT as HEIGHT_CLASSES
from stages.common.errors import BlunfError
from stages.common.io import read_label
from stages.common.memory import check_memory
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


STEREO_BYTES = 48  # per plane and pixel of a view's sweep: its [D, HW] float32 warps and
#                    costs (stages/nerf/stereo.py `_cost`), a dozen alive at once


def check_sizes(cap: Capture, stereo: Any) -> None:
    """Settings whose memory follows the photos' size, refused in one line before any work:
    the plane sweep's cost volume (planes x pixels of the largest view)."""
    if not cap.frames or not getattr(stereo, "enabled", False):
        return
    px = max(f.intrinsics.width * f.intrinsics.height for f in cap.frames)
    px /= max(1, stereo.scale) ** 2 * stereo.coarse**2
    planes = max(stereo.planes, stereo.refine)
    check_memory(planes * px * STEREO_BYTES, f"depth.stereo.planes={stereo.planes}")


def check_edit_classes(cap: Capture, spec: EditSpec | None, labelling: str) -> None:
    """An edit selecting a class the plan cannot hold (not in the capture's class table, or
    not floor / occupied when the plan is labelled by height) fails here, after ingest,
    not after the NeRF trained."""
    if spec is None:
        return
    by_height = labelling == "height" or (labelling == "auto" and not cap.has_labels)
    if not by_height and not cap.classes:
        return  # ids compared as they are: names unknown until the plan
    names = set(HEIGHT_CLASSES.values()) if by_height else set(cap.classes.values())
    for e in spec.edits:
        if e.select.kind == "class" and e.select.value not in names:
            raise BlunfError(
                f"{e.select.where}: no class {e.select.value!r} in the capture's classes "
                f"({', '.join(sorted(names))})"
            )


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

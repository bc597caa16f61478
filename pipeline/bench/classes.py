"""The classes the geometry gives a plan against the classes a capture's own labels give it.

For a capture with depth and per-pixel classes (Replica office0):
  labels     the plan `blunf run` gives from the capture as it is (its classes), read in three
             classes: floor, rug and mat as floor; wall, window, door, pillar, blinds, panel
             and curtain as wall; the rest as object (ceiling and unlabelled: unknown);
  geometry   the plan from a copy with the same colour, depth (and poses, when the capture
             has them) but no labels: its classes come from the semantics stage.
The geometry plan is scored against the labels plan (fwIoU and IoU per class) on the labels
plan's cells within its projected points' bounds (bench.real's `observed`; "padded" counts
the grid's padding band too, where both plans clamp their field), through the
similarity between the two runs' camera centres, with the confusion of each class.

    python -m pipeline.bench.classes CAPTURE --out DIR [--set k=v ...] [--frames N]
writes DIR/classes.json; DIR/labels and DIR/geometry are the run folders (reused when
finished: a second call with other --set reruns the geometry run's changed stages only).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.bench.real import confusion, observed, run_plan, stripped_copy
from pipeline.bench.runs import run_poses
from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import CEILING_NAME, FLOOR_NAME, OBJECT_NAME, WALL_NAME
from stages.common.errors import BlunfError
from stages.common.gt_frame import plan_frame
from stages.common.io import write_json
from stages.common.plan_metrics import evaluate_plan

THREE = {0: FLOOR_NAME, 1: WALL_NAME, 2: OBJECT_NAME}
AS_FLOOR = (FLOOR_NAME, "rug", "mat")  # Replica's class names as ours
AS_WALL = (WALL_NAME, "window", "door", "pillar", "blinds", "panel", "curtain")
AS_NONE = (CEILING_NAME, "unlabelled", "undefined", "")  # left unknown


def three_classes(bp: Blueprint) -> Blueprint:
    """The plan relabelled into floor / wall / object (see the module doc)."""
    lut = np.full(256, UNKNOWN, np.uint8)
    for i, name in bp.classes.items():
        key = name.strip().lower()
        lut[i] = 0 if key in AS_FLOOR else 1 if key in AS_WALL else 255 if key in AS_NONE else 2
    return replace(bp, labels=lut[bp.labels], classes=dict(THREE), instances=None)


def score(labels_run: Path, geometry_run: Path) -> dict:
    """The geometry run's plan against the labels run's, read in three classes."""
    padded = three_classes(Blueprint.load(Path(labels_run) / "blueprint.npz"))
    ref = observed(labels_run, padded)
    pred = Blueprint.load(Path(geometry_run) / "blueprint.npz")
    m, frame = plan_frame(True, run_poses(geometry_run), run_poses(labels_run), ref.grid)
    return {
        "plan": evaluate_plan(pred, ref, m),
        "padded": evaluate_plan(pred, padded, m),  # the grid's padding band counted too
        "frame": frame,
        "confusion": confusion(pred, ref, m),
    }


def measure(src: Path, out: Path, args: list[str], frames: int = 0) -> dict:
    """Both runs of `src` under `out`, scored; writes and returns out/classes.json."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pick = ["--frames", str(frames)] if frames else []
    base = ["--set", "run.methods=[blunf]", *pick]
    run_plan(src, out / "labels", base)
    bare = stripped_copy(src, out / "geometry-capture", sensor=True)
    run_plan(bare, out / "geometry", [*base, *args])
    res = {**score(out / "labels", out / "geometry"), "capture": str(src), "args": args}
    write_json(out / "classes.json", res)
    return res


def summary(res: dict) -> str:
    """One line: fwIoU and per-class IoU, within the bounds and padded."""
    out = []
    for key in ("plan", "padded"):
        p = res[key]
        per = " ".join(f"{c} {p['per_class'].get(c, float('nan')):.1f}" for c in THREE.values())
        out.append(f"{key}: fwIoU {p['fwiou']:.1f} | IoU {per}")
    return " || ".join(out) + f" | {res['frame']}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.classes", description=__doc__)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--set", action="append", default=[], help="geometry run: stage.key=v")
    ap.add_argument("--frames", type=int, default=0, help="N views spread evenly (0 = all)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        res = measure(a.capture, a.out, [x for s in a.set for x in ("--set", s)], a.frames)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(summary(res))
    print(json.dumps(res["confusion"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())

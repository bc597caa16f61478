"""Helpers shared by the stability tests: a tiny room, a run that must succeed, finiteness."""

from __future__ import annotations

import glob
import json
import math
from pathlib import Path

import numpy as np

from pipeline.cli import main
from stages.common.blueprint import Blueprint

FAST = ["--set", "blueprint.blunf.steps=60", "--set", "blueprint.blunf.batch=4096"]
VOXEL = 0.05  # fusion voxel (metres) of every run here: coarse, a tiny room fuses in < 1 s


def small_room(out: Path) -> Path:
    """8 views of 64x48: the smallest room that still gives every class a few hundred points."""
    from stages.synth import make_room

    return make_room(out, views=8, seed=3, size=(64, 48))


def run_ok(capture: Path, out: Path, *extra: str) -> dict:
    """`blunf run` that must succeed; returns report.json."""
    rc = main(["run", str(capture), "--out", str(out), *FAST, *extra])
    assert rc == 0, f"blunf run failed ({rc})"
    return json.loads((out / "report.json").read_text(), parse_constant=_no_constant)


def _no_constant(name: str) -> float:
    raise AssertionError(f"report.json holds {name}: not JSON, and not a number")


def assert_finite_outputs(out: Path) -> None:
    """No NaN or inf in the plan, the projected points, any stage's plan or the metrics
    (report.json is parsed strictly: a NaN or Infinity token anywhere in it fails)."""
    report = json.loads((out / "report.json").read_text(), parse_constant=_no_constant)
    _finite_tree(report["metrics"], "report.json metrics")
    for p in [out / "blueprint.npz", *map(Path, glob.glob(f"{out}/blueprint/*/blueprint.npz"))]:
        bp = Blueprint.load(p)
        assert bp.grid.cell > 0 and np.isfinite(bp.grid.cell), p
        assert np.all(np.isfinite(bp.grid.origin)), p
        assert bp.labels.size > 0, p
    for p in glob.glob(f"{out}/project/*/points.npz"):
        with np.load(p) as z:
            assert len(z["xyz"]) > 0 and np.all(np.isfinite(z["xyz"])), p


def _finite_tree(v: object, where: str) -> None:
    if isinstance(v, dict):
        for k, x in v.items():
            _finite_tree(x, f"{where}.{k}")
    elif isinstance(v, list):
        for i, x in enumerate(v):
            _finite_tree(x, f"{where}[{i}]")
    elif isinstance(v, float):
        assert math.isfinite(v), f"{where} = {v}"

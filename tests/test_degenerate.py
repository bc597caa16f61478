"""Degenerate inputs end in a plan with finite numbers (or one clean error line): invalid
depth (zero, NaN, inf, negative), one view, two identical views, collinear cameras, a single
class, tiny and larger images."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.io import (
    read_depth,
    read_label,
    write_depth_png,
    write_image,
    write_json,
    write_label_png,
)
from tests.runs import FAST, VOXEL, assert_finite_outputs, run_ok, small_room


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return small_room(tmp_path_factory.mktemp("degenerate") / "room")


def _npy_depth(cap: Path) -> None:
    for p in sorted((cap / "depth").glob("*.png")):
        np.save(p.with_suffix(".npy"), read_depth(p))
        p.unlink()


def bad_depth(cap: Path) -> None:
    """Frame 0 all zero, 1 with a NaN patch, 2 an inf patch, 3 a negative patch (float .npy)."""
    _npy_depth(cap)
    files = sorted((cap / "depth").glob("*.npy"))
    d = np.load(files[0])
    np.save(files[0], np.zeros_like(d))
    for f, v in zip(files[1:4], (np.nan, np.inf, -1.0), strict=True):
        d = np.load(f)
        d[10:30, 10:40] = v
        np.save(f, d)


def identical_views(cap: Path) -> None:
    """Two frames, the second a byte copy of the first (image, depth, label and pose)."""
    keep = sorted(p.stem for p in (cap / "images").iterdir())[0]
    for sub in ("images", "depth", "labels"):
        for p in (cap / sub).iterdir():
            if p.stem != keep:
                p.unlink()
        src = next((cap / sub).iterdir())
        shutil.copyfile(src, src.with_name("zz" + src.name))
    cams = json.loads((cap / "cameras.json").read_text())
    cams["frames"] = {keep: cams["frames"][keep], "zz" + keep: cams["frames"][keep]}
    write_json(cap / "cameras.json", cams)


def one_class(cap: Path) -> None:
    """Every pixel labelled floor (class 0)."""
    for p in (cap / "labels").iterdir():
        write_label_png(p, np.zeros_like(read_label(p)))


def collinear(cap: Path) -> None:
    """Re-render the room from 5 cameras on one straight line, all looking the same way."""
    from stages.synth.render import Tracer, intrinsics_for, look, render
    from stages.synth.room import build_room

    room = build_room(3)
    tracer, intr = Tracer(room.parts), intrinsics_for(64, 48)
    cx, cy, a, _ = room.loop
    for sub in ("images", "depth", "labels"):
        shutil.rmtree(cap / sub)
        (cap / sub).mkdir()
    frames = {}
    for k, x in enumerate(np.linspace(cx - 0.6 * a, cx + 0.6 * a, 5)):
        pose = look(np.array([x, cy, 1.4]), math.pi / 2, -math.radians(25))
        v = render(tracer, pose, intr)
        stem = f"{k:04d}"
        write_image(cap / "images" / f"{stem}.png", v.rgb)
        write_depth_png(cap / "depth" / f"{stem}.png", v.depth)
        write_label_png(cap / "labels" / f"{stem}.png", v.label)
        frames[stem] = {"pose": pose.tolist()}
    cams = json.loads((cap / "cameras.json").read_text())
    cams["frames"] = frames
    write_json(cap / "cameras.json", cams)


DEGENERATE = {
    "nan_inf_zero_negative_depth": (bad_depth, ()),
    "single_view": (None, ("--frames", "1")),
    "two_identical_views": (identical_views, ()),
    "collinear_cameras": (collinear, ()),
    "one_class": (one_class, ()),
}


@pytest.mark.parametrize("name", list(DEGENERATE))
def test_degenerate_inputs_give_finite_outputs(room, tmp_path, name):
    edit, extra = DEGENERATE[name]
    cap = tmp_path / "cap"
    shutil.copytree(room, cap)
    if edit is not None:
        edit(cap)
    report = run_ok(cap, tmp_path / "run", "--set", f"fusion.voxel={VOXEL}", *extra)
    assert_finite_outputs(tmp_path / "run")
    bp = Blueprint.load(tmp_path / "run" / "blueprint.npz")
    seen = set(np.unique(bp.labels).tolist()) - {UNKNOWN}
    assert seen, "the plan is all unknown"
    if name == "one_class":
        assert seen == {0}  # floor everywhere: nothing else was ever labelled
    m = report["metrics"]["blueprint"]["blunf"]
    assert 0 <= m["pacc"] <= 100 and 0 <= m["completeness"] <= 100


def test_all_depth_invalid_is_a_one_line_error(room, tmp_path, capsys):
    cap = tmp_path / "cap"
    shutil.copytree(room, cap)
    _npy_depth(cap)
    for p in (cap / "depth").iterdir():
        np.save(p, np.full((48, 64), np.nan, np.float32))
    rc = main(["run", str(cap), "--out", str(tmp_path / "run"), *FAST])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("blunf: error:"), err
    assert "depth" in err[0]
    assert not list((tmp_path / "run").rglob(".tmp-*"))


@pytest.mark.parametrize(
    "size, extra",
    [
        # align.stride = 8 alone would leave 2x1 depth samples of a 16x12 frame (under
        # normal_neighbours + 1): align lowers the stride to reach align.min_samples
        pytest.param((16, 12), (), id="16x12-default"),
        pytest.param((16, 12), ("--set", "align.stride=1"), id="16x12-stride1"),
        pytest.param((240, 180), (), id="240x180"),
    ],
)
def test_image_sizes(tmp_path, size, extra):
    """A 16x12 capture (8x6 projected pixels a view) and a larger one both give plans."""
    from stages.synth import make_room

    tiny = size[0] < 100
    cap = make_room(tmp_path / "cap", views=8 if tiny else 3, seed=5, size=size)
    # 8x6 points a view scatter over a 2 cm plan, and the vector export of such a speckled
    # plan takes ~10 s (stages/export: components are polygonised once per file format);
    # 10 cm cells suit images this small.
    cell = ("--set", "project.cell=0.1") if tiny else ()
    run_ok(cap, tmp_path / "run", "--set", f"fusion.voxel={VOXEL}", *cell, *extra)
    assert_finite_outputs(tmp_path / "run")

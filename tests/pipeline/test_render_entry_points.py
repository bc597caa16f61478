"""One edited view through every entry point: the edit stage's `after` picture, `blunf render`
and the studio's scene give the same pixels, on the volume path and on the fast path (each
renders through `stages.edit.view.EditedView`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.render import Scene, run_files
from pipeline.studio.state import Session
from stages.common.io import read_image
from stages.edit.spec import load_spec
from tests.runs import VOXEL, run_ok, small_room

# a field edit and a mask edit together: the mask is the unedited scene's, drawn over the
# removal (the part a copy of the view would most easily get wrong)
SPEC = """\
edits:
  - {select: {class: table}, op: remove}
  - {select: {class: chair}, op: recolor, color: [40, 200, 40], strength: 0.8}
  - {select: {class: sofa}, op: mask}
views: [0]
"""
SEPARATOR = 4  # the stage's before | after pictures: white pixels between them


RUN = ["--set", f"fusion.voxel={VOXEL}", "--set", "nerf.train.time_budget=0",
       "--set", "nerf.train.max_steps=20", "--set", "nerf.threads=1",
       "--set", "edit.render.threads=1", "--set", "edit.gif.frames=2"]  # fmt: skip


@pytest.mark.slow  # a run with a NeRF (20 steps: pixels are compared, not judged), ~1 min
def test_every_entry_point_renders_the_same_pixels(tmp_path) -> None:
    cap = small_room(tmp_path / "room")
    spec = tmp_path / "edits.yaml"
    spec.write_text(SPEC)
    run = tmp_path / "run"
    for path in ("volume", "surface"):  # the second run renders the edits only
        run_ok(cap, run, "--edits", str(spec), *RUN, "--set", f"edit.render.path={path}")
        _same_pixels(run, spec, path == "surface", tmp_path / f"{path}.png")


def _same_pixels(run: Path, spec: Path, fast: bool, out: Path) -> None:
    scene = Scene(run_files(run))
    stem = scene.cap.frames[0].stem
    pair = read_image(run / "edits" / f"{stem}.png")  # the edit stage's before | after
    w = (pair.shape[1] - SEPARATOR) // 2
    stage_before, stage_after = pair[:, :w], pair[:, w + SEPARATOR :]
    assert not np.array_equal(stage_before, stage_after)  # the edits show

    args = ["render", str(run), "--view", "0", "--edits", str(spec), "--out", str(out)]
    assert main(args + (["--fast"] if fast else [])) == 0
    np.testing.assert_array_equal(read_image(out), stage_after)

    session = Session(run)  # the studio's: a tab standing at input view 0
    edits = load_spec(spec).edits
    pose, intr = session.scene.view(0)
    after = session.scene.render(pose, intr, edits, fast=fast).rgb
    np.testing.assert_array_equal(after, stage_after)
    before = session.scene.render(pose, intr, edits, before=True, fast=fast).rgb
    np.testing.assert_array_equal(before, stage_before)

"""The planner: which stages a capture needs, and why each skipped one is skipped.

Captures are built in memory (the planner reads only what the frames hold, never the files),
except the ground-truth folder, whose files it checks for.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import default_config, load_config
from pipeline.planner import make_plan
from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError

INTR = Intrinsics(50.0, 50.0, 16.0, 12.0, 32, 24)


def _capture(
    n: int = 3, depth: bool = True, poses: bool = True, labels: bool = True, gt: Path | None = None
) -> Capture:
    """n frames whose files need not exist; depth / poses / labels present or not."""
    frames = tuple(
        Frame(
            stem=f"{i:04d}",
            image=Path(f"/nowhere/images/{i:04d}.png"),
            intrinsics=INTR,
            depth=Path(f"/nowhere/depth/{i:04d}.png") if depth else None,
            label=Path(f"/nowhere/labels/{i:04d}.png") if labels else None,
            pose=np.eye(4) if poses else None,
        )
        for i in range(n)
    )
    return Capture(root=Path("/nowhere"), frames=frames, classes={0: "floor"}, gt=gt)


def test_capture_with_depth_skips_nerf_depth():
    plan = make_plan(_capture(), default_config())
    step = plan.get("depth")
    assert (step.impl, step.run, step.reason) == ("stereo", False, "capture gives depth")
    # nor is the NeRF trained for anything else: the default methods are blunf and mvr
    nerf = plan.get("nerf")
    assert not nerf.run and nerf.reason == "no edits and no NeRF baseline asked"
    assert not plan.runs("edit")


def test_capture_without_depth_plans_nerf_depth():
    plan = make_plan(_capture(depth=False, poses=False), default_config())
    step = plan.get("depth")
    assert (step.stage, step.impl, step.run, step.work) == ("depth", "stereo", True, None)
    assert "no depth" in step.reason and "'0000'" in step.reason  # names a frame without depth
    assert plan.runs("poses") and plan.get("poses").impl == "sfm"
    # the depth step is the photos-only path: fusion still runs on its output
    assert plan.runs("fusion")


def test_photos_only_depth_is_stereo_alone_unless_a_field_is_asked_for(tmp_path):
    # the field's fill off, no edits, no NeRF top view: the depth stage sweeps stereo and
    # trains no field, and the nerf step is skipped with its reason
    phone = _capture(depth=False, poses=False, labels=False)
    alone = ["depth.field.fill=false"]
    plan = make_plan(phone, load_config(sets=alone))
    step, nerf = plan.get("depth"), plan.get("nerf")
    assert step.run and (step.impl, step.work) == ("stereo", None)
    assert "plane-sweep stereo" in step.reason and "no field trained" in step.reason
    assert not nerf.run and nerf.reason == "no edits and no NeRF baseline asked"
    # an edit spec trains the nerf step's field (on the fused depth), not a second one for
    # depth
    plan = make_plan(phone, load_config(sets=alone), tmp_path / "spec.yaml")
    assert plan.get("depth").impl == "stereo" and plan.get("nerf").run
    # the default: stereo first, the field only if the readings cover too little (decided
    # by the depth stage once it has swept: stages/depth/stage.py)
    plan = make_plan(phone, default_config())
    step = plan.get("depth")
    assert step.impl == "stereo" and "depth.field.fill auto" in step.reason
    assert "under 50 %" in step.reason
    # fill true: the field always, after the sweep
    plan = make_plan(phone, load_config(sets=["depth.field.fill=true"]))
    step = plan.get("depth")
    assert step.impl == "stereo" and "(depth.field.fill)" in step.reason
    # not a boolean nor auto: one line naming the key
    with pytest.raises(BlunfError, match="depth.field.fill"):
        load_config(sets=["depth.field.fill=sometimes"])
    with pytest.raises(BlunfError, match=r"depth\.field\.below"):
        load_config(sets=["depth.field.below=1.5"])
    # stereo off, or the field asked for by name: only the field gives depth
    for sets in (["depth.stereo.enabled=false"], ["depth.impl=field"]):
        step = make_plan(phone, load_config(sets=sets)).get("depth")
        assert step.impl == "field" and "SfM tracks" in step.reason


def test_photos_with_given_poses_train_the_field_for_depth():
    # poses given, no depth: no SfM tracks bound a sweep, so the field learns depth
    plan = make_plan(_capture(depth=False, poses=True, labels=False), default_config())
    step = plan.get("depth")
    assert step.impl == "field" and "no SfM tracks" in step.reason


def test_part_of_the_depth_missing_is_an_error():
    # depth for frames 0000 and 0002 but not 0001: a broken capture, not a photos-only one
    cap = _capture()
    frames = list(cap.frames)
    frames[1] = replace(frames[1], depth=None)
    with pytest.raises(BlunfError, match="no depth for frame '0001' while frame '0000' has"):
        make_plan(cap.with_frames(frames), default_config())


def test_nerf_top_method_runs_the_nerf():
    cfg = load_config(sets=["run.methods=[blunf, nerf_top]"])
    plan = make_plan(_capture(), cfg)
    nerf = plan.get("nerf")
    assert (nerf.impl, nerf.run) == ("grid", True)
    assert nerf.reason == "asked for: NeRF top view baseline"
    # one blueprint step per method, in the order asked
    assert [s.impl for s in plan.steps if s.stage == "blueprint"] == ["blunf", "nerf_top"]
    assert not plan.runs("edit") and plan.get("edit").reason == "no edit spec given"
    # depth still comes from the capture: the NeRF trains on it, it does not replace it
    assert not plan.runs("depth")


def test_edit_spec_runs_the_nerf_and_the_edit(tmp_path):
    spec = tmp_path / "edits.yaml"
    plan = make_plan(_capture(), default_config(), edits=spec)
    nerf, edit = plan.get("nerf"), plan.get("edit")
    assert nerf.run and nerf.reason == "asked for: edit spec"
    assert edit.run and edit.reason == f"edit spec {spec}"
    # both reasons at once
    cfg = load_config(sets=["run.methods=[nerf_top]"])
    assert make_plan(_capture(), cfg, spec).get("nerf").reason == (
        "asked for: NeRF top view baseline, edit spec"
    )


def test_photos_only_with_nerf_top_trains_both():
    # no depth and the NeRF baseline asked: the NeRF runs twice in the recipe (on the photos
    # and SfM tracks for depth, then on the fused depth and labels): both steps are planned
    cfg = load_config(sets=["run.methods=[nerf_top]"])
    plan = make_plan(_capture(depth=False, poses=False, labels=False), cfg)
    assert plan.runs("depth") and plan.runs("nerf")
    assert plan.runs("semantics")  # labels derived from geometry (semantics.impl=geometry)


def test_poses_and_labels_given_are_skipped_with_reasons():
    plan = make_plan(_capture(), default_config())
    assert plan.get("poses").reason == "capture gives poses" and not plan.runs("poses")
    assert plan.get("semantics").reason == "capture gives labels"
    # every skipped step says why
    assert all(s.reason for s in plan.steps if not s.run)


def test_given_poses_required_when_asked():
    cfg = load_config(sets=["poses.impl=given"])
    with pytest.raises(BlunfError, match="poses.impl=given"):
        make_plan(_capture(poses=False), cfg)


def test_evaluate_follows_the_ground_truth_files(tmp_path):
    gt = tmp_path / "gt"
    gt.mkdir()
    # a gt/ folder without the known files, and labels: scored on held-out views only
    plan = make_plan(_capture(gt=gt), default_config())
    assert plan.get("evaluate").reason == "held-out views"
    (gt / "blueprint.npz").write_bytes(b"")  # the planner only checks that the file is there
    plan = make_plan(_capture(gt=gt), default_config())
    # with a ground-truth plan, held-out views are not scored instead
    assert plan.get("evaluate").reason == "ground truth: blueprint"
    plan = make_plan(_capture(labels=False), load_config(sets=["semantics.impl=height"]))
    # no ground truth, no held-out views: the plan's observation is measured all the same
    assert plan.runs("evaluate") and plan.get("evaluate").reason == (
        "observation only (no ground truth)"
    )

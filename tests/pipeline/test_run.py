"""The whole path on a tiny room: outputs, report, cache behaviour, CLI errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.cli import main
from stages.common.blueprint import Blueprint
from stages.common.classes import OBJECT
from stages.common.components import component_map

FAST = ["--set", "blueprint.blunf.steps=300", "--set", "fusion.voxel=0.04"]


def _run(capture: Path, out: Path, *extra: str) -> dict:
    assert main(["run", str(capture), "--out", str(out), *FAST, *extra]) == 0
    return json.loads((out / "report.json").read_text())


def _status(report: dict) -> dict[str, str]:
    return {f"{s['name']}:{s['impl']}": s["status"] for s in report["stages"]}


def test_run_outputs_report_and_cache(tiny_room, tmp_path):
    out = tmp_path / "run"
    first = _run(tiny_room, out)
    st = _status(first)
    # The room gives poses, depth and labels: those stages are skipped, with reasons.
    assert st["poses:given"] == "skipped" and st["depth:stereo"] == "skipped"
    assert st["semantics:given"] == "skipped" and st["nerf:grid"] == "skipped"
    for name in (
        "ingest:auto",
        "align:auto",
        "fusion:tsdf",
        "project:pinhole",
        "blueprint:blunf",
        "blueprint:mvr",
        "evaluate:gt",
        "export:files",
    ):
        assert st[name] == "ran", name
    assert all(s["reason"] for s in first["stages"] if s["status"] == "skipped")
    for f in ("blueprint.png", "blueprint.npz", "mesh.ply", "transforms.json"):
        assert (out / f).is_file(), f
    bp = Blueprint.load(out / "blueprint.npz")
    assert bp.labels.ndim == 2 and bp.grid.cell > 0 and "floor" in bp.classes.values()
    m = first["metrics"]["blueprint"]
    assert set(m) == {"blunf", "mvr"}
    for k in ("pacc", "fwiou", "miou", "completeness"):
        assert 0 <= m["blunf"][k] <= 100
    # BluNF labels the room's extent up to project.fill_radius of a point: the tiny room's
    # sparse views leave about 1 % of the ground truth's cells unknown (measured 99.0)
    assert m["blunf"]["completeness"] >= 97.0
    assert first["metrics"]["observation"]["invented_pct"] <= 3.0
    assert m["blunf"]["fwiou"] > 60  # a tiny room at 96x72 and 300 steps; the real bar is in bench
    # a ground-truth plan to score against: every view goes into the plan, none held out
    assert "heldout_pacc" not in m["blunf"]
    ev = next(s for s in first["stages"] if s["name"] == "evaluate")
    assert ev["reason"] == "ground truth: blueprint, poses"

    # Nothing changed: everything that ran is now cached, and the outputs are identical.
    before = (out / "blueprint.npz").read_bytes()
    second = _run(tiny_room, out)
    assert {k: v for k, v in _status(second).items() if v != "skipped"} == {
        k: "cached" for k, v in st.items() if v == "ran"
    }
    assert (out / "blueprint.npz").read_bytes() == before
    assert second["metrics"] == first["metrics"]

    # A blueprint setting reruns the BluNF blueprint (and what follows it), nothing upstream.
    third = _run(tiny_room, out, "--set", "blueprint.blunf.seed=7")
    st3 = _status(third)
    assert st3["blueprint:blunf"] == "ran"
    for name in ("ingest:auto", "align:auto", "fusion:tsdf", "project:pinhole", "blueprint:mvr"):
        assert st3[name] == "cached", name


def test_capture_is_never_written(tiny_room, tmp_path):
    before = sorted((p.relative_to(tiny_room), p.stat().st_mtime_ns) for p in tiny_room.rglob("*"))
    _run(tiny_room, tmp_path / "run")
    after = sorted((p.relative_to(tiny_room), p.stat().st_mtime_ns) for p in tiny_room.rglob("*"))
    assert before == after


def test_frames_budget_changes_views(tiny_room, tmp_path):
    r = _run(tiny_room, tmp_path / "run", "--frames", "4")
    ingest = next(s for s in r["stages"] if s["name"] == "ingest")
    assert ingest["status"] == "ran"
    frames = json.loads(next((tmp_path / "run" / "ingest").glob("*/frames.json")).read_text())
    assert len(frames["frames"]) == 4


def test_bad_inputs_one_line_errors(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    (tmp_path / "empty").mkdir()
    assert main(["run", str(tmp_path / "empty"), "--out", str(tmp_path / "r2")]) == 2
    assert "empty" in capsys.readouterr().err


def test_unknown_config_key_fails_before_work(tiny_room, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(tiny_room), "--out", str(out), "--set", "fusion.voxell=0.1"]) == 2
    err = capsys.readouterr().err
    assert "fusion.voxell" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_module_entry_point_matches_console_script(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline",
            "run",
            str(tmp_path / "missing"),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert r.stderr.strip().startswith("blunf: error:") and "Traceback" not in r.stderr


def test_a_run_logs_a_short_story(tiny_room, tmp_path):
    """A whole run on the console: a line or two per stage, none from the libraries' chatter
    (ezdxf announced each of the 13 DXF dictionaries it created, twice per run), no stage's
    whole config (the runner names the settings that differ) and no temporary paths."""
    out = tmp_path / "run"
    r = subprocess.run(
        [sys.executable, "-m", "pipeline", "run", str(tiny_room), "--out", str(out), *FAST],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert not [x for x in lines if "ezdxf" in x or "ACAD" in x], lines
    assert not [x for x in lines if "Config(" in x or ".tmp-" in x], lines
    stages = len(json.loads((out / "report.json").read_text())["stages"])
    assert len(lines) <= 5 * stages, "\n".join(lines)


def test_killed_stage_leaves_no_entry(tiny_room, tmp_path):
    """A crash inside a stage leaves only a temp folder, swept on the next run."""
    from pipeline.cache import Cache

    out = tmp_path / "run"
    _run(tiny_room, out)
    # Simulate a run killed mid-stage: a temp folder from a dead process.
    dead = out / "fusion" / ".tmp-deadbeef-999999"
    dead.mkdir()
    (dead / "partial.ply").write_text("x")
    Cache(out).sweep()
    assert not dead.exists()
    assert all(
        (p / "meta.json").is_file()
        for p in (out / "fusion").iterdir()
        if not p.name.startswith(".")
    )


def test_semantics_from_geometry_when_labels_are_hidden(tiny_room, tmp_path):
    """Without labels the semantics stage derives floor / wall / object from the fused mesh
    and the plan uses them; semantics.impl=height keeps the height bands instead."""
    capture = tmp_path / "nolabels"
    shutil.copytree(tiny_room, capture, ignore=shutil.ignore_patterns("labels", "labels.json"))
    out = tmp_path / "run"
    r = _run(capture, out)
    st = _status(r)
    assert st["semantics:geometry"] == "ran"
    sem = next(s for s in r["stages"] if s["name"] == "semantics")
    assert sem["reason"] == "capture has no labels" and sem["facts"]["objects"] >= 1
    assert set(r["plan"]["classes"]) == {"floor", "wall", "object"}
    m = r["metrics"]["blueprint"]["blunf"]
    # scored against the GT plan coarsened to floor / wall / object
    assert set(m["per_class"]) == {"floor", "wall", "object"} and m["pacc"] > 60
    assert "heldout_pacc" not in m

    h = _run(capture, out, "--set", "semantics.impl=height")
    st = _status(h)
    assert st["semantics:height"] == "skipped" and st["fusion:tsdf"] == "cached"
    sem = next(s for s in h["stages"] if s["name"] == "semantics")
    assert sem["reason"].startswith("semantics.impl=height")
    assert set(h["plan"]["classes"]) == {"floor", "occupied"}
    assert "heldout_pacc" not in h["metrics"]["blueprint"]["blunf"]  # no labels to score

    # no ground-truth plan: views 4 and 12 of 16 are held out (project.holdout_every = 8)
    # and the plan is scored on their own (derived) labels
    (capture / "gt" / "blueprint.npz").unlink()
    g = _run(capture, tmp_path / "run-nogt")
    m = g["metrics"]["blueprint"]["blunf"]
    assert m["heldout_views"] == 2 and m["heldout_pacc"] > 60
    ev = next(s for s in g["stages"] if s["name"] == "evaluate")
    assert ev["reason"] == "ground truth: poses; held-out views"


def test_objects_of_a_label_free_capture_stay_apart_in_the_blunf_plan(tiny_room, tmp_path):
    """Without labels the semantics stage finds object instances, and the BluNF plan keeps
    them apart although it fills the unseen cells between them with "object": in this room
    (16 views of 96x72) chair_1 and chair_2 stand side by side, chair_4 beside cabinet_1, and
    each pair is one object region of the class raster (checked below: one component without
    the instance layer). With it, each object is its own component, named by its instance."""
    capture = tmp_path / "nolabels"
    shutil.copytree(tiny_room, capture, ignore=shutil.ignore_patterns("labels", "labels.json"))
    out = tmp_path / "run"
    # the floor the views saw past the fused surface's rims (semantics.floor_fill.past) and
    # the floor the views looked past with no point on it (blueprint.blunf.free_floor) open
    # the gap between chair_4 and cabinet_1 in the class raster itself: off here, so that the
    # pair touches and the instance layer is what keeps it apart
    off = ("--set", "semantics.floor_fill.past=0", "--set", "blueprint.blunf.free_floor=false")
    r = _run(capture, out, *off)
    key = next(s["key"] for s in r["stages"] if s["impl"] == "blunf")
    bp = Blueprint.load(out / "blueprint" / key / "blueprint.npz")
    assert bp.instances is not None
    gt = {
        v["name"]: v["bbox"]
        for v in json.loads((capture / "gt/instances.json").read_text()).values()
    }
    names = ["chair_1", "chair_2", "chair_4", "cabinet_1"]
    xy = np.array([[(gt[n][0] + gt[n][3]) / 2, (gt[n][1] + gt[n][4]) / 2] for n in names])
    row, col, inside = bp.grid.cell_of(xy)  # the GT centre of each object on the plan
    assert inside.all() and (bp.labels[row, col] == OBJECT).all()
    flat = component_map(replace(bp, instances=None))[row, col]  # class only: as before
    assert flat[0] == flat[1] and flat[2] == flat[3]
    cmap = component_map(bp)[row, col]
    assert len(set(cmap.tolist())) == 4, dict(zip(names, cmap.tolist(), strict=True))
    inst = bp.instances[row, col]
    assert (inst > 0).all() and len(set(inst.tolist())) == 4
    comps = {c["id"]: c for c in r["plan"]["components"]}  # the product's plan is BluNF's
    assert [comps[k]["instance"] for k in cmap.tolist()] == inst.tolist()

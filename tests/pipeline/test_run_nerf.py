"""The NeRF paths through the whole pipeline (slow: each trains a NeRF): edits and the NeRF
top view on a room with depth, and phone captures (photos and intrinsics only)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline.cli import main
from stages.common.blueprint import Blueprint
from stages.common.components import class_name, component_map

ROOT = Path(__file__).resolve().parents[2]
FAST = ["--set", "blueprint.blunf.steps=300", "--set", "fusion.voxel=0.04"]
NERF = [
    "--set",
    "nerf.train.time_budget=0",
    "--set",
    "nerf.train.max_steps=200",
    "--set",
    "nerf.threads=1",
    "--set",
    "depth.field.train.time_budget=0",
    "--set",
    "depth.field.train.max_steps=200",
    "--set",
    "depth.threads=1",
]


def _run(capture: Path, out: Path, *extra: str) -> dict:
    assert main(["run", str(capture), "--out", str(out), *FAST, *NERF, *extra]) == 0
    return json.loads((out / "report.json").read_text())


def _status(report: dict) -> dict[str, str]:
    return {f"{s['name']}:{s['impl']}": s["status"] for s in report["stages"]}


@pytest.mark.slow
def test_edits_and_nerf_top(tiny_room, tmp_path):
    spec = tmp_path / "edits.yaml"
    spec.write_text(
        "edits:\n  - select: {class: chair}\n    op: recolor\n    color: [200, 40, 40]\n"
        "views: [0, 8]\n"
    )
    out = tmp_path / "run"
    args = ("--edits", str(spec), "--set", "run.methods=[blunf,mvr,nerf_top]")
    args += ("--set", "edit.gif.frames=4")
    r = _run(tiny_room, out, *args)
    st = _status(r)
    assert st["depth:stereo"] == "skipped"  # the room gives depth
    for name in ("nerf:grid", "blueprint:nerf_top", "edit:nerf"):
        assert st[name] == "ran", name
    nerf = next(s for s in r["stages"] if s["name"] == "nerf")
    assert nerf["reason"] == "asked for: NeRF top view baseline, edit spec"
    n = r["metrics"]["nerf"]
    assert n["steps"] == 200 and n["stop_reason"] == "steps"
    assert n["depth_absrel"] < 0.05 and n["psnr_heldout"] > 15
    assert set(r["metrics"]["blueprint"]) == {"blunf", "mvr", "nerf_top"}
    (e,) = r["metrics"]["edit"]
    # every chair recoloured: the changed pixels are the chairs' (GT instance masks)
    assert e["op"] == "recolor" and e["changed_iou"] > 0.5 and e["psnr_outside"] > 25
    for f in ("orbit.gif", "blueprint_edited.png", "mesh_edited.ply", "0000.png", "0008.png"):
        assert (out / "edits" / f).is_file(), f

    again = _run(tiny_room, out, *args)  # nothing changed: nothing recomputed
    assert {s["status"] for s in again["stages"]} <= {"cached", "skipped"}
    assert again["metrics"] == r["metrics"]


@pytest.mark.slow
def test_demo_edits_change_only_their_objects(tmp_path):
    # make demo's edit run as it is (60-view room, configs/edit-fast.yaml: 200 steps, the
    # edits rendered through the fused mesh, refined at 1 cm round each selection;
    # configs/edits/demo.yaml), on one thread, in every rendered view that shows the object
    # (None: the view shows neither it nor a change). Measured: remove chair_2 0.935 / 0.926
    # / 0.954, recolor sofa_1 - / 0.982 / 0.981, retexture table_1 0.911 / - / 0.991
    # (without the refinement: 0.876 / 0.866 / 0.914, - / 0.974 / 0.967, 0.906 / - / 0.987).
    # The target, 0.9 in every view, is the removal's bar (2.5 points under its lowest view);
    # the paints keep 3 points under theirs (the retexture's view 4 moved 0.89-0.92 with the
    # refined mesh's block size).
    from stages.synth import make_room

    cap = make_room(tmp_path / "capture", views=60, seed=0)
    out = tmp_path / "run"
    cfg, spec = ROOT / "configs" / "edit-fast.yaml", ROOT / "configs" / "edits" / "demo.yaml"
    args = ["run", str(cap), "--out", str(out), "--config", str(cfg), "--edits", str(spec)]
    assert main(args) == 0
    r = json.loads((out / "report.json").read_text())
    assert r["metrics"]["nerf"]["steps"] == 200
    ms = r["metrics"]["edit"]
    assert [m["op"] for m in ms] == ["remove", "recolor", "retexture"]
    for m, shown, bar in zip(ms, (3, 2, 2), (0.9, 0.95, 0.88), strict=True):
        seen = [v for v in m["changed_iou_views"] if v is not None]
        assert len(m["changed_iou_views"]) == 3 and len(seen) == shown, m
        assert min(seen) >= bar and m["psnr_outside"] >= 40, m
    stats = json.loads(next((out / "edit").glob("*/edit.json")).read_text())
    assert stats["render"]["refined"]["boxes"] == 3  # one round each (none is floor)
    n = r["metrics"]["nerf"]  # scored on held-out pixels, no held-out view rendered
    assert n["psnr_heldout"] > 23 and n["depth_absrel"] < 0.01, n
    assert not list((out / "nerf").glob("*/heldout/*.png"))
    got = [[g["name"] for g in e["metrics"]["gt_instances"]] for e in stats["edits"]]
    assert got == [["chair_2"], ["sofa_1"], ["table_1"]]  # one chair, not the class


@pytest.mark.slow
@pytest.mark.parametrize("field", [False, True])
def test_photos_only_capture_reaches_a_plan(tmp_path, field):
    from stages.synth import make_room

    cap = make_room(tmp_path / "phone", views=30, seed=0, size=(160, 120), photos_only=True)
    out = tmp_path / "run"
    fill = ["--set", f"depth.field.fill={str(field).lower()}"]
    r = _run(cap, out, "--config", str(ROOT / "configs" / "phone.yaml"), *fill)
    st = _status(r)
    for name in ("poses:sfm", "fusion:tsdf", "semantics:geometry", "blueprint:blunf"):
        assert st[name] == "ran", name
    # the depth stage runs; the nerf step (edits / nerf_top) is skipped with its reason
    (depth,) = [s for s in r["stages"] if s["name"] == "depth"]
    (later,) = [s for s in r["stages"] if s["name"] == "nerf"]
    assert depth["status"] == "ran" and later["status"] == "skipped"
    assert later["reason"] == "no edits and no NeRF baseline asked"
    assert depth["reason"].startswith("no depth") and depth["impl"] == "stereo"
    facts = depth["facts"]
    assert facts["kept"] > 0.3 and facts["coverage"]["sweep"] > 0.3 and facts["cpu_seconds"] > 0
    assert set(r["plan"]["classes"]) == {"floor", "wall", "object"}
    m = r["metrics"]["blueprint"]["blunf"]
    # Measured 72.0 here with the field (30 views, 160x120, 200 NeRF steps; stereo depth on
    # 67 % of the training pixels; 72.7 with the render checked against the stereo; 69.6 in
    # a later run, the same with and without phone.yaml's surface check and shrink, which
    # move the 320x240 rooms by +2 to +7) where the NeRF alone on photos and tracks gave
    # 60.5 and 63.3, against ~88 from the same room with its rendered depth. SfM is not
    # bit-reproducible across machines (CI once scored 40.7 where this machine scored 53.7):
    # the bar leaves that margin and catches a broken path (garbage depth or a wrong frame:
    # < 30; the NeRF without stereo: ~60).
    if field:  # the field trains on the stereo depth and fills its holes where confirmed
        assert "(depth.field.fill)" in depth["reason"]
        assert 0 < facts["field"]["stereo_check_kept"] < 1
        assert facts["coverage"]["field"] > facts["coverage"]["sweep"]
        assert facts["by_source"]["field"] > 0
        assert r["metrics"]["nerf"]["steps"] == 200  # the fill's field, reported as the NeRF
    else:  # stereo alone: no field trained, none reported
        assert "no field trained" in depth["reason"] and "field" not in facts
        assert "nerf" not in r["metrics"] and facts["by_source"]["field"] == 0
    assert m["frame"] == "aligned to gt poses" and m["fwiou"] > 50, m


@pytest.mark.slow
def test_photos_only_plan_is_within_5_of_the_plan_from_true_depth(tmp_path):
    """Issue 4's bar on a room no setting was tuned on (synth seed 3, 60 views of 320x240):
    the plan from its photos alone (configs/phone.yaml) against the plan from the same photos
    with their exact depth (default config; poses from SfM in both). Measured 84.6 against
    86.0 (78.1 without the floor fill, 71.4 before the fused-surface check and stereo's
    readings at full resolution). The NeRF gets a fixed step count instead of its 120 s
    budget (~265 steps here), so a slower machine trains it as far. ~9 minutes."""
    import shutil

    from stages.synth import make_room

    phone = make_room(tmp_path / "phone", views=60, seed=3, photos_only=True)
    full = make_room(tmp_path / "full", views=60, seed=3)
    with_depth = tmp_path / "with_depth"
    shutil.copytree(phone, with_depth)
    shutil.copytree(full / "depth", with_depth / "depth")
    cams = json.loads((with_depth / "cameras.json").read_text())
    cams["depth_scale"] = json.loads((full / "cameras.json").read_text())["depth_scale"]
    (with_depth / "cameras.json").write_text(json.dumps(cams))
    steps = ["--set", "depth.field.train.time_budget=0", "--set", "depth.field.train.max_steps=250"]
    config = ["--config", str(ROOT / "configs" / "phone.yaml")]
    fwiou, layout = {}, {}
    for name, cap, extra in [("photos", phone, [*config, *steps]), ("depth", with_depth, [])]:
        out = tmp_path / f"run_{name}"
        assert main(["run", str(cap), "--out", str(out), *extra]) == 0
        r = json.loads((out / "report.json").read_text())
        m = r["metrics"]["blueprint"]["blunf"]
        assert m["frame"] == "aligned to gt poses", m
        fwiou[name], layout[name] = m["fwiou"], r["metrics"]["layout"]
    print(f"\nphotos-only plan fwIoU {fwiou['photos']:.1f}, from exact depth {fwiou['depth']:.1f}")
    print(f"photos-only layout {layout['photos']}")
    assert fwiou["depth"] > 80, fwiou  # the reference itself is sound
    assert fwiou["photos"] >= fwiou["depth"] - 5, fwiou
    # the architect's drawing from the photos alone holds the layout targets
    s = layout["photos"]
    assert s["room_f1"] >= 0.9 and s["corner_f1"] >= 0.85 and s["angle_f1"] >= 0.85, s
    assert s["wall_length_err_m"] <= 0.05, s


def _click_on(run: Path, cls: str, rank: int = 0) -> tuple[float, float]:
    """World (x, y) of a cell of the rank-th largest component of class `cls` in the run's
    plan: the component's cell nearest its centroid (a centroid may fall outside an L)."""
    bp = Blueprint.load(run / "blueprint.npz")
    comps = json.loads((run / "components.json").read_text())["components"]
    comps = sorted((c for c in comps if c["class"] == cls), key=lambda c: -c["area_m2"])
    c = comps[rank]
    cells = np.argwhere(component_map(bp) == c["id"])  # [N, 2] row, col
    xy = bp.grid.centers()[cells[:, 0], cells[:, 1]]  # [N, 2]
    best = xy[np.argmin(((xy - np.asarray(c["centroid"])) ** 2).sum(axis=1))]
    return float(best[0]), float(best[1])


@pytest.mark.slow
def test_replica_edits(tmp_path):
    """Replica office_0 (SfM poses, sensor depth, instance labels): the largest sofa
    recoloured and a chair removed, each picked by a click on the plan, matched to a Replica
    sofa / chair instance, the pictures written to the run's edits/ folder, and scored
    against Replica's instance masks. The clicks come from this run's plan, in the spec's
    format, with the shipped spec's views; the shipped spec's own clicks must land on a sofa
    and a chair of this run's plan (the align stage fixes SfM's turn about z by the first
    photo, so every run gives the plan in one frame)."""
    from tests.conftest import shared_capture

    src = shared_capture("replica-office0")
    out = tmp_path / "run"
    _run(src, out)
    sofa, chair = _click_on(out, "sofa"), _click_on(out, "chair")
    shipped = (ROOT / "configs" / "edits" / "replica-office0.yaml").read_text()
    bp = Blueprint.load(out / "blueprint.npz")
    for entry, cls in zip(yaml.safe_load(shipped)["edits"], ("sofa", "chair"), strict=True):
        row, col, inside = bp.grid.cell_of(np.asarray([entry["select"]["click"]], np.float64))
        assert inside[0] and class_name(bp, int(bp.labels[row[0], col[0]])) == cls, entry
    views = next(line for line in shipped.splitlines() if line.startswith("views:"))
    spec = tmp_path / "edits.yaml"
    spec.write_text(
        "edits:\n"
        f"  - {{select: {{click: [{sofa[0]}, {sofa[1]}]}}, op: recolor, color: [180, 60, 40]}}\n"
        f"  - {{select: {{click: [{chair[0]}, {chair[1]}]}}, op: remove}}\n"
        f"{views}\n"
    )
    r = _run(src, out, "--edits", str(spec))
    st = _status(r)
    assert st["edit:nerf"] == "ran" and st["fusion:tsdf"] == "cached"
    recolor, remove = r["metrics"]["edit"]
    assert (recolor["op"], remove["op"]) == ("recolor", "remove")
    edit = next(s for s in r["stages"] if s["name"] == "edit")["facts"]["edits"]
    assert [c["class"] for c in edit[0]["components"]] == ["sofa"]
    assert [c["class"] for c in edit[1]["components"]] == ["chair"]
    # each click matched one Replica instance of its class (sofas 7 and 9, chairs 4 and 61)
    (s_id,) = [g["id"] for g in edit[0]["metrics"]["gt_instances"]]
    (c_id,) = [g["id"] for g in edit[1]["metrics"]["gt_instances"]]
    assert s_id in (7, 9) and c_id in (4, 61), (s_id, c_id)
    for m in (recolor, remove):
        assert m["changed_iou"] > 0.6 and m["psnr_outside"] > 35, m
    assert edit[1]["fill"] is not None and edit[0]["fill"] is None
    for f in ("orbit.gif", "blueprint_edited.png", "mesh_edited.ply"):
        assert (out / "edits" / f).is_file(), f
    for stem in ("0000", "0005", "0079"):
        assert (out / "edits" / f"{stem}.png").is_file(), stem

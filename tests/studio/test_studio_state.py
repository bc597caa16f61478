"""The studio without a browser: viewer camera -> pose, click -> selection, edits, save / load,
and bad input (a message, nothing applied). On a real run of a tiny room (no NeRF trained)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.render import camera_json, pose_wxyz, viewer_camera
from pipeline.studio.plan_view import StrokeDrag, cell_centre, plan_picture, screen_ray, top_view
from pipeline.studio.state import SPEC_NAME, Session
from pipeline.studio.train import Trainer, training_config
from pipeline.studio.values import floor_point
from stages.common.classes import class_color
from stages.common.errors import BlunfError
from stages.edit.render import look_at
from stages.edit.spec import load_spec
from tests.runs import VOXEL


@pytest.fixture(scope="module")
def run(studio_run) -> tuple[Path, Path]:
    return studio_run  # tests/studio/conftest.py


def _centre(cap: Path, name: str) -> tuple[float, float]:
    inst = json.loads((cap / "gt" / "instances.json").read_text())
    b = next(v["bbox"] for v in inst.values() if v["name"] == name)
    return (b[0] + b[3]) / 2, (b[1] + b[4]) / 2


def test_viewer_camera_is_the_pose_and_pinhole() -> None:
    pose = look_at(np.array([1.0, -2.0, 1.5]), np.array([3.0, 2.0, 0.3]))
    fov = np.deg2rad(50.0)
    p, intr = viewer_camera(pose[:3, 3], pose_wxyz(pose), fov, 16 / 9, 240)
    assert np.allclose(p, pose, atol=1e-9)
    assert (intr.width, intr.height) == (427, 240)
    # the top image edge is fov / 2 above the optical axis
    assert np.isclose(np.arctan((0 - 0.5 - intr.cy) / -intr.fy), fov / 2)
    # a world point straight ahead lands on the image centre
    x = pose[:3, 3] + 2.0 * pose[:3, 2]
    xc = np.linalg.inv(pose) @ np.append(x, 1.0)
    u = intr.fx * xc[0] / xc[2] + intr.cx
    assert np.isclose(u, (intr.width - 1) / 2)


def test_camera_file(tmp_path) -> None:
    pose = look_at(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0]))
    intr = {"fx": 100, "fy": 100, "cx": 39.5, "cy": 29.5, "width": 80, "height": 60}
    f = tmp_path / "cam.json"
    f.write_text(json.dumps({"pose": pose.tolist(), "intrinsics": intr}))
    p, i = camera_json(f)
    assert np.allclose(p, pose) and (i.width, i.height, i.fx) == (80, 60, 100)
    f.write_text(json.dumps({"pose": [[1, 0], [0, 1]], "intrinsics": intr}))
    with pytest.raises(BlunfError, match="cam.json: pose"):
        camera_json(f)


def test_floor_point() -> None:
    assert floor_point((1.0, 2.0, 3.0), (0.0, 0.6, -0.8)) == pytest.approx((1.0, 4.25))
    with pytest.raises(BlunfError, match="off the plan"):
        floor_point((1.0, 2.0, 3.0), (0.0, 0.6, 0.8))  # looking up: never meets the floor


def test_click_selects_the_component(run) -> None:
    cap, out = run
    s = Session(out)
    x, y = _centre(cap, "chair_2")
    sel = s.click_ray((x, y, 2.5), (0.0, 0.0, -1.0))  # a ray straight down on the chair
    assert sel.select == {"click": [round(x, 4), round(y, 4)]}
    assert sel.info["class"] == "chair"
    r, c, _ = s.scene.bp.grid.cell_of(np.array([[x, y]]))
    assert np.array_equal(sel.cells, s.scene.cmap == s.scene.cmap[r[0], c[0]])
    assert sel.info["bbox"][0] <= x <= sel.info["bbox"][2]
    # a click off the plan or a ray that misses the floor: an error, the selection kept
    with pytest.raises(BlunfError, match="outside the plan"):
        s.click(500.0, 500.0)
    with pytest.raises(BlunfError, match="off the plan"):
        s.click_ray((x, y, 2.5), (0.0, 0.0, 1.0))
    assert s.selection is sel


def test_edits_save_and_load_round_trip(run) -> None:
    cap, out = run
    s = Session(out)
    s.click(*_centre(cap, "chair_2"))
    s.apply("remove")
    s.click(*_centre(cap, "sofa_1"))
    s.apply("recolor", color=(40, 90, 200), strength=0.8)
    s.select_class("table")
    s.apply("retexture", texture="tiles.png", strength=1.0)
    s.add_stroke_point(*_centre(cap, "table_1"))
    s.add_stroke_point(_centre(cap, "table_1")[0] + 0.3, _centre(cap, "table_1")[1])
    s.apply("sketch", color=(255, 0, 0), width=0.1)
    assert s.undo() and len(s.edits) == 3 and s.redo() and len(s.edits) == 4
    path = s.save([0, 2])
    assert path == out / "studio" / SPEC_NAME
    spec = load_spec(path)  # the pipeline's own parser reads it
    assert [e.op for e in spec.edits] == ["remove", "recolor", "retexture", "sketch"]
    assert spec.views == (0, 2) and spec.edits[1].color == (40.0, 90.0, 200.0)
    assert spec.textures == ((out / "studio" / "textures" / "tiles.png").resolve(),)
    s2 = Session(out)
    assert s2.load() == 4 and s2.edits == s.edits


def test_bad_input_changes_nothing(run, tmp_path) -> None:
    cap, out = run
    s = Session(out)
    with pytest.raises(BlunfError, match="select something"):
        s.apply("remove")
    with pytest.raises(BlunfError, match="draw a stroke"):
        s.apply("sketch", color=(255, 0, 0))  # a sketch with no stroke
    with pytest.raises(BlunfError, match="notes.txt: not an image"):
        s.add_texture("notes.txt", b"these are not pixels")
    assert not (out / "studio" / "textures" / "notes.png").exists()
    assert s.edits == [] and s.version == 0
    with pytest.raises(BlunfError, match="not a run folder"):
        Session(tmp_path)
    assert main(["studio", str(tmp_path)]) == 2
    # no NeRF in this run: rendering names the command that trains one
    assert main(["render", str(out), "--view", "0", "--out", str(tmp_path / "v.png")]) == 2
    assert not (tmp_path / "v.png").exists()


def test_plan_view_click_selects_the_component_under_the_picture(run) -> None:
    # the plan's picture (panel) and the plan view (canvas, camera straight above the plan):
    # a pixel of the picture -> its plan cell -> the world point -> the canvas point where
    # the plan view shows it -> the pointer's ray -> the floor -> the same component
    cap, out = run
    s = Session(out)
    g = s.scene.bp.grid
    r, c, _ = g.cell_of(np.array([_centre(cap, "chair_2")]))
    pic = plan_picture(s.scene.bp, scale=2)
    assert pic.shape[:2] == (2 * g.shape[0], 2 * g.shape[1])
    chair = s.scene.bp.labels[r[0], c[0]]
    assert tuple(pic[2 * r[0] + 1, 2 * c[0] + 1]) == class_color(int(chair))
    xy = cell_centre(g, 2 * r[0] // 2, (2 * c[0] + 1) // 2)  # picture pixel -> cell -> world
    aspect, fov = 16 / 9, np.deg2rad(40.0)
    position, wxyz = top_view(g, aspect, fov)
    pose, intr = viewer_camera(position, wxyz, fov, aspect, 720)
    assert pose[2, 2] < -0.999  # looking down
    corners = [(g.origin[0], g.origin[1]), (g.origin[0] + g.shape[1] * g.cell, g.origin[1])]
    corners += [(g.origin[0], g.origin[1] + g.shape[0] * g.cell)]
    screen = []
    for x, y in [xy, *corners]:
        xc = np.linalg.inv(pose) @ np.array([x, y, 0.0, 1.0])
        u, v = intr.fx * xc[0] / xc[2] + intr.cx, intr.fy * xc[1] / xc[2] + intr.cy
        screen.append(((u + 0.5) / intr.width, (v + 0.5) / intr.height))
    # the whole plan in view, north up, east right
    assert all(0 <= a <= 1 and 0 <= b <= 1 for a, b in screen)
    assert screen[2][0] > screen[1][0] and screen[3][1] < screen[1][1]
    o, d = screen_ray(position, wxyz, fov, aspect, screen[0])
    sel = s.click_ray(o, d)
    assert sel.info["class"] == "chair"
    assert np.array_equal(sel.cells, s.scene.cmap == s.scene.cmap[r[0], c[0]])
    # the picture shows the selection
    pic = plan_picture(s.scene.bp, sel.cells, scale=2)
    assert tuple(pic[2 * r[0], 2 * c[0]]) != class_color(int(chair))


def test_drag_draws_the_sketch_stroke(run) -> None:
    # a drag on the plan: the grab point, then pointer points on the pointer's rays (as the
    # viewer gives them: on a plane facing the camera, here halfway to the floor)
    cap, out = run
    s = Session(out)
    g = s.scene.bp.grid
    cam, _ = top_view(g, 4 / 3)
    a = np.array(_centre(cap, "table_1"))
    b = a + np.array([0.6, 0.3])
    drag = StrokeDrag(s, min_step=g.cell / 2)
    s.add_stroke_point(*(a - 1.0))  # an older stroke: a new drag replaces it
    assert drag.start((a[0], a[1], 0.002)) == 1
    for t in np.linspace(0.0, 1.0, 40):
        p = a + t * (b - a)
        drag.move(cam, cam + 0.5 * (np.array([p[0], p[1], 0.0]) - cam))
    n = drag.end(cam, cam + 0.3 * (np.array([b[0], b[1], 0.0]) - cam))
    st = np.array(s.stroke)
    assert n == len(st) and len(st) > 5
    assert np.allclose(st[0], a, atol=1e-3) and np.allclose(st[-1], b, atol=1e-3)
    gaps = np.linalg.norm(np.diff(st, axis=0), axis=1)
    assert gaps.min() >= g.cell / 2 - 1e-3  # no crowd of points where the pointer lingers
    # every point on the segment a-b (on the floor under the pointer)
    ab = (b - a) / np.linalg.norm(b - a)
    off = (st - a) - np.outer((st - a) @ ab, ab)
    assert np.abs(off).max() < 1e-3
    e = s.apply("sketch", color=(255, 0, 0), width=0.1)
    assert e.op == "sketch" and s.edits[-1]["select"]["stroke"] == [list(p) for p in st]
    assert s.stroke == []
    # moves after the drag's end draw nothing
    assert drag.move(cam, (a[0], a[1], 0.0)) == 0


def test_training_needs_an_edit_and_takes_the_runs_config(run) -> None:
    cap, out = run
    s = Session(out)
    t = Trainer(s)
    with pytest.raises(BlunfError, match="apply an edit first"):
        t.start()
    assert t.state == "idle" and t.thread is None  # nothing started
    cfg = training_config(out, ["nerf.train.max_steps=7"])
    assert cfg["fusion"].voxel == VOXEL  # the run's own settings
    assert cfg["nerf"].train.edge_batch == 0.5  # configs/edit-fast.yaml's
    assert cfg["edit"].render.path == "surface"
    assert training_config(out)["nerf"].train.max_steps == 200
    assert cfg["nerf"].train.max_steps == 7  # and the sets given

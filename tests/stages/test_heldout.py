"""Held-out views: the project stage keeps them out of the plan, evaluate scores the plan under
their pixels (heldout_pacc). Every expected value is worked out by hand."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stages.common.blueprint import Blueprint, Grid
from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame, heldout_views
from stages.common.errors import BlunfError
from stages.common.io import write_depth_png, write_image, write_label_png
from stages.common.points import read_points
from stages.evaluate import IMPLS as EVALUATE
from stages.evaluate import EvaluateConfig, EvaluateInputs
from stages.evaluate.heldout import heldout_pacc
from stages.project import IMPLS as PROJECT
from stages.project import ProjectConfig, ProjectInputs, ProjectOutputs

# An 8x6 camera, fx = fy = 8, principal point (3.5, 2.5), 1 m above the floor at the world
# origin, looking straight down (x_cam = +x, y_cam = -y, z_cam = -z). With depth 1 m, pixel
# (u, v) lands at x = (u - 3.5) / 8, y = -(v - 2.5) / 8, z = 0: u = 0..3 give x < 0 (west
# half), u = 4..7 give x > 0; the footprint is x, y in [-0.44, 0.44] x [-0.32, 0.32].
INTR = Intrinsics(8.0, 8.0, 3.5, 2.5, 8, 6)
DOWN = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]], np.float64)
CLASSES = {0: "floor", 1: "wall", 2: "ceiling", 3: "object"}
GRID = Grid((-1.0, -1.0), 0.5, (4, 4))  # 2 m x 2 m around the footprint; x < 0 = columns 0, 1


def _capture(tmp: Path, labels: list[np.ndarray], depth: float = 1.0) -> Path:
    """One frame per label map, all from the same camera; returns frames.json."""
    root = tmp / "cap"
    for sub in ("images", "depth", "labels"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, lab in enumerate(labels):
        img, dep, lp = (root / d / f"{i}.png" for d in ("images", "depth", "labels"))
        write_image(img, np.zeros((6, 8, 3), np.uint8))
        write_depth_png(dep, np.full((6, 8), depth))
        write_label_png(lp, lab)
        frames.append(Frame(str(i), img, INTR, dep, lp, DOWN))
    Capture(root, tuple(frames), classes=CLASSES, ignore=(2,)).save(tmp / "frames.json")
    return tmp / "frames.json"


def _plan(labels: np.ndarray, classes=None) -> Blueprint:
    return Blueprint(labels.astype(np.uint8), GRID, classes or {0: "floor", 1: "wall"})


FLOOR_VIEW = np.zeros((6, 8), np.int32)  # every pixel floor


def test_all_floor_view_on_all_floor_plan_is_100_and_swapped_is_0(tmp_path):
    cap = Capture.load(_capture(tmp_path, [FLOOR_VIEW]))
    # 48 pixels, stride 1, all floor, all on floor cells
    r = heldout_pacc(_plan(np.zeros((4, 4))), cap, ["0"], stride=1)
    assert r == {
        "heldout_pacc": 100.0,
        "heldout_pacc_surface": 100.0,  # a flat floor reads the cell under it either way
        "heldout_pacc_behind": 100.0,
        "heldout_pixels": 48,
        "heldout_views": 1,
    }
    # the plan says wall everywhere: no pixel agrees
    assert heldout_pacc(_plan(np.ones((4, 4))), cap, ["0"], stride=1)["heldout_pacc"] == 0.0
    # swapping the names instead of the ids: the plan's id 0 is now "wall", matched by name
    swapped = _plan(np.zeros((4, 4)), {0: "wall", 1: "floor"})
    assert heldout_pacc(swapped, cap, ["0"], stride=1)["heldout_pacc"] == 0.0


def test_unknown_cells_count_as_wrong_and_ignored_pixels_are_not_scored(tmp_path):
    lab = FLOOR_VIEW.copy()
    lab[0, 4:] = 2  # 4 ceiling pixels (ignored), east half of the top row
    lab[5, 4:] = 255  # 4 unknown pixels, east half of the bottom row
    cap = Capture.load(_capture(tmp_path, [lab]))
    plan = np.zeros((4, 4))
    plan[:, :2] = 255  # west half unknown: the 24 pixels u = 0..3 read it
    r = heldout_pacc(_plan(plan), cap, ["0"], stride=1)
    # scored: 48 - 4 ignored - 4 unknown = 40; right: the east half's 24 - 8 = 16 pixels
    assert r["heldout_pixels"] == 40
    assert r["heldout_pacc"] == pytest.approx(100.0 * 16 / 40)
    # stride 2 keeps pixels (u, v) in {1, 3, 5, 7} x {1, 3, 5}: 12; row 0 (ceiling) is not
    # among them, (5, 5) and (7, 5) are unknown: 10 scored; right: u = 5, 7 on rows 1, 3 = 4
    r2 = heldout_pacc(_plan(plan), cap, ["0"], stride=2)
    assert (r2["heldout_pixels"], r2["heldout_pacc"]) == (10, 40.0)


def test_a_class_the_plan_lacks_and_points_outside_the_plan_are_wrong(tmp_path):
    lab = FLOOR_VIEW.copy()
    lab[:, :4] = 3  # west half "object": the plan has no such class
    cap = Capture.load(_capture(tmp_path, [lab]))
    r = heldout_pacc(_plan(np.zeros((4, 4))), cap, ["0"], stride=1)
    assert r["heldout_pacc"] == 50.0
    # a plan that does not reach the footprint: 1 cell far to the north-east
    far = Blueprint(np.zeros((1, 1), np.uint8), Grid((5.0, 5.0), 0.5, (1, 1)), {0: "floor"})
    assert heldout_pacc(far, cap, ["0"], stride=1)["heldout_pacc"] == 0.0
    with pytest.raises(BlunfError, match="'7'"):
        heldout_pacc(far, cap, ["7"], stride=1)


# A 16x12 camera 1 m above the floor at the world origin looking along +x (x_cam = -y,
# y_cam = -z, z_cam = +x), fx = fy = 16: every pixel at depth 0.9 lies on the plane x = 0.9.
LEVEL = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1], [0, 0, 0, 1]], np.float64)
INTR_16 = Intrinsics(16.0, 16.0, 7.5, 5.5, 16, 12)


def test_a_wall_face_is_right_in_its_own_cell_or_half_a_cell_behind(tmp_path):
    # A wall face at x = 0.9 m, seen head-on. On 0.5 m cells the face runs through the cell
    # x in [0.5, 1.0), whose centre (0.75) lies in front of the face: by the ground truth's
    # convention (one ray down through each cell centre) that cell is floor and the wall
    # begins at x = 1.0; a plan from the points alone makes the face's own cell wall.
    root = tmp_path / "cap"
    for sub in ("images", "depth", "labels"):
        (root / sub).mkdir(parents=True)
    img, dep, lp = (root / d / "0.png" for d in ("images", "depth", "labels"))
    write_image(img, np.zeros((12, 16, 3), np.uint8))
    write_depth_png(dep, np.full((12, 16), 0.9))
    write_label_png(lp, np.ones((12, 16), np.int32))  # every pixel wall
    Capture(root, (Frame("0", img, INTR_16, dep, lp, LEVEL),), classes=CLASSES).save(
        tmp_path / "frames.json"
    )
    cap = Capture.load(tmp_path / "frames.json")
    grid = Grid((-1.0, -1.0), 0.5, (4, 6))  # x in [-1, 2), y in [-1, 1)
    centre_x = -1.0 + 0.5 * (np.arange(6) + 0.5)

    def score(wall_cols: np.ndarray) -> tuple:
        labels = np.zeros((4, 6), np.uint8)
        labels[:, wall_cols] = 1
        r = heldout_pacc(Blueprint(labels, grid, {0: "floor", 1: "wall"}), cap, ["0"], stride=1)
        assert r["heldout_pixels"] == 192
        return r["heldout_pacc"], r["heldout_pacc_surface"], r["heldout_pacc_behind"]

    # drawn to the ground truth's convention: wrong on the surface point (x = 0.9, the floor
    # cell), right half a cell behind it (x = 1.15)
    assert score(centre_x > 0.9) == (100.0, 0.0, 100.0)
    # the wall in the face's own cell only (as from the points alone): the other way round
    assert score((centre_x > 0.5) & (centre_x < 1.0)) == (100.0, 100.0, 0.0)
    # from the face's cell on: right both ways
    assert score(centre_x > 0.5) == (100.0, 100.0, 100.0)
    # one cell late, or one cell early and thin: wrong both ways
    assert score(centre_x > 1.5) == (0.0, 0.0, 0.0)
    assert score((centre_x > 0.0) & (centre_x < 0.5)) == (0.0, 0.0, 0.0)


def test_heldout_views_rule():
    # index % k == k // 2: k = 8 holds out 4, 12; k = 2 the odd views; 0 none; 1 view never
    assert heldout_views(16, 8) == [4, 12]
    assert heldout_views(5, 2) == [1, 3]
    assert heldout_views(16, 0) == [] and heldout_views(1, 2) == []


def _project(tmp: Path, frames: Path, **kw) -> ProjectOutputs:
    out = tmp / "proj"
    out.mkdir(parents=True)
    cfg = ProjectConfig(stride=1, cell=0.5, pad=0.0, bounds_pct=0.0, occlusion="none", **kw)
    return PROJECT["pinhole"](cfg, ProjectInputs(frames), out)


def test_project_keeps_heldout_views_out_of_the_points(tmp_path):
    frames = _capture(tmp_path, [FLOOR_VIEW] * 5)
    outs = _project(tmp_path, frames, holdout_every=2)
    _, _, view, _ = read_points(outs.points)
    # views 1 and 3 held out: 48 points from each of views 0, 2, 4
    np.testing.assert_array_equal(np.unique(view), [0, 2, 4])
    assert len(view) == 3 * 48
    assert json.loads(outs.heldout.read_text()) == {
        "every": 2,
        "views": [1, 3],
        "stems": ["1", "3"],
    }


def test_project_holds_nothing_out_without_labels_or_when_off(tmp_path):
    frames = _capture(tmp_path, [FLOOR_VIEW] * 5)
    outs = _project(tmp_path, frames, holdout_every=0)
    assert len(read_points(outs.points)[2]) == 5 * 48
    assert json.loads(outs.heldout.read_text())["views"] == []
    with pytest.raises(BlunfError, match="holdout_every"):
        _project(tmp_path / "b", frames, holdout_every=1)
    # height labelling has no labels to score: no view is held out
    outs = _project(tmp_path / "c", frames, holdout_every=2, labelling="height")
    assert json.loads(outs.heldout.read_text())["views"] == []


def test_evaluate_scores_heldout_views_without_ground_truth(tmp_path):
    # views 0 and 2 floor, view 1 (held out) half object (west): the plan from views 0 and 2
    # is all floor where they see, so the held-out view scores its east half: 50
    half = FLOOR_VIEW.copy()
    half[:, :4] = 3
    frames = _capture(tmp_path, [FLOOR_VIEW, half, FLOOR_VIEW])
    proj = _project(tmp_path, frames, holdout_every=2)
    xyz, lab, _, classes = read_points(proj.points)
    grid = Grid.covering(xyz[:, :2].min(0), xyz[:, :2].max(0), 0.5, pad=0.5)
    labels = np.full(grid.shape, 255, np.uint8)
    r, c, _ = grid.cell_of(xyz[:, :2])
    labels[r, c] = lab  # every seen cell floor (0)
    plan = tmp_path / "plan.npz"
    Blueprint(labels, grid, classes).save(plan)
    out = tmp_path / "eval"
    out.mkdir()
    inputs = EvaluateInputs(frames, None, (plan,), ("mvr",), False, heldout=proj.heldout)
    m = json.loads(
        EVALUATE["gt"](EvaluateConfig(heldout_stride=1), inputs, out).metrics.read_text()
    )
    assert m == {
        "blueprint": {
            "mvr": {
                "heldout_pacc": 50.0,
                "heldout_pacc_surface": 50.0,
                "heldout_pacc_behind": 50.0,
                "heldout_pixels": 48,
                "heldout_views": 1,
            }
        }
    }
    # the score switched off: nothing to report
    out2 = tmp_path / "eval2"
    out2.mkdir()
    cfg = EvaluateConfig(heldout=False)
    assert json.loads(EVALUATE["gt"](cfg, inputs, out2).metrics.read_text()) == {}

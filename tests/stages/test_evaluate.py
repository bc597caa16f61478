"""The evaluate stage on plans built in another frame (estimated poses) and on given poses."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from stages.common.blueprint import Blueprint, Grid
from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.gt_frame import FRAME_ALIGNED, FRAME_GT, FRAME_UNALIGNED, plan_frame
from stages.common.plan_metrics import evaluate_plan
from stages.evaluate import IMPLS, EvaluateConfig, EvaluateInputs

CLASSES = {0: "floor", 1: "wall", 3: "table", 4: "chair"}
CELL = 0.05
GRID = Grid((1.0, -2.0), CELL, (40, 60))  # 3 m x 2 m


def _plan(shift: int = 0) -> np.ndarray:
    """A room: walls on the border, a table, a chair; `shift` moves the furniture east."""
    lab = np.zeros(GRID.shape, np.uint8)
    lab[:2], lab[-2:], lab[:, :2], lab[:, -2:] = 1, 1, 1, 1
    lab[10:22, 15 + shift : 35 + shift] = 3
    lab[25:31, 40 + shift : 46 + shift] = 4
    return lab


def _similarity(yaw: float, scale: float, t: tuple[float, float, float]) -> np.ndarray:
    """4x4 x -> scale R_z(yaw) x + t."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = scale * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    m[:3, 3] = t
    return m


def _moved(pred: Blueprint, pred_to_gt: np.ndarray, fine: int = 3) -> Blueprint:
    """`pred` redrawn in the frame that pred_to_gt maps to its own, on cells `fine` x smaller.

    Each cell of the new raster takes the label of `pred` under its centre mapped by
    pred_to_gt. The new cells measure CELL / fine in the GT's units, so the centre nearest to
    any mapped GT centre is within half a new diagonal, CELL / fine / sqrt(2) = 0.24 CELL for
    fine = 3, of it: inside the same GT cell. Reading the moved plan back through pred_to_gt
    is then exact, whatever the rotation.
    """
    scale = float(np.cbrt(np.linalg.det(pred_to_gt[:3, :3])))
    corners = GRID.origin + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * (
        np.array(GRID.shape[::-1]) * CELL
    )  # [4, 2] GT plan corners
    back = np.linalg.solve(
        pred_to_gt[:3, :3], (np.c_[corners, np.zeros(4)] - pred_to_gt[:3, 3]).T
    ).T[:, :2]
    grid = Grid.covering(back.min(0), back.max(0), CELL / fine / scale, pad=CELL / scale)
    q = grid.centers().reshape(-1, 2)  # [M, 2] in the moved frame
    q3 = np.c_[q, np.zeros(len(q))] @ pred_to_gt[:3, :3].T + pred_to_gt[:3, 3]  # [M, 3]
    return Blueprint(pred.sample(q3[:, :2]).reshape(grid.shape), grid, pred.classes)


GT = Blueprint(_plan(), GRID, CLASSES)
PRED = Blueprint(_plan(shift=3), GRID, CLASSES)  # furniture 3 cells east of the truth


@pytest.mark.parametrize(
    "pred_to_gt",
    [
        _similarity(math.pi / 2, 2.0, (1.0, 3.0, 0.0)),
        _similarity(0.61, 0.8, (-2.5, 4.0, 0.0)),
        _similarity(-2.2, 1.07, (0.3, -0.2, 0.0)),
    ],
)
def test_moved_prediction_scores_as_the_unmoved_one(pred_to_gt):
    want = evaluate_plan(PRED, GT)
    assert 60 < want["fwiou"] < 100  # the shift makes it imperfect, so agreement is not trivial
    moved = _moved(PRED, pred_to_gt)
    got = evaluate_plan(moved, GT, pred_to_gt)
    for k in ("pacc", "fwiou", "miou", "completeness"):
        assert got[k] == pytest.approx(want[k], abs=1e-9), k
    # read cell by cell in the wrong frame, the same plan is nowhere near
    assert evaluate_plan(moved, GT)["fwiou"] < want["fwiou"] - 30


def test_identity_transform_changes_nothing():
    want = evaluate_plan(PRED, GT)
    got = evaluate_plan(PRED, GT, np.eye(4))
    assert got == want


def test_a_singular_transform_is_refused():
    with pytest.raises(BlunfError, match="invertible 4x4 similarity"):
        evaluate_plan(PRED, GT, np.zeros((4, 4)))


def _poses(n: int = 6) -> dict[str, np.ndarray]:
    """Camera-to-world poses on a circle of 1 m at heights 1.2 .. 1.7 m (not coplanar)."""
    out = {}
    for i in range(n):
        a = 2 * math.pi * i / n
        p = np.eye(4)
        p[:3, 3] = [2.5 + math.cos(a), -1.0 + math.sin(a), 1.2 + 0.1 * i]
        out[f"f{i}"] = p
    return out


def test_plan_frame_recovers_the_similarity_from_camera_centres():
    s = _similarity(0.61, 0.8, (-2.5, 4.0, 0.0))
    gt = _poses()
    inv = np.linalg.inv(s)
    est = {k: inv @ v for k, v in gt.items()}  # the reconstruction's frame
    del est["f5"]  # an unregistered frame is simply not used
    m, frame = plan_frame(True, est, gt, GRID)
    assert frame == FRAME_ALIGNED
    np.testing.assert_allclose(m, s, atol=1e-9)
    # two shared cameras cannot fix a similarity: compared as they are, and said so
    two = {k: est[k] for k in ("f0", "f1")}
    assert plan_frame(True, two, gt, GRID) == (None, FRAME_UNALIGNED)
    assert plan_frame(False, two, gt, GRID) == (None, FRAME_GT)
    assert plan_frame(False, est, {}, GRID) == (None, FRAME_GT)  # no GT poses


def test_given_poses_moved_by_the_align_stage_are_aligned_too():
    gt = _poses()
    # a Manhattan-like yaw of 20 degrees about the origin: the plans are not in the GT frame
    yaw = _similarity(math.radians(20), 1.0, (0.0, 0.0, 0.0))
    m, frame = plan_frame(False, {k: np.linalg.inv(yaw) @ v for k, v in gt.items()}, gt, GRID)
    assert frame == FRAME_ALIGNED
    np.testing.assert_allclose(m, yaw, atol=1e-9)
    # a yaw of 1e-5 rad moves the GT plan's farthest corner (|(4, -2)| = 4.5 m from the
    # origin) by 4.5e-5 m, far under a tenth of a 5 cm cell: that is the GT frame itself
    tiny = _similarity(1e-5, 1.0, (0.0, 0.0, 0.0))
    est = {k: np.linalg.inv(tiny) @ v for k, v in gt.items()}
    assert plan_frame(False, est, gt, GRID) == (None, FRAME_GT)


def _inputs(tmp: Path, est: dict[str, np.ndarray], pred: Blueprint, estimated: bool):
    (tmp / "gt").mkdir()
    GT.save(tmp / "gt" / "blueprint.npz")
    gt_poses = {k: v.tolist() for k, v in _poses().items()}
    (tmp / "gt" / "poses.json").write_text(json.dumps(gt_poses))
    intr = Intrinsics(10.0, 10.0, 4.0, 3.0, 8, 6)
    frames = tuple(Frame(k, tmp / f"{k}.png", intr, None, None, v) for k, v in est.items())
    Capture(tmp, frames).save(tmp / "frames.json")
    pred.save(tmp / "pred.npz")
    out = tmp / "out"
    out.mkdir()
    inputs = EvaluateInputs(
        tmp / "frames.json", tmp / "gt", (tmp / "pred.npz",), ("blunf",), estimated
    )
    return inputs, out


def test_stage_aligns_plans_built_from_estimated_poses(tmp_path):
    s = _similarity(-2.2, 1.07, (0.3, -0.2, 0.0))
    inv = np.linalg.inv(s)
    est = {k: inv @ v for k, v in _poses().items()}
    inputs, out = _inputs(tmp_path, est, _moved(PRED, s), estimated=True)
    metrics = json.loads(IMPLS["gt"](EvaluateConfig(), inputs, out).metrics.read_text())
    bp = metrics["blueprint"]["blunf"]
    assert bp["frame"] == FRAME_ALIGNED
    assert bp["fwiou"] == pytest.approx(evaluate_plan(PRED, GT)["fwiou"], abs=1e-9)
    assert metrics["poses"]["ate_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert metrics["poses"]["align_scale"] == pytest.approx(1.07)
    assert metrics["alignment"]["poses"] == len(est)  # the frame's conditioning, reported
    assert metrics["alignment"]["conditioning"] > 0.3


def test_stage_with_given_poses_compares_in_the_gt_frame(tmp_path):
    inputs, out = _inputs(tmp_path, _poses(), PRED, estimated=False)
    metrics = json.loads(IMPLS["gt"](EvaluateConfig(), inputs, out).metrics.read_text())
    assert metrics["blueprint"]["blunf"]["frame"] == FRAME_GT
    assert metrics["blueprint"]["blunf"]["fwiou"] == evaluate_plan(PRED, GT)["fwiou"]
    assert "poses" not in metrics  # given poses are not scored


def test_stage_aligns_given_poses_the_align_stage_turned(tmp_path):
    yaw = _similarity(math.radians(20), 1.0, (0.0, 0.0, 0.0))
    inv = np.linalg.inv(yaw)
    est = {k: inv @ v for k, v in _poses().items()}
    inputs, out = _inputs(tmp_path, est, _moved(PRED, yaw), estimated=False)
    metrics = json.loads(IMPLS["gt"](EvaluateConfig(), inputs, out).metrics.read_text())
    bp = metrics["blueprint"]["blunf"]
    assert bp["frame"] == FRAME_ALIGNED
    assert bp["fwiou"] == pytest.approx(evaluate_plan(PRED, GT)["fwiou"], abs=1e-9)
    assert "poses" not in metrics

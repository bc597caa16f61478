"""MVR on points whose per-cell majority is known."""

from __future__ import annotations

import json

import numpy as np

from stages.blueprint import IMPLS, BlueprintConfig, BlueprintInputs, MvrConfig
from stages.blueprint.mvr import majority_vote
from stages.common.blueprint import Blueprint, Grid

# 2 rows x 3 columns of 1 m cells, origin (0, 0): row 0 holds y in [1, 2) (north), row 1 y in
# [0, 1). Points at cell centres (+ small offsets) with these labels:
GRID = Grid((0.0, 0.0), 1.0, (2, 3))
VOTES = {
    (0, 0): [1, 1, 2],  # majority 1
    (0, 1): [2, 2, 1, 3],  # majority 2
    (0, 2): [4, 3],  # tie: lowest id, 3
    (1, 1): [5],  # one vote: 5 (unknown with min_votes = 2)
    (1, 2): [0, 0, 0, 7, 7],  # majority 0
}  # (1, 0) has no point: unknown


def _points():
    xy, lab = [], []
    for (r, c), labels in VOTES.items():
        for i, k in enumerate(labels):
            xy.append((c + 0.1 + 0.15 * i, 2 - r - 0.5 + 0.05 * i))  # inside cell (r, c)
            lab.append(k)
    xy += [(-0.5, 0.5), (1.5, 2.5)]  # outside the grid: not counted
    lab += [9, 9]
    return np.array(xy), np.array(lab, np.uint8)


def test_majority_per_cell():
    xy, lab = _points()
    plan, voted = majority_vote(xy, lab, GRID)
    np.testing.assert_array_equal(plan, [[1, 2, 3], [255, 5, 0]])
    assert voted == 5


def test_min_votes_leaves_thin_cells_unknown():
    xy, lab = _points()
    plan, _ = majority_vote(xy, lab, GRID, min_votes=2)
    np.testing.assert_array_equal(plan, [[1, 2, 3], [255, 255, 0]])


def test_stage_writes_blueprint_and_stats(tmp_path):
    xy, lab = _points()
    xyz = np.concatenate([xy, np.zeros((len(xy), 1))], 1).astype(np.float32)
    classes = {k: f"c{k}" for k in range(10)}
    np.savez(
        tmp_path / "points.npz",
        xyz=xyz,
        label=lab,
        view=np.zeros(len(lab), np.int32),
        classes=json.dumps({str(k): v for k, v in classes.items()}),
    )
    (tmp_path / "grid.json").write_text(json.dumps(GRID.to_json()))
    out = tmp_path / "out"
    out.mkdir()
    cfg = BlueprintConfig(impl="mvr", mvr=MvrConfig(min_votes=1))
    outs = IMPLS["mvr"](cfg, BlueprintInputs(tmp_path / "points.npz", tmp_path / "grid.json"), out)
    bp = Blueprint.load(outs.blueprint)
    np.testing.assert_array_equal(bp.labels, [[1, 2, 3], [255, 5, 0]])
    assert bp.grid == GRID and bp.classes == classes
    stats = json.loads(outs.stats.read_text())
    assert outs.stats.name == "mvr.json" and stats["cells_voted"] == 5
    assert stats["completeness"] == round(100 * 5 / 6, 3)

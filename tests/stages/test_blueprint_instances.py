"""The plan's instance layer (stages.blueprint.instances): nearest-instance propagation worked
out by hand and checked against a brute-force reference, the layer saved with the plan, and
every blueprint method writing it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.blueprint import IMPLS, BlueprintConfig, BlueprintInputs, BlunfConfig
from stages.blueprint.instances import cell_majority, instance_raster
from stages.common.blueprint import Blueprint, Grid
from stages.common.components import components

U, FLOOR, OBJ = 255, 0, 3
# 2 rows x 6 columns of 1 m cells from (0, 0): row 0 holds y in [1, 2), row 1 y in [0, 1).
GRID = Grid((0.0, 0.0), 1.0, (2, 6))
LABELS = np.array([[OBJ, OBJ, OBJ, OBJ, OBJ, FLOOR], [OBJ, OBJ, U, OBJ, OBJ, FLOOR]], np.uint8)


def _at(r: int, c: int, n: int = 1) -> list[tuple[float, float]]:
    """n world points inside cell (row r, col c) of GRID."""
    return [(c + 0.2 + 0.1 * i, 2 - r - 0.7 + 0.1 * i) for i in range(n)]


def test_nearest_instance_worked_by_hand():
    # object points: cell (0,0) holds instance 1 twice and 2 once (majority 1), cell (1,4)
    # instance 2; an object point without instance at (0,2) and floor points do not count, nor
    # does a point outside the grid.
    pts = [
        (_at(0, 0, 2), OBJ, 1),
        (_at(0, 0, 1), OBJ, 2),
        (_at(1, 4), OBJ, 2),
        (_at(0, 2), OBJ, 0),
        (_at(0, 5) + _at(1, 5), FLOOR, 0),
        ([(-0.5, 0.5)], OBJ, 9),
    ]
    xy = np.array([p for ps, _, _ in pts for p in ps])
    lab = np.array([k for ps, k, _ in pts for _ in ps])
    inst = np.array([i for ps, _, i in pts for _ in ps])
    got = instance_raster(LABELS, GRID, xy, lab, inst)
    # Object cells take the nearer seed, (0,0) -> 1 or (1,4) -> 2, by cell-centre distance:
    # (0,1) 1 vs sqrt(10); (0,2) 2 vs sqrt(5) = 2.24: 1; (0,3) 3 vs sqrt(2): 2; (0,4) 2;
    # (1,0) 1 vs 4: 1; (1,1) sqrt(2) vs 3: 1; (1,3) 1: 2. Floor and unknown cells: 0.
    np.testing.assert_array_equal(got, [[1, 1, 1, 2, 2, 0], [1, 1, 0, 2, 2, 0]])
    assert got is not None and got.dtype == np.int32


def test_no_instance_no_layer():
    xy = np.array(_at(0, 0) + _at(1, 5))
    assert instance_raster(LABELS, GRID, xy, np.array([OBJ, FLOOR]), np.zeros(2, int)) is None


def test_cell_majority_ties_go_to_the_lowest_value():
    cells, win = cell_majority(np.array([5, 5, 5, 5, 2, 9, 9]), np.array([7, 3, 7, 3, 4, 1, 8]))
    np.testing.assert_array_equal(cells, [2, 5, 9])
    np.testing.assert_array_equal(win, [4, 3, 1])


def test_matches_a_brute_force_nearest_seed():
    """Random plans of two classes with instances: every cell of a class takes an instance
    seeded by a cell of that class at the smallest distance (any one of them on a tie)."""
    rng = np.random.default_rng(0)
    grid = Grid((0.0, 0.0), 0.5, (23, 31))
    for _ in range(5):
        labels = rng.choice(np.array([0, 1, 2, U], np.uint8), grid.shape)
        n = 60
        xy = rng.uniform(0, 1, (n, 2)) * [31 * 0.5, 23 * 0.5]
        lab = rng.choice([1, 2], n)
        inst = np.where(lab == 1, rng.integers(1, 4, n), rng.integers(10, 13, n))
        inst[rng.random(n) < 0.2] = 0  # some points carry no instance
        got = instance_raster(labels, grid, xy, lab, inst)
        assert got is not None
        row, col, _ = grid.cell_of(xy)
        rr, cc = np.mgrid[0 : grid.shape[0], 0 : grid.shape[1]]
        for k in (1, 2):
            m = (lab == k) & (inst > 0)
            seeds = {}  # seeded cell (row, col) -> the majority instance of its points
            for r, c in set(zip(row[m].tolist(), col[m].tolist(), strict=True)):
                vals, counts = np.unique(inst[m & (row == r) & (col == c)], return_counts=True)
                seeds[(r, c)] = int(vals[counts.argmax()])  # first maximum: the lowest value
            pos = np.array(list(seeds))  # [S, 2]
            val = np.array(list(seeds.values()))  # [S]
            d2 = (rr[..., None] - pos[:, 0]) ** 2 + (cc[..., None] - pos[:, 1]) ** 2  # [H, W, S]
            for r, c in np.argwhere(labels == k).tolist():
                allowed = set(val[d2[r, c] == d2[r, c].min()].tolist())
                assert got[r, c] in allowed, (k, r, c, got[r, c], allowed)
        assert (got[labels == 0] == 0).all() and (got[labels == U] == 0).all()
        assert set(np.unique(got[labels == 1])) <= {1, 2, 3}
        assert set(np.unique(got[labels == 2])) <= {10, 11, 12}


def test_layer_saved_with_the_plan_and_old_plans_load(tmp_path):
    inst = np.arange(12, dtype=np.int32).reshape(2, 6)
    Blueprint(LABELS, GRID, {0: "floor", 3: "object"}, inst).save(tmp_path / "a.npz")
    back = Blueprint.load(tmp_path / "a.npz")
    assert back.instances is not None
    np.testing.assert_array_equal(back.instances, inst)
    Blueprint(LABELS, GRID, {0: "floor"}).save(tmp_path / "b.npz")  # no layer: as before
    assert "instances" not in np.load(tmp_path / "b.npz").files
    assert Blueprint.load(tmp_path / "b.npz").instances is None


# Two tables (class 3) that touch, on a 2 x 1 m floor of 1/16 m cells: table 1 spans x in
# [0.25, 1.0), table 2 x in [1.0, 1.75), both y in [0.25, 0.75). Their points carry their
# instance; floor points none.
TGRID = Grid((0.0, 0.0), 1 / 16, (16, 32))


def _tables(tmp: Path) -> BlueprintInputs:
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 1, (6000, 2)) * [2.0, 1.0]
    on = (xy[:, 0] >= 0.25) & (xy[:, 0] < 1.75) & (xy[:, 1] >= 0.25) & (xy[:, 1] < 0.75)
    lab = np.where(on, 3, 0).astype(np.uint8)
    inst = np.where(on, np.where(xy[:, 0] < 1.0, 1, 2), 0).astype(np.int32)
    np.savez(
        tmp / "points.npz",
        xyz=np.concatenate([xy, np.zeros((len(xy), 1))], 1).astype(np.float32),
        label=lab,
        view=np.zeros(len(lab), np.int32),
        instance=inst,
        classes=json.dumps({"0": "floor", "3": "table"}),
    )
    (tmp / "grid.json").write_text(json.dumps(TGRID.to_json()))
    return BlueprintInputs(tmp / "points.npz", tmp / "grid.json")


@pytest.mark.parametrize("impl", ["blunf", "mvr"])
def test_methods_keep_two_touching_tables_apart(tmp_path, impl):
    ins = _tables(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    n = torch.get_num_threads()
    try:
        cfg = BlueprintConfig(impl=impl, blunf=BlunfConfig(steps=150, batch=2048, threads=1))
        bp = Blueprint.load(IMPLS[impl](cfg, ins, out).blueprint)
    finally:
        torch.set_num_threads(n)
    assert bp.instances is not None
    x = bp.grid.centers()[..., 0]
    table = bp.labels == 3
    assert table.sum() > 180  # of the 24 x 8 table cells
    # the tables are one region of their class: one component without the instance layer,
    # two with it
    flat = Blueprint(bp.labels, bp.grid, bp.classes)
    assert [c["class"] for c in components(flat, min_area_m2=0.05)].count("table") == 1
    comps = [c for c in components(bp, min_area_m2=0.05) if c["class"] == "table"]
    assert sorted(c["instance"] for c in comps) == [1, 2]
    right = (bp.instances == np.where(x < 1.0, 1, 2)) | ~table
    assert right[table].mean() > 0.97
    assert (bp.instances[~table] == 0).all()

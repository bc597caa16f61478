"""BluNF on a tiny synthetic plan: two rectangles of different classes on a floor."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from stages.blueprint import IMPLS, BlueprintConfig, BlueprintInputs, BlunfConfig, paper_recipe
from stages.blueprint.blunf import _sampler, auto_freqs, field_labels, shrink_objects
from stages.common.blueprint import Blueprint, Grid
from stages.common.encoding import HashGrid2D
from stages.common.errors import BlunfError
from stages.common.plan_metrics import plan_metrics
from stages.common.threads import torch_threads

# A 2 x 2 m floor (class 0) with a rug (class 1) and a table (class 3: ids need not be
# contiguous), on 32 x 32 cells of 1/16 m. Every coordinate is a multiple of 2^-9 m so that
# offsetting by 1e4 m or scaling by 1e3 is exact in float32 and the normalised coordinates are
# bit-identical: the plans must then be identical too.
GRID = Grid((0.0, 0.0), 1 / 16, (32, 32))
CLASSES = {0: "floor", 1: "rug", 3: "table"}
RECTS = [(1, (0.375, 0.375, 1.0, 0.875)), (3, (1.25, 1.125, 1.75, 1.625))]
FAST: dict[str, Any] = dict(steps=150, batch=2048, threads=1)
SETTINGS: dict[
    str, dict[str, Any]
] = {  # small step counts per encoding (SIREN wants a smaller learning rate)
    "none": dict(FAST, steps=300),
    "pe": dict(FAST, n_freqs=8),
    "hash": dict(FAST, encoding="hash"),
    "siren": dict(FAST, steps=300, lr=1e-3),
}


def _labels(xy: np.ndarray) -> np.ndarray:
    lab = np.zeros(len(xy), np.uint8)
    for k, (x0, y0, x1, y1) in RECTS:
        lab[(xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)] = k
    return lab


def _points(n: int = 16000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points over the floor with 1 cm noise and 3 % of labels drawn at random."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 2, (n, 2))
    lab = _labels(xy)
    xy = np.clip(xy + rng.normal(0, 0.01, xy.shape), 0, 2 - 2**-9)
    bad = rng.random(n) < 0.03
    lab[bad] = rng.choice([0, 1, 3], int(bad.sum()))
    xy = np.round(xy * 512) / 512
    return np.concatenate([xy, np.zeros((n, 1))], 1), lab


def _gt() -> np.ndarray:
    return _labels(GRID.centers().reshape(-1, 2)).reshape(GRID.shape)


def _run(
    tmp: Path,
    cfg: BlunfConfig,
    xyz=None,
    grid: Grid = GRID,
    name: str = "out",
    bounds=None,
    lab=None,
    classes=CLASSES,
):
    xyz0, lab0 = _points()
    xyz = xyz0 if xyz is None else xyz
    lab = lab0 if lab is None else lab
    d = tmp / name
    d.mkdir()
    np.savez(
        d / "points.npz",
        xyz=xyz.astype(np.float32),
        label=lab,
        view=np.zeros(len(lab), np.int32),
        classes=json.dumps({str(k): v for k, v in classes.items()}),
    )
    extra = {} if bounds is None else {"bounds": list(bounds)}
    (d / "grid.json").write_text(json.dumps({**grid.to_json(), **extra}))
    out = d / "run"
    out.mkdir()
    outs = IMPLS["blunf"](
        BlueprintConfig(impl="blunf", blunf=cfg),
        BlueprintInputs(d / "points.npz", d / "grid.json"),
        out,
    )
    return Blueprint.load(outs.blueprint), outs


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.mark.parametrize("encoding", ["none", "pe", "hash", "siren"])
def test_every_encoding_recovers_the_plan(tmp_path, encoding):
    cfg = BlunfConfig(**{"encoding": encoding, **SETTINGS[encoding]})
    bp, outs = _run(tmp_path, cfg)
    m = plan_metrics(bp.labels, _gt(), CLASSES)
    assert m["completeness"] == 100.0
    assert m["fwiou"] >= 95.0, m
    assert bp.classes == CLASSES and bp.grid == GRID
    stats = json.loads(outs.stats.read_text())
    assert stats["steps"] == cfg.steps and stats["train_accuracy"] > 90.0
    assert (outs.blueprint.parent / "model.pt").exists()


def test_same_seed_same_plan_other_seed_other_field(tmp_path):
    cfg = BlunfConfig(**SETTINGS["pe"])
    a, ao = _run(tmp_path, cfg, name="a")
    b, bo = _run(tmp_path, cfg, name="b")
    c, co = _run(tmp_path, replace(cfg, seed=1), name="c")
    np.testing.assert_array_equal(a.labels, b.labels)
    loss = [json.loads(o.stats.read_text())["final_loss"] for o in (ao, bo, co)]
    assert loss[0] == loss[1] and loss[0] != loss[2]


def test_field_does_not_depend_on_the_callers_thread_count(tmp_path):
    # The runner gives the stage the free cores' count; the field trains with
    # blueprint.blunf.threads (1) whatever that is. With threads=0 (the caller's count) 2
    # threads and 1 train other weights: with 5 classes torch's CPU matrix product splits the
    # last layer's weight gradient (5 x 64, summed over the batch) between threads (3 or 8
    # classes it does not split).
    xyz, lab = _points()
    lab = np.where(xyz[:, 0] > 1.5, 4, np.where(xyz[:, 1] > 1.5, 5, lab)).astype(np.uint8)
    classes = {**CLASSES, 4: "chair", 5: "sofa"}

    def weights(caller: int, threads: int) -> dict:
        cfg = BlunfConfig(**dict(SETTINGS["pe"], steps=10, threads=threads))
        with torch_threads(caller):
            name = f"t{caller}-{threads}"
            _, outs = _run(tmp_path, cfg, xyz, name=name, lab=lab, classes=classes)
        return torch.load(outs.blueprint.parent / "model.pt", weights_only=True)["state_dict"]

    one, two = weights(1, 1), weights(2, 1)
    assert all(torch.equal(one[k], two[k]) for k in one)
    free1, free2 = weights(1, 0), weights(2, 0)
    assert any(not torch.equal(free1[k], free2[k]) for k in free1), "2 threads split nothing"


@pytest.mark.parametrize(
    "offset, scale, exact", [(1e4, 1.0, True), (0.0, 1e3, True), (0.0, 1e-3, False)]
)
def test_plan_does_not_depend_on_units_or_offset(tmp_path, offset, scale, exact):
    cfg = BlunfConfig(**SETTINGS["pe"])
    base, _ = _run(tmp_path, cfg, name="base")
    xyz, _ = _points()
    moved = Grid(
        (GRID.origin[0] * scale + offset, GRID.origin[1] * scale + offset),
        GRID.cell * scale,
        GRID.shape,
    )
    other, _ = _run(tmp_path, cfg, xyz * scale + np.array([offset, offset, 0]), moved, "moved")
    if exact:  # the normalised coordinates are bit-identical (see the header)
        np.testing.assert_array_equal(other.labels, base.labels)
    else:  # scaling by 1e-3 rounds in float32: a few border cells may flip
        assert (other.labels == base.labels).mean() >= 0.99


def test_saved_field_predicts_the_plan(tmp_path):
    bp, outs = _run(tmp_path, BlunfConfig(**SETTINGS["pe"]))
    xy = GRID.centers().reshape(-1, 2)
    np.testing.assert_array_equal(
        field_labels(outs.blueprint.parent / "model.pt", xy), bp.labels.reshape(-1)
    )


def test_hash_grid_matches_a_per_level_reference():
    enc = HashGrid2D(levels=4, features=2, log2_size=6, base_res=2, max_res=16)
    with torch.no_grad():
        enc.table.normal_()
    u = torch.rand(50, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    # reference: one level at a time, one corner at a time. Resolutions 2, 4, 8, 16 (growth 2):
    # (res + 1)^2 = 9 and 25 fit the 64-entry table (dense), 81 and 289 do not (hashed)
    assert enc.res == [2, 4, 8, 16]
    ref, offset = [], 0
    for r in enc.res:
        size = min(64, (r + 1) ** 2)
        pos = (u + 1) / 2 * r
        i0 = torch.minimum(pos.floor(), torch.tensor(r - 1.0)).long()
        f = pos - i0
        acc = torch.zeros(50, 2)
        for dx in (0, 1):
            for dy in (0, 1):
                x, y = i0[:, 0] + dx, i0[:, 1] + dy
                idx = x + y * (r + 1) if (r + 1) ** 2 <= 64 else (x ^ (y * 2654435761)) % 64
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1])
                acc += w[:, None] * enc.table[offset + idx]
        ref.append(acc)
        offset += size
    torch.testing.assert_close(enc(u), torch.cat(ref, 1))


def test_auto_frequencies_stop_near_the_cell_size():
    # finest period = cells_across / 2^(n-1) cells, about 2.5: 320 cells -> 2^7 = 128 (period
    # 2.5 cells) -> n = 8; 32 cells -> 2^3 = 8 (period 4; 2^4 would give 2 < 2.5) -> n = 4
    assert auto_freqs(320) == 8 and auto_freqs(32) == 4 and auto_freqs(1) == 1


def test_paper_recipe_is_the_papers():
    p = paper_recipe()
    assert (p.encoding, p.n_freqs, p.width, p.lr, p.batch) == ("pe", 12, 64, 5e-3, 50_000)


def test_cells_beyond_the_bounds_read_the_field_at_the_edge(tmp_path):
    # Bounds end at x = 1.5, inside the table (x 1.25 .. 1.75, y 1.125 .. 1.625). Columns 24..31
    # (centres x = 1.53 .. 1.97) lie beyond: clamped to x = 1.5, each row repeats one label,
    # and the table rows carry the table to the east edge of the grid, where the points say
    # floor (x > 1.75) and the unclamped field does too.
    cfg = BlunfConfig(**SETTINGS["pe"])
    bp, outs = _run(tmp_path, cfg, bounds=(0.0, 0.0, 1.5, 2.0))
    beyond = bp.labels[:, 24:]
    assert (beyond == beyond[:, :1]).all()
    # row r has its centre at y = (31.5 - r) / 16: the table holds rows 6..13; rows 7..12
    # (y = 1.53 .. 1.22) are well inside it
    rows = slice(7, 13)
    assert (bp.labels[rows, 31] == 3).all()
    # the saved field clamps the same way
    far = np.array([[5.0, 1.4], [1.5, 1.4]])
    assert field_labels(outs.blueprint.parent / "model.pt", far).tolist() == [3, 3]
    free, _ = _run(tmp_path, replace(cfg, outside="field"), bounds=(0.0, 0.0, 1.5, 2.0), name="f")
    assert (free.labels[rows, 31] == 0).mean() > 0.5


def test_cell_balance_draws_every_occupied_cell_alike():
    # 1000 points in cell 7, 10 in cell 3, 1 in cell 99: each cell a third of the draws
    cell = torch.tensor([7] * 1000 + [3] * 10 + [99])
    y = torch.zeros(len(cell), dtype=torch.int64)
    c = BlunfConfig(balance="cell", batch=30_000)
    idx = _sampler(c, y, 1, torch.Generator().manual_seed(0), cell)()
    frac = torch.bincount(cell[idx], minlength=100)[[7, 3, 99]].double() / c.batch
    # binomial sd = sqrt(1/3 * 2/3 / 30000) = 0.0027: +-0.015 is over 5 sd
    torch.testing.assert_close(
        frac, torch.full((3,), 1 / 3, dtype=torch.float64), atol=0.015, rtol=0
    )
    # within a cell, its points come up alike: the 10 points of cell 3 all appear
    assert set(idx[cell[idx] == 3].tolist()) == set(range(1000, 1010))


def test_shrink_moves_object_edges_facing_the_floor_to_the_floor():
    """Floor 0, wall 1 along the left edge, a cabinet 3 against the wall, a table 5 on the
    floor with a chair 6 touching it. One cell of shrink: the object cells next to the floor
    (4-neighbours: a disk of radius 1) become floor; the cabinet keeps its side on the wall
    and the table and chair the side they share; the wall and floor do not change."""
    classes = {0: "floor", 1: "wall", 3: "cabinet", 5: "table", 6: "chair"}
    lab = np.zeros((10, 12), np.uint8)
    lab[:, 0] = 1
    lab[1:4, 1:4] = 3  # cabinet, columns 1-3, against the wall (column 0)
    lab[5:9, 4:8] = 5  # table, 4 x 4
    lab[5:9, 8:10] = 6  # chair, touching the table's right side
    out, n = shrink_objects(lab, classes, 1)
    want = np.zeros_like(lab)
    want[:, 0] = 1
    want[2, 1:3] = 3  # the cabinet's wall-side cells that no floor cell touches
    want[6:8, 5:8] = 5  # the table without its top, bottom and left rows
    want[6:8, 8] = 6  # the chair without its far column and the top / bottom rows
    assert out.tolist() == want.tolist()
    assert n == int((out != lab).sum()) and n > 0
    assert ((out == lab) | (out == 0)).all()  # objects only ever turn to floor
    same, none = shrink_objects(lab, classes, 0)
    assert none == 0 and (same == lab).all()
    no_floor = {0: "rug", 1: "wall", 3: "cabinet", 5: "table", 6: "chair"}
    kept, none = shrink_objects(lab, no_floor, 2)
    assert none == 0 and (kept == lab).all()


def test_shrink_in_the_stage_is_the_plan_shrunk(tmp_path):
    """The stage with shrink = one cell writes the plan it writes without, shrunk (same
    seed, same field), and says so in train.json; a negative shrink is refused."""
    cfg = BlunfConfig(**SETTINGS["pe"])
    plain, _ = _run(tmp_path, cfg, name="plain")
    shrunk, outs = _run(tmp_path, replace(cfg, shrink=GRID.cell), name="shrunk")
    want, n = shrink_objects(plain.labels, CLASSES, 1)
    assert n > 0 and (shrunk.labels == want).all()
    stats = json.loads(outs.stats.read_text())
    assert stats["shrink_cells"] == 1 and stats["shrunk_cells"] == n
    # the table is a 8 x 8-cell square on the floor: one cell off its 4 sides, 28 cells
    assert (plain.labels == 3).sum() - (shrunk.labels == 3).sum() >= 24
    with pytest.raises(BlunfError, match="blueprint.blunf.shrink"):
        _run(tmp_path, replace(cfg, shrink=-0.1), name="bad")

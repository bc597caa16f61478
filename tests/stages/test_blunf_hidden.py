"""blueprint.blunf.hidden_insides: the inside of a tall object, which no view saw into and no
ray crossed, becomes the object whose points close round it; a wall's inside, floor the rays
missed and space larger than furniture keep the field's labels."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stages.blueprint import BlueprintConfig, BlueprintInputs, BlunfConfig
from stages.blueprint.blunf import run
from stages.blueprint.hidden import MAX_AREA, fill_pockets
from stages.common.blueprint import Blueprint, Grid
from stages.common.points import write_grid, write_points

FLOOR, WALL, CABINET, CHAIR = 0, 1, 6, 4
CLASSES = {FLOOR: "floor", WALL: "wall", CHAIR: "chair", CABINET: "cabinet"}
CELL = 0.02
GRID = Grid((-0.1, -0.1), CELL, (100, 120))  # x in [-0.1, 2.3], y in [-0.1, 1.9]
# the room x in [0, 2], y in [0, 1.5]; its north wall 0.12 thick (faces y = 1.5 and 1.62);
# a cabinet x in [0.6, 1.4], y in [1.0, 1.44], 6 cm off the wall
ROOM = (0.0, 0.0, 2.0, 1.5)
BACK = 1.62
CAB = (0.6, 1.0, 1.4, 1.44)


def _box(xy: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    x0, y0, x1, y1 = box
    return (xy[..., 0] >= x0) & (xy[..., 0] <= x1) & (xy[..., 1] >= y0) & (xy[..., 1] <= y1)


def _inner(c: np.ndarray) -> np.ndarray:
    """The cells (centres c [H, W, 2]) of the cabinet's footprint a cell in from its faces."""
    return _box(c, (CAB[0] + CELL, CAB[1] + CELL, CAB[2] - CELL, CAB[3] - CELL))


def _scene(rng: np.random.Generator, front: int = CABINET) -> tuple[np.ndarray, np.ndarray]:
    """Points (xyz [N, 3], label [N]) as the views of a tall cabinet against the wall see it:
    the floor round it, the wall's face beside it (the cabinet hides it up to the wall's
    top), the cabinet's front and sides labelled `front`; nothing inside its footprint or in
    the gap behind it, so the gap meets the wall's inside."""
    n = 20000
    fl = np.c_[rng.uniform(0, 2, n), rng.uniform(0, 1.5, n), np.zeros(n)]
    fl = fl[~_box(fl[:, :2], (CAB[0] - 0.01, CAB[1] - 0.01, CAB[2] + 0.01, 1.5))]
    wall = np.c_[rng.uniform(0, 2, n), np.full(n, 1.5), rng.uniform(0, 2.5, n)]
    wall = wall[~_box(wall[:, :2], (CAB[0], 0, CAB[2], 2))]
    m = 3000
    fx = rng.uniform(CAB[0], CAB[2], m)
    sy = rng.uniform(CAB[1], CAB[3], m)
    cab = np.r_[
        np.c_[fx, np.full(m, CAB[1]), rng.uniform(0, 1.8, m)],  # the front
        np.c_[np.full(m, CAB[0]), sy, rng.uniform(0, 1.8, m)],  # the sides
        np.c_[np.full(m, CAB[2]), sy, rng.uniform(0, 1.8, m)],
    ]
    xyz = np.concatenate([fl, wall, cab])
    label = np.r_[np.full(len(fl), FLOOR), np.full(len(wall), WALL), np.full(len(cab), front)]
    return xyz, label.astype(np.uint8)


def _layers() -> tuple[np.ndarray, np.ndarray]:
    """(free, inside) bool [H, W]: the rays cross the room but not the cabinet's footprint
    or the gap behind it (they end on its front and sides; its top is above the cameras);
    the room's extent runs to the wall's back face."""
    c = GRID.centers()
    inside = _box(c, (ROOM[0] - CELL, ROOM[1] - CELL, ROOM[2] + CELL, BACK))
    free = _box(c, ROOM) & ~_box(c, (CAB[0] - CELL / 2, CAB[1] - CELL / 2, CAB[2] + CELL / 2, 1.5))
    return free, inside


def _field_guess() -> np.ndarray:
    """Labels as the field draws them: floor in the room, wall from the face to the back
    face, and across the cabinet's unseen inside stripes of floor and wall."""
    c = GRID.centers()
    labels = np.full(GRID.shape, FLOOR, np.uint8)
    labels[c[..., 1] >= 1.5 - CELL / 2] = WALL
    cab = _box(c, (CAB[0] + CELL, CAB[1] + CELL, CAB[2] - CELL, 1.5 - CELL))
    stripe = (np.arange(GRID.shape[0]) // 3 % 2 == 0)[:, None]
    labels[cab & stripe] = WALL
    front = _box(c, (CAB[0], CAB[1] - CELL / 2, CAB[2], CAB[1] + CELL / 2))
    labels[front] = CABINET
    return labels


def test_a_tall_cabinets_unseen_inside_becomes_the_cabinet() -> None:
    xyz, label = _scene(np.random.default_rng(0))
    free, inside = _layers()
    guess = _field_guess()
    out, changed = fill_pockets(guess, CLASSES, GRID, xyz[:, :2], label, free, inside)
    c = GRID.centers()
    cab = _inner(c)
    assert (guess[cab] != CABINET).mean() > 0.9  # the field's guess: floor and wall
    assert (out[cab] == CABINET).all()
    assert changed == int((out != guess).sum()) > 0
    # the wall between its faces (no point, no ray: a pocket too, but the plan's wall that
    # holds the face's points) stays wall, behind the cabinet as beside it
    wall = _box(c, (0.0, 1.5 + 1.5 * CELL, 2.0, BACK - CELL))
    assert (out[wall] == WALL).all()
    # the room's floor and what lies outside the room are the field's
    assert (
        out[~_box(c, (CAB[0] - CELL, CAB[1] - CELL, CAB[2] + CELL, 1.5))]
        == guess[~_box(c, (CAB[0] - CELL, CAB[1] - CELL, CAB[2] + CELL, 1.5))]
    ).all()


def test_a_pocket_rimmed_by_floor_keeps_the_field_labels() -> None:
    """Floor the rays happened to miss in a low chair's corner: half its rim is the chair's
    two sides, half floor; it is no object's inside."""
    rng = np.random.default_rng(1)
    xyz, label = _scene(rng, front=CABINET)
    free, inside = _layers()
    c = GRID.centers()
    hole = _box(c, (0.3, 0.3, 0.5, 0.5))  # no point, no ray
    free = free & ~hole
    keep = ~_box(xyz[:, :2], (0.3, 0.3, 0.5, 0.5))
    side = rng.uniform(0.3 - CELL, 0.5 + CELL, 200)
    chair = np.r_[
        np.c_[np.full(200, 0.5 + CELL / 2), side, rng.uniform(0, 0.8, 200)],
        np.c_[side, np.full(200, 0.5 + CELL / 2), rng.uniform(0, 0.8, 200)],
    ]
    xyz = np.concatenate([xyz[keep], chair])
    label = np.r_[label[keep], np.full(400, CHAIR, np.uint8)]
    guess = _field_guess()
    out, _ = fill_pockets(guess, CLASSES, GRID, xyz[:, :2], label, free, inside)
    assert (out[hole] == guess[hole]).all()
    assert (out[_inner(c)] == CABINET).all()  # the cabinet's inside, as before


def test_a_pocket_larger_than_furniture_keeps_the_field_labels() -> None:
    """A cabinet front 3 m wide with 1.5 m of unseen space behind it is no cabinet's inside
    (MAX_AREA); the same front with a cabinet's depth behind it is."""
    assert 3.0 * 1.5 > MAX_AREA > 0.8 * 0.44
    g = Grid((-0.1, -0.1), CELL, (110, 170))  # x in [-0.1, 3.3], y in [-0.1, 2.1]
    c = g.centers()
    rng = np.random.default_rng(2)
    front = np.c_[rng.uniform(0.1, 3.1, 8000), np.full(8000, 0.2)]
    sides = np.r_[
        np.c_[np.full(3000, 0.1), rng.uniform(0.2, 1.7, 3000)],
        np.c_[np.full(3000, 3.1), rng.uniform(0.2, 1.7, 3000)],
    ]
    back = np.c_[rng.uniform(0.1, 3.1, 8000), np.full(8000, 1.7)]
    xy = np.concatenate([front, sides, back])
    label = np.r_[np.full(14000, CABINET), np.full(8000, WALL)].astype(np.uint8)
    inside = np.ones(g.shape, bool)
    free = ~_box(c, (0.1, 0.2, 3.1, 1.7))
    guess = np.full(g.shape, FLOOR, np.uint8)
    out, changed = fill_pockets(guess, CLASSES, g, xy, label, free, inside)
    assert changed == 0 and (out == guess).all()
    free = ~_box(c, (0.1, 0.2, 3.1, 0.6))  # 0.4 m deep
    xy = np.concatenate([front, sides[sides[:, 1] < 0.6], back - [0, 1.1]])
    label = np.r_[np.full(len(xy) - 8000, CABINET), np.full(8000, WALL)].astype(np.uint8)
    out, changed = fill_pockets(guess, CLASSES, g, xy, label, free, inside)
    assert changed > 0 and (out[_box(c, (0.2, 0.3, 3.0, 0.5))] == CABINET).all()


def _inputs(tmp_path, xyz: np.ndarray, label: np.ndarray) -> BlueprintInputs:
    n = len(label)
    zeros = np.zeros(n, np.int32)
    write_points(
        tmp_path / "points.npz", xyz.astype(np.float32), np.zeros(3), label, zeros, zeros, CLASSES
    )
    write_grid(tmp_path / "grid.json", GRID, np.array([0.0, 0.0]), np.array([2.0, BACK]))
    free, inside = _layers()
    ones = np.ones(GRID.shape, np.uint8)
    np.savez(
        tmp_path / "observed.npz",
        near=ones,
        inside=inside.astype(np.uint8),
        labelled=ones,
        free=free.astype(np.uint8),
    )
    return BlueprintInputs(
        tmp_path / "points.npz", tmp_path / "grid.json", tmp_path / "observed.npz"
    )


@pytest.mark.parametrize("on", [True, False])
def test_the_stage_fills_the_inside_only_when_asked(tmp_path, on) -> None:
    xyz, label = _scene(np.random.default_rng(3))
    ins = _inputs(tmp_path, xyz, label)
    n = torch.get_num_threads()
    try:
        c = BlunfConfig(threads=1, seed=0, hidden_insides=on)
        out = run(BlueprintConfig(blunf=c), ins, tmp_path)
    finally:
        torch.set_num_threads(n)
    bp = Blueprint.load(out.blueprint)
    stats = json.loads(out.stats.read_text())
    cab = _inner(GRID.centers())
    if on:
        assert (bp.labels[cab] == CABINET).all() and stats["hidden_inside_cells"] > 0
    else:
        assert stats["hidden_inside_cells"] == 0

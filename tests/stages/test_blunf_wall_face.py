"""blueprint.blunf.wall_face: a plan cell is wall when its centre lies behind the face the
views saw, as the ground truth rasterises it (one ray down through each cell centre), not
whenever the cell holds points of the face."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stages.blueprint import BlueprintConfig, BlueprintInputs, BlunfConfig
from stages.blueprint.blunf import run
from stages.blueprint.faces import wall_fronts
from stages.common.blueprint import Blueprint, Grid

CLASSES = {0: "floor", 1: "wall"}
CELL = 0.02
# a room between two wall faces that cross cells off their centres: x = 0.087 (the room on
# its right: the cell [0.08, 0.10] centred 3 mm in front of it) and x = 0.413 (the room on
# its left: the cell [0.40, 0.42] centred 3 mm in front of it)
LEFT, RIGHT = 0.087, 0.413
GRID = Grid((-0.1, 0.0), CELL, (30, 33))  # x in [-0.1, 0.56], y in [0, 0.6]


def _room(tmp_path, rng: np.random.Generator) -> BlueprintInputs:
    """points.npz, grid.json and observed.npz of the room: each face seen in many views
    (many points at every height), the floor seen sparsely and not within 4 cm of a face (a
    top view hides it under the wall's points)."""
    n = 6000
    y = rng.uniform(0.0, 0.6, 2 * n)
    face_x = np.r_[np.full(n, LEFT), np.full(n, RIGHT)] + rng.normal(0, 0.001, 2 * n)
    wall = np.c_[face_x, y, rng.uniform(0.0, 2.0, 2 * n)]
    fx = rng.uniform(LEFT + 0.04, RIGHT - 0.04, 1500)
    floor = np.c_[fx, rng.uniform(0.0, 0.6, 1500), np.zeros(1500)]
    xyz = np.concatenate([wall, floor])
    label = np.r_[np.ones(2 * n), np.zeros(1500)].astype(np.uint8)
    np.savez(
        tmp_path / "points.npz",
        xyz=xyz.astype(np.float32),
        label=label,
        view=np.zeros(len(label), np.int32),
        instance=np.zeros(len(label), np.int32),
        classes=json.dumps({str(k): v for k, v in CLASSES.items()}),
    )
    grid = {**GRID.to_json(), "bounds": [-0.1, 0.0, 0.56, 0.6]}
    (tmp_path / "grid.json").write_text(json.dumps(grid))
    x = GRID.centers()[..., 0]
    free = (x > LEFT - CELL / 2) & (x < RIGHT + CELL / 2)  # the rays end on the faces' cells
    ones = np.ones(GRID.shape, np.uint8)
    np.savez(
        tmp_path / "observed.npz", near=ones, inside=ones, labelled=ones, free=free.astype(np.uint8)
    )
    return BlueprintInputs(
        tmp_path / "points.npz", tmp_path / "grid.json", tmp_path / "observed.npz"
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_the_cell_in_front_of_a_face_is_floor_the_one_behind_wall(tmp_path, seed) -> None:
    ins = _room(tmp_path, np.random.default_rng(seed))
    n = torch.get_num_threads()
    try:
        c = BlunfConfig(
            steps=300, batch=2048, threads=1, seed=seed, wall_face=True, wall_face_margin=0.0
        )
        cfg = BlueprintConfig(blunf=c)
        bp = Blueprint.load(run(cfg, ins, tmp_path).blueprint)
    finally:
        torch.set_num_threads(n)
    x = GRID.centers()[0, :, 0]
    col = {round(float(v), 3): j for j, v in enumerate(x)}
    rows = slice(3, -3)  # away from the ends of the faces
    assert (bp.labels[rows, col[0.09]] == 0).all()  # centre 3 mm in front of the left face
    assert (bp.labels[rows, col[0.07]] == 1).all()  # centre 17 mm behind it
    assert (bp.labels[rows, col[0.41]] == 0).all()  # centre 3 mm in front of the right face
    assert (bp.labels[rows, col[0.43]] == 1).all()  # centre 17 mm behind it
    inside = (x > LEFT) & (x < RIGHT)
    assert (bp.labels[rows][:, inside] == 0).all()  # the whole room floor


@pytest.mark.parametrize("angle", [0.0, 23.0, 90.0, 151.0])
def test_a_slanted_face_cuts_the_wall_cells_by_their_centres(angle) -> None:
    """A face at any angle crossing cells anywhere: every wall cell whose centre lies in
    front of it (the free side) turns floor, every one behind stays wall."""
    grid = Grid((0.0, 0.0), CELL, (40, 40))
    rng = np.random.default_rng(3)
    t = np.deg2rad(angle)
    normal = np.array([np.cos(t), np.sin(t)])  # towards the room
    on = np.array([0.4, 0.4]) + 0.0037 * normal  # the face: (p - on) . normal = 0
    along = np.array([-normal[1], normal[0]])
    xy = on + np.outer(rng.uniform(-0.5, 0.5, 20000), along)
    xy = xy[(xy >= 0).all(1) & (xy < 0.8).all(1)]
    s = (grid.centers() - on) @ normal  # [H, W] metres, + = in front
    free = s > -CELL  # the rays end on the face's cells
    labels = np.where(s < 0.07, 1, 0).astype(np.uint8)  # the wall drawn 3.5 cells too thick
    out, changed = wall_fronts(labels, CLASSES, grid, xy, free)
    near = np.abs(s) < 0.2
    assert changed == int(((s > 0) & (s < 0.07)).sum())
    assert (out[near & (s > 0)] == 0).all()
    assert (out[near & (s < 0)] == 1).all()


def test_a_margin_keeps_the_cell_the_face_crosses() -> None:
    """margin 0.5: only the wall cells wholly in front of the face's own cell turn floor; the
    cell the face crosses stays wall whichever side of its centre the face passes."""
    grid = Grid((0.0, 0.0), CELL, (20, 20))
    x = grid.centers()[..., 0]
    for face in (0.2063, 0.2137):  # the cell centred 0.21 3.7 mm behind it, 3.7 mm in front
        xy = np.c_[np.full(2000, face), np.linspace(0.0, 0.4, 2000)]
        labels = np.where(x > 0.13, 1, 0).astype(np.uint8)  # wall drawn from 0.14 on
        out, changed = wall_fronts(labels, CLASSES, grid, xy, x < face + CELL, margin=0.5)
        own = (x > face - CELL / 2) & (x < face + CELL / 2)  # the face's own cell: within 1 cm
        assert (out[own] == 1).all() and (out[x > face] == 1).all()
        assert (out[x < face - CELL / 2] == 0).all()
        assert changed == 20 * int(((x[0] > 0.13) & (x[0] < face - CELL / 2)).sum())


def test_without_free_cells_or_wall_points_the_plan_is_unchanged() -> None:
    grid = Grid((0.0, 0.0), CELL, (10, 10))
    labels = np.ones((10, 10), np.uint8)
    labels[:, :3] = 0
    xy = np.c_[np.full(100, 0.055), np.linspace(0, 0.2, 100)]
    for pts, free in ((xy, np.zeros((10, 10), bool)), (np.zeros((0, 2)), np.ones((10, 10), bool))):
        out, changed = wall_fronts(labels, CLASSES, grid, pts, free)
        assert changed == 0 and (out == labels).all()


def test_without_a_floor_class_the_front_takes_the_nearest_other_class() -> None:
    """A plan labelled without floor (no such class): the wall cells in front of the face
    take the class of the nearest cell that is not wall."""
    grid = Grid((0.0, 0.0), CELL, (20, 20))
    x = grid.centers()[..., 0]
    face = 0.2037  # the room at x < face
    y = np.linspace(0.0, 0.4, 2000)
    xy = np.c_[np.full(len(y), face), y]
    labels = np.where(x > 0.15, 1, 3).astype(np.uint8)  # wall drawn from 0.16 on
    out, changed = wall_fronts(labels, {1: "wall", 3: "table"}, grid, xy, x < face + CELL)
    assert changed == 20 * 2  # the columns centred 0.17 and 0.19 (0.21 lies behind)
    assert (out[:, x[0] < face] == 3).all() and (out[:, x[0] > face] == 1).all()


def test_a_face_with_free_cells_on_both_sides_is_left_to_the_field() -> None:
    """Stereo reads through walls: where rays crossed both sides of a face, the room's side
    is unknown and the wall cells stay as the field drew them; one-sided, they are cut."""
    grid = Grid((0.0, 0.0), CELL, (20, 20))
    x = grid.centers()[..., 0]
    xy = np.c_[np.full(2000, 0.2037), np.linspace(0.0, 0.4, 2000)]
    labels = np.where((x > 0.15) & (x < 0.3), 1, 0).astype(np.uint8)
    both, changed = wall_fronts(labels, CLASSES, grid, xy, np.ones((20, 20), bool))
    assert changed == 0 and (both == labels).all()
    one, changed = wall_fronts(labels, CLASSES, grid, xy, x < 0.2037 + CELL)
    assert changed == 20 * 2 and (one[:, x[0] > 0.2037] == labels[:, x[0] > 0.2037]).all()


def test_the_nearest_fill_gives_furniture_against_a_wall_its_cells_and_floor_the_rest() -> None:
    """fill "nearest": the wall cells cut in front of the face take the class of the nearest
    cell the field drew not wall: a sofa standing against the wall keeps the cells up to it,
    the open floor beside it stays floor; fill "floor" gives the sofa's cells to the floor."""
    grid = Grid((0.0, 0.0), CELL, (20, 20))
    x, y = grid.centers()[..., 0], grid.centers()[..., 1]
    face = 0.2037  # the room at x < face
    xy = np.c_[np.full(2000, face), np.linspace(0.0, 0.4, 2000)]
    labels = np.where(x > 0.16, 1, 0).astype(np.uint8)  # wall drawn from 0.16 on
    labels[(x < 0.16) & (y < 0.2)] = 3  # the sofa the field drew up to the wall's band
    classes = {0: "floor", 1: "wall", 3: "sofa"}
    cut = (x > 0.16) & (x < face)  # the columns centred 0.17 and 0.19
    near, n_near = wall_fronts(labels, classes, grid, xy, x < face + CELL, fill="nearest")
    flat, n_flat = wall_fronts(labels, classes, grid, xy, x < face + CELL, fill="floor")
    assert n_near == n_flat == int(cut.sum()) == 20 * 2
    assert (near[cut & (y < 0.2)] == 3).all() and (near[cut & (y > 0.2)] == 0).all()
    assert (flat[cut] == 0).all()
    assert (near[x > face] == 1).all() and (flat[x > face] == 1).all()
    assert (near[~cut] == labels[~cut]).all()

"""blueprint.blunf.free_floor: floor samples where the views looked through and past, and saw
nothing."""

from __future__ import annotations

import numpy as np

from stages.blueprint.blunf import add_free_floor
from stages.common.blueprint import Grid

CLASSES = {0: "floor", 1: "wall", 6: "cabinet"}


def _scene(tmp_path, free: np.ndarray | None, past: np.ndarray | None = None):
    """A 20 x 20 plan of 0.1 m cells: a wall along column 10, floor points in columns 0-1 and
    18-19, one cabinet point at row 5, column 16; every other cell empty (the cameras' path)."""
    grid = Grid((0.0, 0.0), 0.1, (20, 20))
    cells = [(r, 10, 1) for r in range(20)] + [(r, c, 0) for r in range(20) for c in (0, 1, 18, 19)]
    cells.append((5, 16, 6))
    rc = np.array([(r, c) for r, c, _ in cells])
    xy = grid.centers()[rc[:, 0], rc[:, 1]]
    xyz = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    label = np.array([k for *_, k in cells], np.uint8)
    row, col, inside = grid.cell_of(xyz[:, :2])
    path = tmp_path / "observed.npz"
    arrays = {"near": np.ones(grid.shape, np.uint8)}
    if free is not None:
        arrays["free"] = free.astype(np.uint8)
        arrays["past"] = (2 * free if past is None else past).astype(np.uint16)
    np.savez(path, **arrays)
    return path, grid, xyz, label, row, col, inside


def test_empty_cells_the_rays_crossed_become_floor_samples(tmp_path) -> None:
    free = np.ones((20, 20), bool)
    free[:, 12:14] = False  # no ray crossed these: left alone
    past = 2 * free.astype(np.uint16)
    past[15:, 2:10] = 1  # one view looked past the space above these: not enough
    path, grid, xyz, label, row, col, inside = _scene(tmp_path, free, past)
    xyz2, label2, row2, col2, inside2, n = add_free_floor(
        path, grid, CLASSES, xyz, label, row, col, inside
    )
    added = np.zeros(grid.shape, bool)
    added[row2[len(xyz) :], col2[len(xyz) :]] = True
    assert n == int(added.sum()) == len(xyz2) - len(xyz) == len(label2) - len(label)
    assert (label2[len(label) :] == 0).all() and inside2[len(xyz) :].all()
    assert added[:15, 2:10].all()  # the empty band beside the wall: floor, not wall
    assert not added[15:, 2:10].any()
    assert not added[:, [0, 1, 10, 18, 19]].any()  # cells holding points keep only theirs
    assert not added[:, 12:14].any()  # not crossed by a ray
    assert not added[5, 15] and not added[4, 16]  # nearest to the cabinet: maybe its top
    # the added points sit at the centres of their cells
    r, c, ok = grid.cell_of(xyz2[len(xyz) :, :2])
    assert ok.all() and (r == row2[len(xyz) :]).all() and (c == col2[len(xyz) :]).all()


def test_without_free_cells_nothing_is_added(tmp_path) -> None:
    path, grid, xyz, label, row, col, inside = _scene(tmp_path, None)
    out = add_free_floor(path, grid, CLASSES, xyz, label, row, col, inside)
    assert out[-1] == 0 and len(out[0]) == len(xyz)


def test_without_views_looking_past_nothing_is_added(tmp_path) -> None:
    """An observed.npz without the "past" layer (or with no view looking past) adds nothing:
    rays cross an object whose top no view saw as they cross the floor."""
    free = np.ones((20, 20), bool)
    path, grid, xyz, label, row, col, inside = _scene(tmp_path, free, np.zeros((20, 20)))
    assert add_free_floor(path, grid, CLASSES, xyz, label, row, col, inside)[-1] == 0
    np.savez(path, near=np.ones((20, 20), np.uint8), free=free.astype(np.uint8))
    assert add_free_floor(path, grid, CLASSES, xyz, label, row, col, inside)[-1] == 0

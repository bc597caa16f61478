"""MVR baseline: every cell takes the most frequent label among the points projected into it.

Vectorised: votes are counted with a bincount over (cell, class) pairs, CHUNK points at a
time into one table of the plan's cells by the classes present, so the memory follows the
plan's area, not the number of points (views); cells with fewer than `min_votes` points stay
unknown (255). Ties go to the lowest class id.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from stages.blueprint.config import BlueprintConfig, BlueprintInputs, BlueprintOutputs
from stages.blueprint.instances import instance_raster
from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.common.io import write_json
from stages.common.points import read_grid, read_instances, read_points

log = logging.getLogger(__name__)

CHUNK = 1 << 20  # points counted at a time
TABLE_MAX = 1 << 23  # cells x classes counted in one table; a larger plan counts at once


def run(cfg: BlueprintConfig, inputs: BlueprintInputs, out: Path) -> BlueprintOutputs:
    """Majority vote of the projected labels per cell."""
    if cfg.mvr.min_votes < 1:
        raise BlunfError(f"blueprint.mvr.min_votes must be >= 1, got {cfg.mvr.min_votes}")
    log.debug("blueprint/mvr: %s", cfg.mvr)
    t0 = time.perf_counter()
    xyz, label, _, classes = read_points(inputs.points)
    grid = read_grid(inputs.grid)
    t1 = time.perf_counter()
    labels, voted = majority_vote(xyz[:, :2], label, grid, cfg.mvr.min_votes)
    seconds = time.perf_counter() - t1
    inst = instance_raster(labels, grid, xyz[:, :2], label, read_instances(inputs.points))
    outs = BlueprintOutputs(blueprint=Path(out) / "blueprint.npz", stats=Path(out) / "mvr.json")
    Blueprint(labels, grid, classes, inst).save(outs.blueprint)
    h, w = grid.shape
    write_json(
        outs.stats,
        {
            "points": int(len(label)),
            "cells": h * w,
            "cells_voted": voted,
            "completeness": round(100.0 * float((labels != UNKNOWN).mean()), 3),
            "seconds": round(seconds, 3),
            "total_seconds": round(time.perf_counter() - t0, 3),
        },
    )
    log.info("blueprint/mvr: %d of %d cells voted in %.2f s", voted, h * w, seconds)
    return outs


def majority_vote(
    xy: np.ndarray, label: np.ndarray, grid: Grid, min_votes: int = 1
) -> tuple[np.ndarray, int]:
    """Per-cell majority label of points xy [N, 2] with labels [N].

    Returns (labels uint8 [H, W] with UNKNOWN where fewer than min_votes points fell,
    number of cells with at least one point).
    """
    h, w = grid.shape
    plan = np.full(h * w, UNKNOWN, np.uint8)
    label = np.asarray(label)
    if len(label) == 0:
        return plan.reshape(h, w), 0
    present = np.bincount(label.astype(np.int64), minlength=256) > 0  # class ids are < 256
    ids = np.flatnonzero(present)  # [K] sorted: the first maximum is the lowest id
    if h * w * len(ids) > TABLE_MAX:
        return _vote_at_once(xy, label, grid, min_votes)
    index = np.cumsum(present) - 1  # class id -> its column
    votes: np.ndarray = np.zeros((h * w) * len(ids), np.int64)  # [H W K], then [H W, K]
    for s in range(0, len(label), CHUNK):
        row, col, inside = grid.cell_of(xy[s : s + CHUNK])
        cell = (row * w + col)[inside]
        k = index[label[s : s + CHUNK][inside].astype(np.int64)]
        votes += np.bincount(cell * len(ids) + k, minlength=len(votes))
    votes = votes.reshape(h * w, len(ids))  # [H W, K]
    total = votes.sum(axis=1)
    cells = np.flatnonzero(total)  # occupied cells
    win = ids[votes[cells].argmax(axis=1)].astype(np.uint8)  # [C]
    enough = total[cells] >= min_votes
    plan[cells[enough]] = win[enough]
    return plan.reshape(h, w), int(len(cells))


def _vote_at_once(
    xy: np.ndarray, label: np.ndarray, grid: Grid, min_votes: int
) -> tuple[np.ndarray, int]:
    """majority_vote over the occupied cells only, every point at once (plans too large for
    one table of every cell by every class)."""
    h, w = grid.shape
    row, col, inside = grid.cell_of(xy)
    cell = (row * w + col)[inside]  # [M] flat cell of each point inside
    lab = np.asarray(label)[inside].astype(np.int64)  # [M]
    plan = np.full(h * w, UNKNOWN, np.uint8)
    if len(cell) == 0:
        return plan.reshape(h, w), 0
    ids, k = np.unique(lab, return_inverse=True)  # contiguous class index per point
    cells, c = np.unique(cell, return_inverse=True)  # occupied cells, index per point
    votes = np.bincount(c * len(ids) + k, minlength=len(cells) * len(ids))
    votes = votes.reshape(len(cells), len(ids))  # [C, K]
    win = ids[votes.argmax(axis=1)].astype(np.uint8)  # [C] first maximum = lowest id
    enough = votes.sum(axis=1) >= min_votes
    plan[cells[enough]] = win[enough]
    return plan.reshape(h, w), int(len(cells))

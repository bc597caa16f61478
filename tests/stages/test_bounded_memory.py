"""Memory that follows what is near, not the whole capture: functions whose inputs grow with
the views hold a bounded working set (tracemalloc counts numpy's buffers)."""

from __future__ import annotations

import tracemalloc

import numpy as np

from stages.common.blueprint import Grid
from stages.project import observed as obs


def _peak(fn, *args) -> int:
    """Bytes of the largest working set while fn(*args) ran, over what it returns."""
    tracemalloc.start()
    try:
        fn(*args)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _rays(k: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.5, 7.5, size=(k, 2))
    return start, rng.uniform(0.0, 8.0, size=(k, 2))


def test_ray_cells_runs_in_bounded_chunks_and_marks_the_same_cells(monkeypatch) -> None:
    grid = Grid((0.0, 0.0), 0.04, (200, 200))  # 8 x 8 m at 4 cm
    start, end = _rays(5_000)
    whole = obs.ray_cells(grid, start, end)
    monkeypatch.setattr(
        obs, "RAY_CHUNK", 1000, raising=False
    )  # small runs: one ray at least in each
    assert np.array_equal(obs.ray_cells(grid, start, end), whole)
    monkeypatch.setattr(obs, "RAY_CHUNK", 1, raising=False)
    assert np.array_equal(obs.ray_cells(grid, start[:300], end[:300]), obs.ray_cells(
        grid, start[:300], end[:300]))  # fmt: skip
    monkeypatch.undo()
    # ~100 samples a ray: 4x the rays (views) must not take 4x the memory. Without the runs,
    # every sample's [S, 2] position and cell were held at once (~260 MB at 40 000 rays)
    small, big = _rays(10_000), _rays(40_000, seed=1)
    p_small = _peak(obs.ray_cells, grid, *small)
    p_big = _peak(obs.ray_cells, grid, *big)
    inputs = big[0].nbytes * 6  # the per-ray arrays (lengths, ends, segments) do grow
    assert p_big < p_small + inputs, (p_small, p_big)
    assert p_big < 30e6


def _labelled(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.2, 8.2, size=(n, 2))  # some points off the plan
    lab = rng.choice(np.array([0, 3, 4, 7, 200], np.uint8), n, p=[0.4, 0.3, 0.1, 0.1, 0.1])
    return xy, lab


def test_majority_vote_counts_in_chunks_into_a_table_the_size_of_the_plan(monkeypatch) -> None:
    from stages.blueprint import mvr

    grid = Grid((0.0, 0.0), 0.05, (160, 160))
    xy, lab = _labelled(60_000, 0)
    at_once = mvr._vote_at_once(xy, lab, grid, 2)
    monkeypatch.setattr(mvr, "CHUNK", 7_000, raising=False)  # chunks end mid-cell
    got = mvr.majority_vote(xy, lab, grid, 2)
    assert np.array_equal(got[0], at_once[0]) and got[1] == at_once[1]
    monkeypatch.setattr(mvr, "TABLE_MAX", 10, raising=False)  # too large a table: at once
    assert np.array_equal(mvr.majority_vote(xy, lab, grid, 2)[0], at_once[0])
    monkeypatch.setattr(mvr, "TABLE_MAX", 1 << 23, raising=False)
    monkeypatch.setattr(mvr, "CHUNK", 1 << 16, raising=False)
    # 4x the points (views) must not take 4x the memory: without the chunks every point's
    # cell, class and sort order were held at once (~60 MB at 800 000 points)
    small, big = _labelled(200_000, 1), _labelled(800_000, 2)
    p_small = _peak(mvr.majority_vote, *small, grid)
    p_big = _peak(mvr.majority_vote, *big, grid)
    assert p_big < 1.3 * p_small, (p_small, p_big)

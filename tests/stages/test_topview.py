"""Top-view occlusion: hand-made cells, and the vectorised grouping against a per-cell loop."""

from __future__ import annotations

import numpy as np

from stages.project.topview import cell_keep, top_view_keep

FLOOR, WALL, TABLE, CHAIR, CUSHION = 0, 1, 3, 4, 5

# (x, y, z, label, kept?) with cells of 0.1 m, band 0.1 m, min_points 2. The top of a cell is
# the z of its 2nd highest point; a class is kept when its highest point reaches top - 0.1.
POINTS = [
    # cell [0, 0.1) x [0, 0.1): table top seen twice, a leg, floor seen between the legs.
    # top = 0.75 -> table reaches 0.75 (kept, the leg too), floor reaches 0 (dropped)
    (0.02, 0.02, 0.75, TABLE, True),
    (0.08, 0.03, 0.74, TABLE, True),
    (0.05, 0.05, 0.30, TABLE, True),
    (0.03, 0.07, 0.00, FLOOR, False),
    (0.07, 0.08, 0.00, FLOOR, False),
    # cell [0.1, 0.2): floor only, a few mm apart -> all kept
    (0.15, 0.05, 0.00, FLOOR, True),
    (0.12, 0.02, 0.01, FLOOR, True),
    (0.18, 0.09, 0.02, FLOOR, True),
    # cell [0.2, 0.3): one stray chair point high up; the 2nd highest is floor (0.0), so the
    # top is 0.0 and nothing is dropped (the stray point reaches above it: kept as well)
    (0.25, 0.05, 1.00, CHAIR, True),
    (0.22, 0.02, 0.00, FLOOR, True),
    (0.28, 0.08, 0.00, FLOOR, True),
    # cell [0.3, 0.4): a lone point, fewer than min_points: kept whatever it is
    (0.35, 0.05, 0.60, CHAIR, True),
    # cell [0.4, 0.5): a wall from 0.2 to 2.4 m and floor at its foot: top = 1.0 (2nd
    # highest), wall kept whole (its low points too), floor (0 < 0.9) dropped
    (0.45, 0.05, 2.40, WALL, True),
    (0.45, 0.05, 1.00, WALL, True),
    (0.45, 0.05, 0.20, WALL, True),
    (0.42, 0.05, 0.00, FLOOR, False),
    (0.48, 0.05, 0.00, FLOOR, False),
    # cell [0.5, 0.6): a chair seat at 0.45 with a cushion class at 0.37 (within the band
    # of 0.1 below the top 0.45: kept) and floor under the seat (dropped)
    (0.55, 0.05, 0.45, CHAIR, True),
    (0.52, 0.05, 0.45, CHAIR, True),
    (0.55, 0.02, 0.37, CUSHION, True),
    (0.55, 0.08, 0.00, FLOOR, False),
    # cell [-0.1, 0) x [0, 0.1): west of the origin (cells are aligned on multiples of the
    # cell size, not on the points): a table over floor -> floor dropped
    (-0.05, 0.05, 0.75, TABLE, True),
    (-0.02, 0.05, 0.75, TABLE, True),
    (-0.08, 0.05, 0.00, FLOOR, False),
    # cell [0, 0.1) x [0.1, 0.2), north of the first: floor alone, not under that table
    (0.05, 0.15, 0.00, FLOOR, True),
    (0.05, 0.12, 0.00, FLOOR, True),
]


def _arrays():
    a = np.array([p[:3] for p in POINTS], np.float64)  # [N, 3]
    lab = np.array([p[3] for p in POINTS], np.uint8)  # [N]
    keep = np.array([p[4] for p in POINTS])  # [N]
    return a, lab, keep


def test_hand_made_cells():
    xyz, lab, want = _arrays()
    got = cell_keep(xyz, lab, cell=0.1, band=0.1, min_points=2)
    np.testing.assert_array_equal(got, want)
    # one grid (shifts = 1) is cell_keep itself
    np.testing.assert_array_equal(top_view_keep(xyz, lab, 0.1, 0.1, 2, shifts=1), want)


def test_order_of_the_points_does_not_matter():
    xyz, lab, want = _arrays()
    perm = np.random.default_rng(0).permutation(len(lab))
    got = cell_keep(xyz[perm], lab[perm], cell=0.1, band=0.1, min_points=2)
    np.testing.assert_array_equal(got, want[perm])


def test_min_points_one_trusts_the_highest_point():
    xyz, lab, want = _arrays()
    got = cell_keep(xyz, lab, cell=0.1, band=0.1, min_points=1)
    # the stray chair point now is the top of its cell (1.0): the floor there goes
    want[[9, 10]] = False
    # the wall cell's top is 2.4: the wall still reaches it, the floor is dropped as before
    np.testing.assert_array_equal(got, want)


def test_matches_a_per_cell_loop_on_random_points():
    rng = np.random.default_rng(1)
    n = 3000
    xyz = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(0, 2, n)]  # [N, 3]
    lab = rng.integers(0, 5, n).astype(np.uint8)
    cell, band, m = 0.15, 0.3, 3
    got = cell_keep(xyz, lab, cell, band, m)

    want = _reference_keep(xyz, lab, cell, band, m)
    assert 0 < (~want).sum() < n  # the case exercises both outcomes
    np.testing.assert_array_equal(got, want)


def test_shifted_grids_keep_floor_beyond_half_a_cell_from_a_wall():
    # A wall face at x = 0.001 (points up to 2 m, x in [0, 0.002]) and floor at x = 0.005 ..
    # 0.095 every 0.01 m (two points each), cells of 0.08 m, 2 x 2 shifts of 0.04 m.
    # Unshifted, the cell [0, 0.08) holds the wall: the floor up to x < 0.08 goes (8 spots).
    # Shifted by 0.04 the cells are [-0.04, 0.04) (the wall's) and [0.04, 0.12) (floor only):
    # the floor at x >= 0.04 is kept there, so only x = 0.005 .. 0.035 (4 spots) is dropped.
    wall = [(0.001 + 0.001 * (k % 2), 0.02, 0.2 * k, WALL) for k in range(11)]
    floor = [(x, 0.02 + dy, 0.0, FLOOR) for x in np.arange(0.005, 0.1, 0.01) for dy in (0, 0.01)]
    pts = np.array([p[:3] for p in wall + floor])
    lab = np.array([p[3] for p in wall + floor], np.uint8)
    x = pts[:, 0]
    one = top_view_keep(pts, lab, 0.08, 0.1, 2, shifts=1)
    two = top_view_keep(pts, lab, 0.08, 0.1, 2, shifts=2)
    is_floor = lab == FLOOR
    np.testing.assert_array_equal(one[is_floor], x[is_floor] >= 0.08)
    np.testing.assert_array_equal(two[is_floor], x[is_floor] >= 0.04)
    assert one[~is_floor].all() and two[~is_floor].all()


def test_no_points():
    assert top_view_keep(np.zeros((0, 3)), np.zeros(0, np.uint8), 0.1, 0.1, 2, 2).shape == (0,)


def test_ties_at_the_top_count_as_several_points():
    # z on a 5 cm lattice: many points share a cell's highest z. The k-th highest counts
    # them all (two points at the top make it the 2nd highest), as a sort does; labels use
    # ids up to 255
    rng = np.random.default_rng(2)
    n = 4000
    xyz = np.c_[rng.uniform(-1, 1, (n, 2)), np.round(rng.uniform(0, 2, n) / 0.05) * 0.05]
    lab = rng.choice(np.array([0, 7, 200, 255], np.uint8), n)
    cell, band = 0.2, 0.05
    for m in (2, 3):
        got = cell_keep(xyz, lab, cell, band, m)
        want = _reference_keep(xyz, lab, cell, band, m)
        assert 0 < (~want).sum() < n
        np.testing.assert_array_equal(got, want)


def _reference_keep(xyz: np.ndarray, lab: np.ndarray, cell: float, band: float, m: int):
    """cell_keep written plainly, cell by cell: a class's points in a cell with at least m
    points stay when its highest point is within `band` of the cell's m-th highest."""
    want = np.ones(len(xyz), bool)
    ij = np.floor(xyz[:, :2] / cell).astype(int)
    for key in {tuple(k) for k in ij}:
        idx = np.flatnonzero((ij == key).all(axis=1))
        if len(idx) < m:
            continue
        top = np.sort(xyz[idx, 2])[::-1][m - 1]
        for c in np.unique(lab[idx]):
            of_c = idx[lab[idx] == c]
            want[of_c] = xyz[of_c, 2].max() >= top - band
    return want


def test_offset_grids_match_cell_keep_on_each_shifted_grid():
    # top_view_keep groups the points once into cells of cell / shifts and merges them per
    # offset grid; it must keep exactly the union of cell_keep over the shifted grids
    # (ties on a 5 cm lattice, a few points per cell, several classes)
    rng = np.random.default_rng(3)
    n = 3000
    xyz = np.c_[rng.uniform(-0.7, 0.9, (n, 2)), np.round(rng.uniform(0, 2, n) / 0.05) * 0.05]
    lab = rng.choice(np.array([0, 1, 7, 255], np.uint8), n)
    cell, band = 0.12, 0.1
    for shifts in (2, 3):
        for m in (1, 2, 3):
            want = np.zeros(n, bool)
            for i in range(shifts):
                for j in range(shifts):
                    off = np.array([i * cell / shifts, j * cell / shifts, 0.0])
                    want |= cell_keep(xyz + off, lab, cell, band, m)
            assert 0 < (~want).sum() < n
            np.testing.assert_array_equal(top_view_keep(xyz, lab, cell, band, m, shifts), want)

"""Walls seen through holes in the fused surface (stages/semantics/wallfill.py): rays of exact
geometry against two wall planes of a 4 x 3 m room."""

from __future__ import annotations

import numpy as np

from stages.semantics.floorfill import Footprint, floor_through
from stages.semantics.wallfill import wall_through

# the north wall y = 3 (facing -y; along it s = x) seen in x 0.5-3.5 m, z 0.8-2 m, and the
# east wall x = 4 (facing -x; s = -y) seen in y 0.1-2.9 m, z 0.8-2 m: boxes as the
# segmentation writes them, [s_lo, z_lo, s_hi, z_hi]
NORTH = {"kind": "wall", "normal": [0.0, -1.0, 0.0], "d": 3.0, "box": [0.5, 0.8, 3.5, 2.0]}
EAST = {"kind": "wall", "normal": [-1.0, 0.0, 0.0], "d": 4.0, "box": [-2.9, 0.8, -0.1, 2.0]}
EYE = (2.0, 1.0, 1.5)
CASES = [  # (direction, first surface hit (ray parameter), expected crossing, wall index)
    ((0.0, 1.0, 0.0), np.inf, 2.0, 0),  # level at the north wall: a hole in it
    ((0.0, 1.0, -0.6), np.inf, 2.0, 0),  # z 0.3: below the seen box, above the floor
    ((0.0, 1.0, -1.0), np.inf, 0.0, -1),  # z -0.5: under the floor
    ((0.0, 1.0, 0.0), 1.0, 0.0, -1),  # a surface in front of the wall
    ((0.0, 1.0, 0.0), 2.5, 0.0, -1),  # a surface behind its plane: seen through an opening
    ((-1.6, 1.0, 0.0), np.inf, 0.0, -1),  # x -1.2 on the north plane: beyond its extent
    ((0.0, -1.0, 0.0), np.inf, 0.0, -1),  # away from both
    ((1.0, 0.5, 0.0), np.inf, 2.0, 1),  # the east wall at y 2, before the north plane
    ((0.0, 1.0, 0.55), np.inf, 0.0, -1),  # z 2.6: above the wall's top
]


def _rays() -> np.ndarray:
    d = np.array([c[0] for c in CASES], np.float64)
    return np.concatenate([np.broadcast_to(EYE, d.shape), d], axis=1).astype(np.float32)


def test_wall_is_seen_through_holes_inside_its_extent_only():
    t_hit = np.array([c[1] for c in CASES])
    t, which = wall_through(_rays(), t_hit, (NORTH, EAST), floor_z=0.0, room=None, margin=0.03)
    assert t.dtype == np.float32
    np.testing.assert_allclose(t, [c[2] for c in CASES], atol=1e-5)
    np.testing.assert_array_equal(which, [c[3] for c in CASES])


def test_wall_fill_stays_inside_the_room_footprint():
    """A footprint covering x < 1.5 only: the crossing at x = 2 on the north wall is outside."""
    xy = np.stack(np.meshgrid(np.arange(0.0, 1.5, 0.04), np.arange(0.0, 3.0, 0.04)), -1)
    room = Footprint.of(xy.reshape(-1, 2), 0.05)
    t_hit = np.full(len(CASES), np.inf)
    t, which = wall_through(_rays(), t_hit, (NORTH,), floor_z=0.0, room=room, margin=0.03)
    assert (t == 0).all() and (which == -1).all()
    rays = np.array([[1.0, 1.0, 1.5, 0.0, 1.0, 0.0]], np.float32)  # x = 1: inside
    t, _ = wall_through(rays, np.array([np.inf]), (NORTH,), 0.0, room, 0.03)
    np.testing.assert_allclose(t, [2.0], atol=1e-5)


def test_a_view_of_rays_gives_each_ray_what_it_gives_alone():
    """wall_through and floor_through compute only the rays still in play (unhit, or bound for
    the floor) and scatter them back: over an [H, W] view with hits and holes mixed, every
    pixel reads as that ray passed alone."""
    rng = np.random.default_rng(3)
    h, w = 9, 11
    d = rng.normal(size=(h, w, 3)) * [1.0, 1.0, 0.6] + [0.3, 0.8, -0.4]
    rays = np.concatenate([np.broadcast_to(EYE, d.shape), d], axis=-1).astype(np.float32)
    t_hit = np.where(rng.random((h, w)) < 0.4, rng.uniform(0.5, 4.0, (h, w)), np.inf)
    xy = np.stack(np.meshgrid(np.arange(0.0, 4.0, 0.04), np.arange(0.0, 3.0, 0.04)), -1)
    room = Footprint.of(xy.reshape(-1, 2), 0.05)
    t, which = wall_through(rays, t_hit, (NORTH, EAST), 0.0, room, 0.03)
    floor = floor_through(rays, t_hit, 0.0, room, 0.03, (NORTH, EAST))
    assert t.shape == which.shape == floor.shape == (h, w)
    assert (t > 0).sum() > 5 and (floor > 0).sum() > 5 and (t[np.isfinite(t_hit)] == 0).all()
    for i, j in np.ndindex(h, w):
        one = rays[i, j][None], t_hit[i, j][None]
        t1, w1 = wall_through(*one, (NORTH, EAST), 0.0, room, 0.03)
        assert (t1[0], w1[0]) == (t[i, j], which[i, j])
        assert floor_through(*one, 0.0, room, 0.03, (NORTH, EAST))[0] == floor[i, j]

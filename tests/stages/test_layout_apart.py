"""layout: two rooms' faces of one partition that met on one line are set a wall apart again
(stages/layout/walls.py kept_apart), the face whose room took the partition's band in moving
back; faces a real wall's thickness apart, or not side by side, are left."""

from __future__ import annotations

import numpy as np
import pytest

from stages.common.blueprint import Blueprint, Grid
from stages.layout import LayoutConfig
from stages.layout.walls import kept_apart

CELL = 0.02
GRID = Grid((-0.5, -2.5), CELL, (250, 300))  # x in [-0.5, 5.5], y in [-2.5, 2.5]


def _plan(band: tuple[float, float]) -> Blueprint:
    """Floor, with a partition's band of wall cells at y in `band` across x in [0, 5]."""
    c = GRID.centers()
    labels = np.zeros(GRID.shape, np.uint8)
    labels[(c[..., 1] > band[0]) & (c[..., 1] < band[1]) & (c[..., 0] > 0) & (c[..., 0] < 5)] = 1
    return Blueprint(labels, GRID, {0: "floor", 1: "wall"})


def _walls(south_top: float, north_bottom: float) -> list[dict]:
    """The partition's two faces: room 0's north edge (counter-clockwise: east to west, its
    outward normal +y) at y = south_top, room 1's south edge (west to east, normal -y) at y =
    north_bottom, with one unrelated wall of room 1."""
    return [
        {"start": [5.0, south_top], "end": [0.0, south_top], "room": 0},
        {"start": [0.0, north_bottom], "end": [5.0, north_bottom], "room": 1},
        {"start": [5.0, north_bottom], "end": [5.0, 2.0], "room": 1},
    ]


def test_the_room_that_took_the_band_in_gives_the_partition_its_thickness_back() -> None:
    cfg = LayoutConfig()
    # both faces on the band's north side: room 0 holds the band
    out = kept_apart(_walls(0.12, 0.12), _plan((0.0, 0.12)), cfg)
    assert out[0] == pytest.approx(-cfg.default_thickness)  # room 0's face back 0.1 m
    assert out[1] == 0 and out[2] == 0
    # both on its south side: room 1 holds it, and moves
    out = kept_apart(_walls(0.0, 0.0), _plan((0.0, 0.12)), cfg)
    assert out[1] == pytest.approx(-cfg.default_thickness) and out[0] == 0
    # 2 cm apart: back to 0.1 m apart
    out = kept_apart(_walls(0.1, 0.12), _plan((-0.02, 0.12)), cfg)
    assert out[0] == pytest.approx(0.02 - cfg.default_thickness)


@pytest.mark.parametrize(
    "walls",
    [
        _walls(0.0, 0.12),  # a partition drawn 0.12 m thick
        _walls(0.12, 0.12)[:1] + [{"start": [5.0, 0.12], "end": [9.0, 0.12], "room": 1}],
    ],
    ids=["thick", "not-side-by-side"],
)
def test_faces_a_wall_apart_or_not_side_by_side_are_left(walls) -> None:
    out = kept_apart(walls, _plan((0.0, 0.12)), LayoutConfig())
    assert not out.any()

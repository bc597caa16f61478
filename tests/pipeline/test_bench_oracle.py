"""The oracle ladder's plane pixels (pipeline/bench/oracle.py, rung O3) on the exact room of
tests/stages/exact_room.py: the floor and the walls of an axis-aligned room are planes; turned
45 degrees about the vertical, the walls are no axis-aligned plane and only the floor is."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pipeline.bench.oracle import plane_mask
from stages.common.capture import Frame
from tests.stages.exact_room import INTR, make_scene, render, room_poses


def _turn_z(deg: float) -> np.ndarray:
    t = np.radians(deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    return m


def test_plane_pixels_are_the_axis_aligned_surfaces():
    scene = make_scene()
    frame = Frame("v", None, INTR)  # only the intrinsics are read
    checked = 0
    for pose in room_poses()[::3]:
        depth, _ = render(scene, pose)  # [H, W] exact
        world = _world(depth, pose)
        floor = (depth > 0) & (np.abs(world[..., 2]) < 0.005)
        walls = (depth > 0) & (
            (np.abs(world[..., 0]) < 0.005)
            | (np.abs(world[..., 0] - 4.0) < 0.005)
            | (np.abs(world[..., 1]) < 0.005)
            | (np.abs(world[..., 1] - 3.0) < 0.005)
        )
        got = plane_mask(depth, frame, pose)
        for surface in (floor, walls):
            # the normals come from neighbours 2 px away: 3 px from another surface or the
            # border they are the surface's own
            sel = ndimage.binary_erosion(surface, iterations=3)
            if sel.sum() > 50:
                assert got[sel].mean() > 0.9
                checked += 1
        # the same view in a room turned 45 degrees: its walls lie on no axis-aligned plane
        turned = plane_mask(depth, frame, _turn_z(45.0) @ pose)
        inner = ndimage.binary_erosion(floor, iterations=3)
        if inner.sum() > 50:
            assert turned[inner].mean() > 0.9
        if walls.sum() > 50:
            assert turned[walls].mean() < 0.1
    assert checked >= 4  # floor and walls seen in several views


def _world(depth: np.ndarray, pose: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))  # integer = pixel centre
    cam = np.stack([(u - INTR.cx) / INTR.fx * depth, (v - INTR.cy) / INTR.fy * depth, depth], -1)
    return cam @ pose[:3, :3].T + pose[:3, 3]

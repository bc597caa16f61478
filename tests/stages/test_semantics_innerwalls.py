"""Walls between rooms from the views' readings (semantics.point_walls.inner): two rooms joined
by a doorway in a 12 cm wall, a wardrobe against that wall, a table; cameras in both rooms
read what their rays hit (ray-cast from the boxes). Both faces of the wall are found, each
stopping at the doorway; the wardrobe's front and the table are no wall, and the same home
without the wall (one room, the wardrobe standing free) gets no wall inside it."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from stages.semantics import SemanticsConfig
from stages.semantics.innerwalls import inner_walls
from stages.semantics.pointwalls import PointWallOptions, point_walls, room_directions
from stages.semantics.segment import segment

T = 0.12  # wall thickness
W, D, H = 6.0, 4.0, 2.5  # the home: x in [0, W], y in [0, D], walls H high
X0 = 3.0  # the wall between the rooms: x in [X0, X0 + T]
DOOR = (1.5, 2.4)  # its doorway along y, 2 m high
OUTER = [
    ((-T, -T, 0.0), (W + T, 0.0, H)),
    ((-T, D, 0.0), (W + T, D + T, H)),
    ((-T, 0.0, 0.0), (0.0, D, H)),
    ((W, 0.0, 0.0), (W + T, D, H)),
    ((-T, -T, -0.05), (W + T, D + T, 0.0)),  # the floor
    ((-T, -T, H), (W + T, D + T, H + 0.05)),  # the ceiling
]
INNER = [
    ((X0, 0.0, 0.0), (X0 + T, DOOR[0], H)),
    ((X0, DOOR[1], 0.0), (X0 + T, D, H)),
    ((X0, DOOR[0], 2.0), (X0 + T, DOOR[1], H)),  # over the doorway
]
FURNITURE = [
    ((X0 + T, 2.7, 0.0), (X0 + T + 0.6, 3.9, 2.0)),  # a wardrobe against the wall
    ((1.0, 1.0, 0.7), (2.2, 2.0, 0.75)),  # a table top
    ((4.0, 0.0, 0.0), (5.5, 0.6, 0.9)),  # a counter against the south wall
]
CAMS = [(1.0, 3.0, 1.5), (2.0, 0.6, 1.4), (1.6, 2.6, 1.6), (4.5, 1.5, 1.5), (5.3, 3.0, 1.4),
        (4.2, 2.2, 1.6)]  # fmt: skip
OPT = PointWallOptions(dist=0.05, min_length=1.0, min_height=0.5, min_area=1.0, max_beyond=0.2,
                       top=1.9)  # fmt: skip


def _readings(boxes, n_rays: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """What rays from every camera in CAMS (every direction) hit: (points, their cameras)."""
    scene = o3d.t.geometry.RaycastingScene()
    for lo, hi in boxes:
        box = trimesh.creation.box(bounds=[lo, hi])
        scene.add_triangles(box.vertices.astype(np.float32), box.faces.astype(np.uint32))
    i = np.arange(n_rays) + 0.5  # a Fibonacci sphere of directions
    z = 1.0 - 2.0 * i / n_rays
    a = np.pi * (1.0 + 5.0**0.5) * i
    d = np.stack([np.cos(a) * np.sqrt(1 - z**2), np.sin(a) * np.sqrt(1 - z**2), z], 1)
    pts, eyes = [], []
    for c in CAMS:
        rays = np.concatenate([np.broadcast_to(c, d.shape), d], 1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        ok = np.isfinite(t)
        pts.append(np.asarray(c) + t[ok, None] * d[ok])
        eyes.append(np.broadcast_to(c, (int(ok.sum()), 3)))
    return np.concatenate(pts), np.concatenate(eyes)


def _walls(p: np.ndarray, eyes: np.ndarray) -> tuple[list[dict], list[dict]]:
    dirs = room_directions(p, OPT.dist)
    outer = point_walls(p, np.unique(eyes, axis=0), dirs, 0.0, OPT)
    return outer, inner_walls(p, eyes, dirs, 0.0, OPT, 0.6, outer)


def test_both_faces_of_the_wall_between_two_rooms_are_found_up_to_the_doorway():
    p, eyes = _readings(OUTER + INNER + FURNITURE)
    outer, inner = _walls(p, eyes)
    assert len(outer) == 4  # the home's bounding walls, one per direction
    west = [w for w in inner if w["normal"][0] < -0.99]  # facing room 1
    east = [w for w in inner if w["normal"][0] > 0.99]  # facing room 2
    assert len(west) + len(east) == len(inner)  # nothing else: no wardrobe, table, counter
    for faces, x in ((west, X0), (east, X0 + T)):
        assert faces
        for w in faces:  # normal . p + d = 0 on the face
            assert -w["d"] / w["normal"][0] == pytest.approx(x, abs=0.03)
        # along y (the box runs along (-n_y, n_x): y for +x, -y for -x), from the doorway on
        ys = [sorted(np.sign(w["normal"][0]) * np.array([w["box"][0], w["box"][2]]))
              for w in faces]  # fmt: skip
        assert not any(a < sum(DOOR) / 2 < b for a, b in ys)  # open at the doorway
        cover = sum(min(b, DOOR[0]) - max(a, 0.0) for a, b in ys if a < DOOR[0])
        assert cover >= 0.8 * DOOR[0]  # the wall south of the doorway
        # north of it: the west face all of it, the east face where the wardrobe leaves it
        north = [(a, b) for a, b in ys if b > DOOR[1]]
        assert north and min(a for a, _ in north) == pytest.approx(DOOR[1], abs=0.25)
    assert not [w for w in inner if abs(-w["d"] / w["normal"][0] - (X0 + T + 0.6)) < 0.1]


def test_one_room_with_its_furniture_gets_no_wall_inside():
    """The same home without the wall: the wardrobe stands free, 2 m high, seen all round
    (its back is a plane 1.2 x 2 m of readings that no ray crossed below 2 m: the ceiling
    seen over it tells it from a wall)."""
    p, eyes = _readings(OUTER + FURNITURE)
    outer, inner = _walls(p, eyes)
    assert len(outer) == 4 and inner == []


def test_the_stretches_of_one_face_either_side_of_a_doorway_are_both_walls():
    """The segmentation keeps every stretch the readings give, not the first of a plane: a
    wall found twice (the same plane, overlapping) is one, a doorway's two sides are two."""
    floor = trimesh.creation.box(bounds=[(0.0, 0.0, -0.05), (W, D, 0.0)])
    p, eyes = _readings(OUTER + INNER + FURNITURE)
    _, inner = _walls(p, eyes)
    west = [w for w in inner if w["normal"][0] < -0.99]
    assert len(west) == 2  # south and north of the doorway
    seg = segment(
        np.asarray(floor.vertices, np.float64),
        np.asarray(floor.faces, np.int64),
        SemanticsConfig(),
        lambda c, n, area, floor_z: [*west, west[0]],  # the south one twice
    )
    walls = [pl for pl in seg.planes if pl["kind"] == "wall"]
    assert sorted(w["box"][0] for w in walls) == sorted(w["box"][0] for w in west)

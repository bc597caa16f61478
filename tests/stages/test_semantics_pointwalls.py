"""Walls from the views' readings (semantics.point_walls): a plain wall that photos alone leave
in patches. The mesh holds two counters and, above the north one, only a 0.6 m strip of the
wall behind it (a backsplash: too low for a wall plane of the mesh), as stereo gives of the
7-Scenes kitchen; the readings the views took of it are the evidence. The strip's plane,
the outermost along north with nothing seen beyond it, is a wall: its triangles are wall and
the rays over it that hit nothing are wall at its plane; the counter fronts (the counter
tops and the strip lie beyond them) are not walls."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.classes import OBJECT, WALL
from stages.common.io import read_label, write_depth_npy
from stages.semantics import IMPLS, SemanticsConfig, SemanticsInputs
from stages.semantics.config import PointWallsConfig
from stages.semantics.pointwalls import PointWallOptions, point_walls, room_directions
from stages.semantics.segment import segment, triangles
from tests.stages.test_semantics import Y, _look, _quad, _views_capture, subdivided
from tests.stages.test_semantics_floorfree import _rays, box_mesh

LX, NORTH = 6.0, 3.0  # the counters run along x in [0, LX]; the wall stands at y = NORTH
STRIP = (0.9, 1.5)  # the wall's readings: z from the north counter's top up to 1.5 m
BOXES = [
    ((0.0, 2.5, 0.45), (LX, NORTH, 0.9)),  # the north counter
    ((0.0, -0.5, 0.45), (LX, 0.0, 0.9)),  # the south counter
    ((0.0, NORTH - 0.02, STRIP[0]), (LX, NORTH, STRIP[1])),  # the strip of wall (2 cm thick)
]
INTR = Intrinsics(24.0, 24.0, 23.5, 17.5, 48, 36)
VIEWS = [
    _look((2.0, 1.2, 1.4), (2.0, 2.2, 0.0)),  # down onto the floor and the north counter
    _look((3.0, 0.8, 1.4), (3.0, NORTH, 0.9)),  # at the wall: the strip and above it
    _look((4.5, 1.0, 1.45), (5.0, NORTH, 1.2)),  # the same, from the east
    _look((0.5, 1.25, 1.5), (4.0, 1.25, 0.0)),  # along the room
]


def _scene(tmp_path) -> SemanticsInputs:
    """The mesh, VIEWS, and their depth ray-cast from it as the evidence (its frames.json)."""
    mesh = box_mesh(BOXES, tmp_path / "mesh.ply")
    _views_capture(tmp_path, VIEWS, INTR)
    cap = Capture.load(tmp_path / "frames.json")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    seen = tmp_path / "seen"
    seen.mkdir()
    frames = []
    for f in cap.frames:
        t = scene.cast_rays(o3d.core.Tensor(_rays(f).astype(np.float32)))["t_hit"].numpy()
        write_depth_npy(seen / f"{f.stem}.npy", np.where(np.isfinite(t), t, 0.0))
        frames.append(Frame(f.stem, f.image, f.intrinsics, seen / f"{f.stem}.npy", None, f.pose))
    Capture(tmp_path, tuple(frames)).save(seen / "frames.json")
    return SemanticsInputs(tmp_path / "frames.json", tmp_path / "mesh.ply", (seen / "frames.json",))


def _run(inputs: SemanticsInputs, out, cfg: SemanticsConfig) -> tuple[Capture, dict]:
    out.mkdir()
    outs = IMPLS["geometry"](cfg, inputs, out)
    return Capture.load(outs.frames), json.loads(outs.stats.read_text())


def test_a_plain_wall_is_found_in_the_readings_and_filled_over_its_holes(tmp_path):
    inputs = _scene(tmp_path)
    plain, before = _run(inputs, tmp_path / "plain", SemanticsConfig())
    cap, stats = _run(
        inputs, tmp_path / "walls", SemanticsConfig(point_walls=PointWallsConfig(enabled=True))
    )
    assert before["planes"]["wall"] == 0  # the strip is 0.6 m tall: no wall of the mesh
    assert stats["point_walls"] == 1 and stats["planes"]["wall"] == 1
    (wall,) = [p for p in stats["plane_list"] if p["kind"] == "wall"]
    assert wall["normal"] == pytest.approx([0.0, -1.0, 0.0], abs=0.02)  # facing the room
    assert wall["d"] == pytest.approx(NORTH - 0.02, abs=0.02)  # -y + d = 0 on the plane
    assert stats["objects"] == before["objects"] == 2  # the counters
    over = 0
    for f, f0 in zip(cap.frames, plain.frames, strict=True):
        got, was = read_label(f.label), read_label(f0.label)
        assert not (read_label(f0.label) == WALL).any()
        r = _rays(f)
        at = r[..., :3] + np.load(f.depth)[..., None] * r[..., 3:]  # [H, W, 3]
        wall_px = got == WALL
        # every wall pixel lies on the wall's plane (mesh triangles within point_walls.dist
        # joined it: the counter top's back edge), from the floor up to its top
        np.testing.assert_allclose(at[wall_px][:, 1], NORTH - 0.02, atol=0.06)
        top = max(STRIP[1], SemanticsConfig().planes.ceiling_min_z)
        assert (at[wall_px][:, 2] <= top + 0.05).all()
        # the strip's pixels (within the readings' span along it: these small views read
        # every other pixel, and its ends only at grazing angles) become wall
        strip = np.abs(at[..., 1] - (NORTH - 0.02)) < 0.01
        strip &= (at[..., 2] > STRIP[0] + 0.03) & (at[..., 2] < STRIP[1] - 0.03)
        strip &= (at[..., 0] > 1.0) & (at[..., 0] < LX - 1.0)
        assert wall_px[strip].all() and not (was[strip] == WALL).any()
        over += int((wall_px & (at[..., 2] > STRIP[1] + 0.03)).sum())
        # the counters' fronts and tops keep their class: they are no wall
        counter = (at[..., 2] < STRIP[0] - 0.01) & (got != WALL)
        assert ((got == OBJECT) == (was == OBJECT))[counter].all()
        assert ((was == OBJECT) & (at[..., 2] < STRIP[0] - 0.01) & ~counter).sum() == 0
    assert over > 100  # the plain wall above the strip, which no surface holds


def test_the_outermost_plane_with_nothing_beyond_it_is_the_wall():
    rng = np.random.default_rng(0)
    u = rng.uniform(0.0, 4.0, 4000)
    z = rng.uniform(0.2, 1.2, 4000)
    wall = np.stack([u, np.full_like(u, 3.0), z], 1)  # y = 3: the wall
    front = np.stack([u, np.full_like(u, 2.4), z * 0.6], 1)  # y = 2.4: a cabinet front
    top = np.stack([u, rng.uniform(2.4, 3.0, 4000), np.full_like(u, 0.75)], 1)  # its top
    noise = np.stack([u[:200], rng.uniform(3.05, 3.5, 200), z[:200]], 1)  # seen past it
    pts = np.concatenate([wall, front, top, noise])
    cams = np.array([[2.0, 1.0, 1.4], [1.0, 1.5, 1.4]])
    dirs = room_directions(pts, 0.05)
    np.testing.assert_allclose(dirs[:2, :2], np.eye(2), atol=0.005)  # on x and y (0.3 deg)
    opt = PointWallOptions(0.05, 1.0, 0.5, 0.5, 0.2, 1.9)
    (w,) = point_walls(pts, cams, dirs, 0.0, opt)  # the fronts are too low, the ends bare
    assert w["normal"] == pytest.approx([0.0, -1.0, 0.0], abs=0.02)  # turned 1 deg at most
    y_mid = -(w["d"] + 2.0 * w["normal"][0]) / w["normal"][1]  # the plane at x = 2
    assert y_mid == pytest.approx(3.0, abs=0.02)
    assert w["box"][1] == 0.0 and w["box"][3] == pytest.approx(1.9)  # from the floor up
    # without the wall, the cabinet front (0.72 m of readings) is no wall: its top lies beyond
    bare = point_walls(np.concatenate([front, top]), cams, dirs, 0.0, opt)
    assert not [w for w in bare if w["normal"][1] < -0.9]


def test_the_room_directions_are_found_in_the_readings_of_a_turned_room():
    """The turn at which the readings' offsets pile up: a room turned by 12 degrees about z
    (walls and a cabinet front, with clutter at other angles) gives its walls' directions."""
    rng = np.random.default_rng(1)
    u, z = rng.uniform(0.0, 4.0, 3000), rng.uniform(0.0, 2.0, 3000)
    parts = [
        np.stack([u, np.full_like(u, 3.0), z], 1),  # north wall
        np.stack([np.full_like(u, 4.0), u * 0.75, z], 1),  # east wall
        np.stack([u[:1000], np.full(1000, 2.4), z[:1000] * 0.4], 1),  # a front
        rng.uniform([0, 0, 0], [4, 3, 1], (1500, 3)),  # clutter
    ]
    a = np.radians(12.0)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    dirs = room_directions(np.concatenate(parts) @ turn.T, 0.05)
    got = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0])) % 90.0  # [4] the same turn, mod 90
    np.testing.assert_allclose(got, 12.0, atol=0.2)


def test_a_wall_whose_readings_scatter_with_their_range_stands_amid_them():
    """Depth from photos errs in proportion to the range: a plain wall 2.5-3 m from the
    cameras, read with a 3 % error along each ray (~8 cm, as the 7-Scenes kitchen's wall
    behind its counters), puts a quarter of its readings more than `dist` past its plane.
    By dist alone they saw through it, and the wall found is the plane at its noise's far
    side (6 cm out); past dist + beyond_rel x range they are its noise, and the wall stands
    amid its readings. A cabinet front with its top reaching 0.6 m behind it stays no wall."""
    rng = np.random.default_rng(2)
    n = 6000
    cams = np.array([[1.0, 0.3, 1.4], [3.0, 0.3, 1.4]])
    eye = cams[rng.integers(0, 2, n)]  # [N, 3] the camera of each reading
    on = np.stack([rng.uniform(0.0, 4.0, n), np.full(n, 3.0), rng.uniform(0.2, 1.4, n)], 1)
    ray = on - eye
    rng_m = np.linalg.norm(ray, axis=1)
    wall = on + ray / rng_m[:, None] * (0.03 * rng_m * rng.standard_normal(n))[:, None]
    dirs = room_directions(wall, 0.05)

    def north(pts: np.ndarray, eyes: np.ndarray, rel: float) -> list[float]:
        opt = PointWallOptions(0.05, 1.0, 0.5, 0.5, 0.2, 1.9, beyond_rel=rel)
        got = point_walls(pts, cams, dirs, 0.0, opt, eyes)
        return [-w["d"] / w["normal"][1] for w in got if w["normal"][1] < -0.9]

    (plain,) = north(wall, eye, 0.0)
    (noisy,) = north(wall, eye, 0.03)
    assert plain > 3.04
    assert noisy == pytest.approx(3.0, abs=0.015)
    # a cabinet front at y = 2.4 and its top out to y = 3.0 (no wall seen): still no wall
    u = rng.uniform(0.0, 4.0, n)
    front = np.stack([u, np.full(n, 2.4), rng.uniform(0.0, 0.72, n)], 1)
    top = np.stack([u, rng.uniform(2.4, 3.0, n), np.full(n, 0.75)], 1)
    assert not north(np.concatenate([front, top]), np.concatenate([eye, eye]), 0.03)


def test_a_board_before_a_wall_the_points_hold_is_no_wall():
    # the mesh holds the floor, a board 2.6 m long from the floor to 1.9 m standing 0.25 m
    # before the north wall, and only a 0.3 m strip of that wall (too little for a wall plane
    # of the mesh), as photos give of a plain wall with a whiteboard before it; the views'
    # points hold the wall (more_walls). The board passes the wall bounds, but the wall
    # behind it is the room's: the plan's wall is the points' at y = Y, and the board is no
    # wall. A mesh plane within the point wall's dist of it is that wall's own surface
    yb = Y - 0.25
    parts = [
        _quad([(0, 0, 0), (4, 0, 0), (4, Y, 0), (0, Y, 0)], (0, 0, 1)),
        _quad([(0.7, yb, 0), (3.3, yb, 0), (3.3, yb, 1.9), (0.7, yb, 1.9)], (0, -1, 0)),
        _quad([(0, Y, 2.0), (4, Y, 2.0), (4, Y, 2.3), (0, Y, 2.3)], (0, -1, 0)),
    ]
    verts, tris = subdivided(parts)
    c, _, _ = triangles(verts, tris)
    board = np.abs(c[:, 1] - yb) < 1e-6

    def wall_at(y: float) -> dict:
        return {"kind": "wall", "normal": [0.0, -1.0, 0.0], "d": y, "area_m2": 9.2,
                "triangles": 0, "box": [0.0, 0.0, 4.0, 2.3], "span": [3.6, 2.1],
                "source": "points", "dist": 0.05}  # fmt: skip

    def walls(seg) -> list[float]:
        return sorted(-p["d"] * np.sign(p["normal"][1]) for p in seg.planes if p["kind"] == "wall")

    seg = segment(verts, tris, SemanticsConfig(), lambda *_: [wall_at(Y)])
    assert walls(seg) == pytest.approx([Y], abs=0.01)
    assert not (seg.cls[board] == WALL).any()
    assert sum(bool(r.get("front")) for r in seg.rejected) == 1  # the board: a front
    # without the points' wall the board is the wall; with it 3 cm behind the board (within
    # its dist) the board is that wall's surface and the points' wall is dropped as the same
    for more, want in ((None, [yb]), (lambda *_: [wall_at(yb + 0.03)], [yb])):
        seg = segment(verts, tris, SemanticsConfig(), more)
        assert walls(seg) == pytest.approx(want, abs=0.01)
        assert (seg.cls[board] == WALL).mean() > 0.9

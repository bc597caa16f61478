"""Align stage: the synthetic room of exact_room moved by a known rigid motion comes back
with its floor at z = 0 and up = +z; and the 7-Scenes kitchen, with and without gravity."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from stages.align import IMPLS, AlignConfig, AlignInputs
from stages.align.config import AlignOutputs
from stages.align.planes import angle_deg, find_floor, rotation_between
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from tests.conftest import shared_capture
from tests.stages.exact_room import room_capture

CFG = AlignConfig(stride=2)  # 64x48 views: every other pixel, all 8 frames
UP = np.array([0.0, 0.0, 1.0])
FLOOR_CORNERS = np.array([[0, 0, 0, 1], [4, 0, 0, 1], [4, 3, 0, 1], [0, 3, 0, 1]], float)


def motion() -> np.ndarray:
    """A known world motion [4, 4]: 25 degrees about (1, 2, 0.5), then 1.2 m up and aside."""
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    M = np.eye(4)
    M[:3, :3] = o3d.geometry.get_rotation_matrix_from_axis_angle(axis * np.radians(25.0))
    M[:3, 3] = (0.3, -0.2, 1.2)
    return M


def moved_room(tmp_path, with_gravity: bool):
    M = motion()
    g = tuple(M[:3, :3] @ [0.0, 0.0, -1.0]) if with_gravity else None
    return room_capture(tmp_path / "cap", ceiling=True, gravity=g, transform=M), M


def align(impl: str, frames, out, cfg: AlignConfig = CFG) -> tuple[AlignOutputs, dict]:
    out.mkdir()
    outs = IMPLS[impl](cfg, AlignInputs(frames), out)
    return outs, json.loads(outs.align.read_text())


def check_aligned(T: np.ndarray, M: np.ndarray) -> None:
    """T @ M maps the true world (floor z = 0, z up) to the aligned one: it must keep z."""
    A = T @ M
    assert angle_deg(A[:3, :3] @ UP, UP) < 0.5
    # the floor's corners, 2.5 m apart, land on z = 0 (which also bounds the tilt)
    np.testing.assert_allclose((FLOOR_CORNERS @ A.T)[:, 2], 0.0, atol=0.01)


@pytest.mark.parametrize("impl", ["gravity", "auto"])
def test_gravity_puts_floor_at_zero(tmp_path, impl):
    frames, M = moved_room(tmp_path, with_gravity=True)
    outs, info = align(impl, frames, tmp_path / "out")
    T = np.array(info["T"])
    assert info["method"] == "gravity" and info["up_from"] == "gravity"
    check_aligned(T, M)
    # T = [R | -floor_z e_z]: the shift is minus the floor height found after the rotation
    assert T[2, 3] == pytest.approx(-info["floor_z_before"])
    before, after = Capture.load(frames), Capture.load(outs.frames)
    for f0, f1 in zip(before.frames, after.frames, strict=True):
        np.testing.assert_allclose(f1.pose, T @ f0.pose, atol=1e-9)
    np.testing.assert_allclose(after.gravity, [0.0, 0.0, -1.0], atol=1e-9)
    if impl == "auto":
        assert info["notes"].startswith("auto: the capture gives gravity")


@pytest.mark.parametrize("impl", ["floor", "auto"])
def test_floor_plane_without_gravity(tmp_path, impl):
    frames, M = moved_room(tmp_path, with_gravity=False)
    outs, info = align(impl, frames, tmp_path / "out")
    assert info["method"] == "floor" and info["up_from"] == "floor"
    # the cameras' mean up leans from the true up: the floor impl could not just take it
    assert info["cameras_up_deg"] > 5.0
    check_aligned(np.array(info["T"]), M)
    assert Capture.load(outs.frames).gravity is None


def test_none_is_identity(tmp_path):
    frames, _ = moved_room(tmp_path, with_gravity=True)
    outs, info = align("none", frames, tmp_path / "out")
    assert info["method"] == "none"
    np.testing.assert_array_equal(info["T"], np.eye(4))
    for f0, f1 in zip(Capture.load(frames).frames, Capture.load(outs.frames).frames, strict=True):
        np.testing.assert_array_equal(f0.pose, f1.pose)


def test_no_depth_and_no_gravity_are_errors(tmp_path):
    frames, _ = moved_room(tmp_path, with_gravity=False)
    cap = Capture.load(frames)
    nodepth = [Frame(f.stem, f.image, f.intrinsics, pose=f.pose) for f in cap.frames]
    cap.with_frames(nodepth).save(tmp_path / "nodepth.json")
    with pytest.raises(BlunfError, match="no depth to find the floor.*align.impl=none"):
        align("floor", tmp_path / "nodepth.json", tmp_path / "o1")
    with pytest.raises(BlunfError, match="no gravity vector"):
        align("gravity", frames, tmp_path / "o2")


def test_rotation_between_is_minimal():
    a, b = np.array([0.0, 0.6, -0.8]), np.array([0.0, 0.0, -1.0])
    R = rotation_between(a, b)
    np.testing.assert_allclose(R @ a, b, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # minimal: it turns about a x b = +x only, by the angle between them (acos 0.8),
    # so the x axis (the "yaw" left free by a and b) is kept
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], atol=1e-12)
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(np.degrees(np.arccos(0.8)))
    # opposite directions: a half turn
    np.testing.assert_allclose(rotation_between(b, -b) @ b, -b, atol=1e-12)


def test_floor_is_the_lowest_large_horizontal_plane():
    """Horizontal points: floor at z = -0.30 (10 %), a counter top at 0.60 (60 %), a ceiling
    at 2.2 above the cameras (30 %); plus 200 scattered points below the floor. The floor is
    the lowest height holding >= 5 % of the horizontal points below the cameras: -0.30."""
    rng = np.random.default_rng(0)

    def plane(n, z):
        return np.c_[rng.uniform(0, 3, (n, 2)), np.full(n, z)]

    pts = np.concatenate([plane(1000, -0.3), plane(6000, 0.6), plane(3000, 2.2), plane(200, 0.0)])
    pts[-200:, 2] = rng.uniform(-2.0, -0.4, 200)  # noise below the floor, spread out
    normals = np.tile(UP, (len(pts), 1))
    fl = find_floor(pts, normals, np.array([1.2, 1.3]), AlignConfig())
    assert fl.z == pytest.approx(-0.3, abs=1e-9)
    np.testing.assert_allclose(fl.normal, UP, atol=1e-9)
    assert fl.inlier_fraction == pytest.approx(1000 / 10200, abs=0.005)
    assert fl.note == ""


def test_floor_alone_thinner_than_a_bin():
    """Only a floor, flat to 1 mm (all heights in one 2 cm bin): it is the floor. (Fewer than
    3 bins once made the 3-bin sum longer than the histogram and the floor was lost.)"""
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(0, 3, (500, 2)), rng.uniform(0.4, 0.401, 500)]
    fl = find_floor(pts, np.tile(UP, (500, 1)), np.array([1.5]), AlignConfig())
    assert fl.z == pytest.approx(0.4005, abs=0.001) and fl.note == ""
    assert fl.inlier_fraction == 1.0


def _sparse_kitchen(rng: np.random.Generator, floor_n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse (SfM-like) points of a kitchen, z up, floor at z = 0: `floor_n` floor points
    (+-1 cm) whose normals lie flat (a textureless floor: too few neighbours for a normal), 1500
    counter-top points at 0.9 m facing up, 400 cabinet-front points (0.05-0.85 m) and 600 wall
    points (0-2.5 m) facing sideways. Returns points [N, 3] and normals [N, 3]."""
    side = np.array([1.0, 0.0, 0.0])
    floor = np.c_[rng.uniform(0, 3, (floor_n, 2)), rng.normal(0.0, 0.01, floor_n)]
    counter = np.c_[
        rng.uniform(0, 3, 1500), rng.uniform(2, 2.6, 1500), rng.normal(0.9, 0.003, 1500)
    ]
    fronts = np.c_[rng.uniform(0, 3, 400), np.full(400, 2.0), rng.uniform(0.05, 0.85, 400)]
    walls = np.c_[np.zeros(600), rng.uniform(0, 3, 600), rng.uniform(0, 2.5, 600)]
    pts = np.concatenate([floor, counter, fronts, walls])
    normals = np.concatenate(
        [np.tile(side, (floor_n, 1)), np.tile(UP, (1500, 1)), np.tile(side, (1000, 1))]
    )
    return pts, normals


def test_sparse_floor_under_counter_tops():
    """Photos only (sparse points): 60 floor points (2 %) without an up-facing normal under
    1500 up-facing counter-top points. The horizontal plane alone is the counter top (0.9 m;
    what dense depth keeps); 13 % of the points below the cameras lie under it, so with
    sparse points the floor is where the lowest points pile up: z = 0."""
    pts, normals = _sparse_kitchen(np.random.default_rng(2), 60)
    cam_z = np.array([1.35, 1.4, 1.45])
    dense = find_floor(pts, normals, cam_z, AlignConfig())
    assert dense.z == pytest.approx(0.9, abs=0.02) and dense.note == ""
    fl = find_floor(pts, normals, cam_z, AlignConfig(), sparse=True)
    assert fl.z == pytest.approx(0.0, abs=0.03)
    assert "under the horizontal plane at 0.90 m" in fl.note


def test_sparse_true_floor_is_kept():
    """Sparse points whose floor faces up (and piles up): the floor plane stands, no note,
    even with 1 % of stray points scattered below it."""
    rng = np.random.default_rng(3)
    pts, normals = _sparse_kitchen(rng, 800)
    normals[:800] = UP
    stray = np.c_[rng.uniform(0, 3, (30, 2)), rng.uniform(-1.0, -0.1, 30)]
    pts = np.concatenate([pts, stray])
    normals = np.concatenate([normals, np.tile(UP, (30, 1))])
    fl = find_floor(pts, normals, np.array([1.4]), AlignConfig(), sparse=True)
    assert fl.z == pytest.approx(0.0, abs=0.01) and fl.note == ""


@pytest.mark.slow
def test_kitchen_gravity_and_floor_agree(tmp_path):
    """7-Scenes redkitchen: the floor is a small part of views of counters. Gravity and the
    floor plane must give the same up (within 3 degrees: the data's floor leans ~2 degrees
    from its gravity vector) and camera heights of a hand-held Kinect (1-2 m)."""
    src = shared_capture("7scenes-redkitchen")
    from stages.ingest import load

    cap = load(src, tmp_path / "work", "7scenes")
    cap.save(tmp_path / "frames.json")
    Ts = {}
    for impl in ("gravity", "floor"):
        _, info = align(impl, tmp_path / "frames.json", tmp_path / impl, AlignConfig())
        assert info["method"] == impl and info["notes"] == ""
        assert info["inlier_fraction"] > 0.01
        Ts[impl] = np.array(info["T"])
    assert angle_deg(Ts["gravity"][2, :3], Ts["floor"][2, :3]) < 3.0
    c = np.c_[cap.poses()[:, :3, 3], np.ones(len(cap.frames))]  # [C, 4]
    zg, zf = (c @ Ts["gravity"].T)[:, 2], (c @ Ts["floor"].T)[:, 2]
    assert 1.0 < np.median(zg) < 2.0
    assert np.abs(zg - zf).max() < 0.10


def _walls_only(folder, M: np.ndarray) -> Path:
    """The exact room seen with depth on its walls alone, 1 m above the floor and up (the
    floor, the counter and the walls' feet read as nothing, as SfM leaves a plain floor and
    counter), the world moved by M."""
    from stages.common.camera import pixel_grid, unproject
    from stages.common.io import write_depth_png, write_image
    from tests.stages.exact_room import INTR, make_scene, render, room_poses

    scene = make_scene()
    folder.mkdir(parents=True)
    frames = []
    for i, pose in enumerate(room_poses()):
        depth, normals = render(scene, pose)
        uv = pixel_grid(*depth.shape[::-1]).reshape(-1, 2)
        height = unproject(uv, depth.reshape(-1), INTR.K, pose)[:, 2].reshape(depth.shape)
        depth = np.where((np.abs(normals[..., 2]) < 0.5) & (height > 1.0), depth, 0.0)
        stem = f"v{i:02d}"
        write_image(folder / f"{stem}.png", np.full((*depth.shape, 3), 128, np.uint8))
        write_depth_png(folder / f"{stem}.png.depth.png", depth)
        frames.append(
            Frame(
                stem,
                folder / f"{stem}.png",
                INTR,
                depth=folder / f"{stem}.png.depth.png",
                pose=M @ pose,
            )
        )
    Capture(folder, tuple(frames)).save(folder / "frames.json")
    return folder / "frames.json"


def test_level_up_is_square_to_the_x_axes_of_level_cameras():
    from stages.align.planes import level_up
    from tests.stages.exact_room import look_at

    M = motion()
    rng = np.random.default_rng(0)
    yaw = np.radians(np.linspace(0, 120, 12))
    poses = [
        M @ look_at((0, 0, 1.5), (np.cos(a), np.sin(a), 1.5 - rng.uniform(0.0, 0.8))) for a in yaw
    ]
    up, facts = level_up(np.stack(poses), 1.0)
    # pitched 0-39 degrees down, rolled not at all: the x axes give the moved world's up
    assert angle_deg(up, M[:3, :3] @ UP) < 1e-6 and facts["level_roll_deg"] < 1e-6
    assert facts["level_turn_deg"] > 20
    # rolled 3 degrees RMS (a hand-held capture): not level, no up
    rolled = []
    for p in poses:
        a = np.radians(rng.normal(0.0, 3.0))
        r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        q = p.copy()
        q[:3, :3] = p[:3, :3] @ r  # about the optical axis
        rolled.append(q)
    up, facts = level_up(np.stack(rolled), 1.0)
    assert up is None and facts["level_roll_deg"] > 1.0
    # every camera facing one way: the up is free about their x axis
    up, facts = level_up(np.stack([poses[0]] * 5), 1.0)
    assert up is None and facts["level_turn_deg"] < 1
    # 0 turns it off
    assert level_up(np.stack(poses), 0.0)[0] is None


def test_floor_impl_takes_the_level_cameras_up_when_no_floor_can_be_fitted(tmp_path):
    M = motion()
    frames = _walls_only(tmp_path / "cap", M)
    _, info = align("floor", frames, tmp_path / "out")
    # no floor under the normals' up: the level cameras' up, kept as it is (the band's
    # lower edge has a few up-facing normals, and a plane fitted to them leans 0.8 degrees)
    assert info["up_from"] == "level cameras"
    assert "cameras are level (RMS roll 0.00 deg)" in info["notes"]
    assert info["level_roll_deg"] < 1e-3 and info["level_turn_deg"] > 20
    assert angle_deg((np.array(info["T"]) @ M)[:3, :3] @ UP, UP) < 0.01
    # without the cue the up is the cameras' mean up axis, which their pitch tilts
    _, off = align("floor", frames, tmp_path / "off", AlignConfig(stride=2, level_roll_deg=0))
    assert "level" not in off["notes"]
    assert angle_deg((np.array(off["T"]) @ M)[:3, :3] @ UP, UP) > 5.0

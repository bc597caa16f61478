"""Manhattan yaw of the align stage: the room of exact_room (walls on x and y) turned about z
by a known angle comes back with its walls on the axes, by the smallest turn; a square room
is kept; a floor without walls keeps its yaw and says why."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import open3d.core as o3c
import pytest
from scipy import ndimage

from stages.align import IMPLS, AlignConfig, AlignInputs
from stages.align.manhattan import MIN_EDGE_VOTES, MIN_NORMALS, find_yaw, heading_turn, rot_z
from stages.common.camera import pixel_grid
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import write_depth_png, write_image
from tests.stages.exact_room import INTR, make_scene, render, room_capture, room_poses
from tests.stages.test_align import align, motion


def turned(deg: float, tilt: bool = False) -> np.ndarray:
    """World motion [4, 4]: `deg` about z, moved 0.4 m aside and 1.1 m up; then, with `tilt`,
    test_align's 25-degree tilt (so up and yaw are both unknown)."""
    M = np.eye(4)
    M[:3, :3] = rot_z(deg)
    M[:3, 3] = (0.4, -0.3, 1.1)
    return motion() @ M if tilt else M


def rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Angle of the rotation between two [3, 3] rotations, degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1.0) / 2.0, -1.0, 1.0))))


@pytest.mark.parametrize(
    "impl, deg, tilt, k",
    [
        # 17 deg: the smallest turn back is -17 deg; the walls land where they were (k = 0)
        ("floor", 17.0, False, 0),
        # 60 deg = 90 - 30: the smallest turn is +30 deg, so the world ends a quarter turn
        # from the truth (k = 1): the x walls now run along y, still on the axes
        ("floor", 60.0, False, 1),
        # -50 deg: +50 or -40; -40 is smaller, ending at -90 deg (k = -1)
        ("floor", -50.0, False, -1),
        # gravity gives up, the normals give the yaw; with the 25-degree tilt on top
        ("gravity", 17.0, True, 0),
        ("floor", 60.0, True, 1),
    ],
)
def test_turned_room_comes_back_square(tmp_path, impl, deg, tilt, k):
    M = turned(deg, tilt)
    g = tuple(M[:3, :3] @ [0.0, 0.0, -1.0]) if impl == "gravity" else None
    frames = room_capture(tmp_path / "cap", ceiling=True, gravity=g, transform=M)
    _, info = align(impl, frames, tmp_path / "out")
    A = np.array(info["T"]) @ M  # true world -> aligned world
    # exact depth but for the millimetre steps of the PNG: measured 0.004 deg
    assert rot_err_deg(A[:3, :3], rot_z(90.0 * k)) < 0.05
    assert info["manhattan_confidence"] > 0.9  # only axis-aligned boxes in this room
    assert info["wall_normals"] > MIN_NORMALS
    if not tilt:  # the up step is exact here, so the recorded yaw is the whole turn back
        assert info["yaw_deg"] == pytest.approx(90.0 * k - deg, abs=0.05)
    assert -45.0 <= info["yaw_deg"] < 45.0


@pytest.mark.parametrize("impl", ["floor", "gravity"])
def test_square_room_is_kept(tmp_path, impl):
    """Walls already on the axes: the yaw is 0 (only the millimetre depth steps blur the
    normals, symmetrically), so T is the identity up to the floor shift."""
    g = (0.0, 0.0, -1.0) if impl == "gravity" else None
    frames = room_capture(tmp_path / "cap", ceiling=True, gravity=g)
    _, info = align(impl, frames, tmp_path / "out")
    assert abs(info["yaw_deg"]) < 0.05
    assert rot_err_deg(np.array(info["T"])[:3, :3], np.eye(3)) < 0.05
    assert info["notes"] == ""


def test_manhattan_off_keeps_the_yaw(tmp_path):
    M = turned(17.0)
    frames = room_capture(tmp_path / "cap", ceiling=True, transform=M)
    _, info = align("floor", frames, tmp_path / "out", AlignConfig(stride=2, manhattan=False))
    A = np.array(info["T"]) @ M
    assert rot_err_deg(A[:3, :3], rot_z(17.0)) < 0.05  # only the (exact) floor step ran
    assert info["yaw_deg"] == 0.0 and info["manhattan_confidence"] is None


def test_floor_without_walls_keeps_the_yaw(tmp_path):
    """Only a 20 x 20 m floor: every normal is vertical, no wall direction exists."""
    scene = o3d.t.geometry.RaycastingScene()
    v = np.array([[-8, -8, 0], [12, -8, 0], [12, 12, 0], [-8, 12, 0]], np.float32)
    scene.add_triangles(o3c.Tensor(v), o3c.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.uint32)))
    M = turned(17.0)
    folder = tmp_path / "cap"
    folder.mkdir()
    frames = []
    for i, pose in enumerate(room_poses()):
        depth, _ = render(scene, pose)
        write_depth_png(folder / f"v{i}.png", depth)
        frames.append(
            Frame(f"v{i}", folder / f"v{i}.png", INTR, depth=folder / f"v{i}.png", pose=M @ pose)
        )
    Capture(folder, tuple(frames)).save(folder / "frames.json")
    _, info = align("floor", folder / "frames.json", tmp_path / "out")
    A = np.array(info["T"]) @ M
    assert rot_err_deg(A[:3, :3], rot_z(17.0)) < 0.05  # up fixed, yaw as it came
    assert info["yaw_deg"] == 0.0 and info["wall_normals"] < MIN_NORMALS
    assert "no walls seen; yaw kept" in info["notes"]
    np.testing.assert_allclose((np.array([[0.0, 0, 0, 1], [5, 5, 0, 1]]) @ A.T)[:, 2], 0, atol=0.01)


@pytest.mark.parametrize("impl", ["floor", "gravity"])
def test_free_yaw_gives_one_frame_whatever_the_input_turn(tmp_path, impl):
    # SfM's world differs by a turn about z from run to run: with free_yaw every input turn
    # comes out in the same frame (the first camera looks within 45 deg of +y), where the
    # smallest turn to the walls alone leaves some a quarter turn apart
    plain, free = [], []
    for deg in (17.0, 60.0, -50.0, 170.0):
        M = turned(deg)
        g = tuple(M[:3, :3] @ [0.0, 0.0, -1.0]) if impl == "gravity" else None
        frames = room_capture(tmp_path / f"cap{deg}", ceiling=True, gravity=g, transform=M)
        for flag, got in ((False, plain), (True, free)):
            out = tmp_path / f"out{deg}{flag}"
            out.mkdir()
            outs = IMPLS[impl](AlignConfig(stride=2), AlignInputs(frames, free_yaw=flag), out)
            info = json.loads(outs.align.read_text())
            got.append((np.array(info["T"]) @ M)[:3, :3])  # true world -> aligned world
            if flag:
                assert info["squared"] and info["heading_turn_deg"] in (0.0, 90.0, 180.0, 270.0)
    assert max(rot_err_deg(a, plain[0]) for a in plain) > 89.0  # quarter turns apart
    for a in free:
        assert rot_err_deg(a, free[0]) < 0.05
        # still square: the turn from the true world is a multiple of 90 degrees
        k = round(float(np.degrees(np.arctan2(a[1, 0], a[0, 0]))) / 90.0)
        assert rot_err_deg(a, rot_z(90.0 * k)) < 0.05


def test_heading_turn_by_hand():
    # a camera looking along +x (optical axis = pose column 2): a quarter turn puts it on +y
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # x right = -y, z fwd = +x
    assert heading_turn(np.eye(3), pose, squared=True) == 90.0
    assert heading_turn(np.eye(3), pose, squared=False) == pytest.approx(90.0)
    # looking 30 deg off +y: squared keeps it (within 45 deg), not squared turns it exactly
    pose2 = np.eye(4)
    pose2[:3, :3] = rot_z(120.0) @ pose[:3, :3]  # optical axis at azimuth 120 deg
    assert heading_turn(np.eye(3), pose2, squared=True) == 0.0
    assert heading_turn(np.eye(3), pose2, squared=False) == pytest.approx(-30.0)
    # looking straight down: no heading
    down = np.eye(4)
    down[:3, :3] = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    assert heading_turn(np.eye(3), down, squared=True) is None


def azimuths(deg: np.ndarray) -> np.ndarray:
    """Horizontal unit normals [N, 3] at these azimuths (degrees)."""
    a = np.radians(deg)
    return np.c_[np.cos(a), np.sin(a), np.zeros_like(a)]


def test_find_yaw_takes_the_mode_not_the_mean():
    """600 wall normals at 17 + k 90 deg (both signs, 0.5 deg noise) and 400 furniture
    normals 20 deg off them. The plain mean of exp(4i theta) would be pulled by the furniture:
    atan2(0.4 sin 80, 0.6 + 0.4 cos 80) / 4 = 30.5 / 4 = 7.6 deg. The mode gives -17."""
    rng = np.random.default_rng(0)
    walls = 17.0 + 90.0 * rng.integers(0, 4, 600) + rng.normal(0, 0.5, 600)
    furniture = 37.0 + 90.0 * rng.integers(0, 4, 400) + rng.normal(0, 0.5, 400)
    n = azimuths(np.r_[walls, furniture])
    n[::3] *= -1  # normal signs are arbitrary
    y = find_yaw(n, AlignConfig())
    assert y.yaw_deg == pytest.approx(-17.0, abs=0.1)
    assert y.normals == 1000 and y.note == ""
    # the resultant length of 0.6 e^0 + 0.4 e^(i 80 deg) (noise shrinks it by ~0.1 %)
    assert y.confidence == pytest.approx(abs(0.6 + 0.4 * np.exp(1j * np.radians(80))), abs=0.02)


@pytest.mark.parametrize("theta, yaw", [(60.0, 30.0), (46.0, 44.0), (-44.0, 44.0), (0.0, 0.0)])
def test_find_yaw_folds_to_the_smallest_turn(theta, yaw):
    # walls at theta + k 90 deg; the turn of least magnitude putting them on the axes
    y = find_yaw(azimuths(theta + 90.0 * np.arange(200)), AlignConfig())
    assert y.yaw_deg == pytest.approx(yaw, abs=1e-9)


def test_find_yaw_without_a_dominant_direction():
    """Evenly spread azimuths (a round room): resultant ~0, below the 0.2 threshold; and
    vertical normals (floor, ceiling) or tilted ones (> max_tilt_deg = 15) are not walls."""
    cfg = AlignConfig()
    y = find_yaw(azimuths(np.linspace(0, 360, 1000, endpoint=False) + 0.3), cfg)
    assert y.yaw_deg is None and y.confidence < 1e-9
    assert "no dominant direction" in y.note
    tilted = azimuths(np.zeros(500)) * np.cos(np.radians(20)) + [0, 0, np.sin(np.radians(20))]
    y = find_yaw(np.r_[np.tile([0.0, 0.0, 1.0], (5000, 1)), tilted], cfg)
    assert y.yaw_deg is None and y.normals == 0 and "no walls seen" in y.note
    with pytest.raises(BlunfError, match="manhattan_min_confidence"):
        AlignConfig(manhattan_min_confidence=1.5)


def shaded_room(folder, M: np.ndarray, size=(320, 240), wall_depth: bool = False):
    """The room of exact_room turned by M, photographed at `size` with each face shaded by
    its normal (an edge at every crease, as a room's corners and counter edges are), and
    depth (320x240) on the floor alone unless `wall_depth`: walls blank to depth, as white
    walls are to SfM. Returns frames.json."""
    scene = make_scene(ceiling=True)
    folder.mkdir()

    def cast(pose: np.ndarray, wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """z-depth [H, W] (inf: no hit) and face normals [H, W, 3] at image size wh."""
        intr = INTR.scaled(*wh)
        uv = pixel_grid(*wh)  # [H, W, 2]
        ray = (
            np.stack(
                [
                    (uv[..., 0] - intr.cx) / intr.fx,
                    (uv[..., 1] - intr.cy) / intr.fy,
                    np.ones(uv.shape[:2]),
                ],
                axis=-1,
            )
            @ pose[:3, :3].T
        )  # camera z = 1: t is the z-depth
        ans = scene.cast_rays(
            o3c.Tensor(
                np.concatenate([np.broadcast_to(pose[:3, 3], ray.shape), ray], -1).astype(
                    np.float32
                )
            )
        )
        return ans["t_hit"].numpy(), ans["primitive_normals"].numpy()

    frames = []
    for i, pose in enumerate(room_poses()):
        t, n = cast(pose, size)
        grey = np.where(
            np.isfinite(t), 120 + 50 * n[..., 0] + 30 * n[..., 1] + 70 * np.abs(n[..., 2]), 0
        )
        write_image(
            folder / f"v{i}.png", np.repeat(grey.clip(0, 255).astype(np.uint8)[..., None], 3, 2)
        )
        t, n = cast(pose, (320, 240))
        keep = np.isfinite(t) & ((np.abs(n[..., 2]) > 0.9) | wall_depth)
        np.save(folder / f"v{i}.npy", np.where(keep, t, 0.0).astype(np.float32))
        frames.append(
            Frame(
                f"v{i}",
                folder / f"v{i}.png",
                INTR.scaled(*size),
                depth=folder / f"v{i}.npy",
                pose=M @ pose,
            )
        )
    Capture(folder, tuple(frames)).save(folder / "frames.json")
    return folder / "frames.json"


@pytest.mark.parametrize("size", [(320, 240), (1280, 960)])
def test_yaw_from_the_images_edges_when_the_walls_are_blank_to_depth(tmp_path, size):
    """Depth on the floor and the tops alone gives no wall normals: the normals keep the
    yaw, the edges of the photos find it (the room's horizontal creases: floor and ceiling
    lines, the counter's and the box's edges). 1280 px photos are read in 2 x 2 blocks."""
    M = turned(17.0)
    frames = shaded_room(tmp_path / "cap", M, size)
    got = {}
    for how in ("auto", "normals"):
        _, info = align("floor", frames, tmp_path / how, AlignConfig(stride=2, yaw_from=how))
        got[how] = (np.array(info["T"]) @ M)[:3, :3], info
    A, info = got["auto"]
    assert info["yaw_from"] == "lines" and info["squared"]
    assert info["normals_yaw_deg"] is None  # no wall normals: the normals alone keep the yaw
    assert rot_err_deg(A, rot_z(0.0)) < 0.1
    assert info["yaw_deg"] == pytest.approx(-17.0, abs=0.1)
    assert info["lines_confidence"] > 0.9 and info["edge_votes"] > MIN_EDGE_VOTES
    B, info = got["normals"]
    assert rot_err_deg(B, rot_z(17.0)) < 0.05 and not info["squared"]
    assert "lines_yaw_deg" not in info


def test_edges_without_a_direction_leave_the_yaw_to_the_normals(tmp_path):
    """Photos of noise (the procedural rooms' textures give edges every way), depth on the
    walls too, one reading in 25 (sparse, as SfM's tracks): the edges' resultant is below
    lines_min_confidence, so "auto" reads the walls' normals, and "lines" alone is an
    error naming the capture. With the depth dense, "auto" does not read the photos."""
    M = turned(17.0)
    frames = shaded_room(tmp_path / "cap", M, size=(160, 120), wall_depth=True)
    rng = np.random.default_rng(0)
    for f in Capture.load(frames).frames:
        blobs = ndimage.zoom(rng.uniform(0, 255, (30, 40)), 4, order=3).clip(0, 255)
        write_image(f.image, np.repeat(blobs.astype(np.uint8)[..., None], 3, 2))
    dense = AlignConfig(stride=2)
    _, info = align("floor", frames, tmp_path / "dense", dense)
    assert info["yaw_from"] == "normals" and "lines_confidence" not in info
    for f in Capture.load(frames).frames:
        d = np.load(f.depth)
        np.save(f.depth, np.where(rng.uniform(size=d.shape) < 0.04, d, 0.0).astype(np.float32))
    _, info = align("floor", frames, tmp_path / "auto", dense)
    A = np.array(info["T"]) @ M
    assert info["yaw_from"] == "normals" and info["lines_confidence"] < 0.2
    assert rot_err_deg(A[:3, :3], rot_z(0.0)) < 0.5
    with pytest.raises(BlunfError, match="yaw_from=lines.*show no room directions"):
        align("floor", frames, tmp_path / "lines", AlignConfig(stride=2, yaw_from="lines"))

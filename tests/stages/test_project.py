"""Π on hand-made views whose world points are worked out by hand."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stages.common.camera import Intrinsics, undistort_pixels
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import write_depth_png, write_image, write_label_png
from stages.common.points import read_bounds, read_grid, read_instances, read_points
from stages.project import IMPLS, ProjectConfig, ProjectInputs

# An 8x6 camera with fx = fy = 4, cx = 3.5, cy = 2.5 (principal point between the central
# pixels), 2 m above the floor at world (1, 2, 2), looking straight down. Its axes in the world:
# x_cam (right) = +x, z_cam (forward) = -z, y_cam (down) = z_cam x x_cam = -y (right-handed:
# x_cam x y_cam = (1,0,0) x (0,-1,0) = (0,0,-1) = z_cam). Image up is therefore north.
# With depth 2 m, pixel (u, v) lands at x = 1 + 2 (u - 3.5) / 4 = 1 + (u - 3.5) / 2 and
# y = 2 - (v - 2.5) / 2, z = 2 - 2 = 0: u = 0..7 gives x = -0.75 .. 2.75 and v = 0..5 gives
# y = 3.25 .. 0.75, both in steps of 0.5 m. That is the footprint.
INTR = Intrinsics(4.0, 4.0, 3.5, 2.5, 8, 6)
DOWN = np.array([[1, 0, 0, 1], [0, -1, 0, 2], [0, 0, -1, 2], [0, 0, 0, 1]], np.float64)


def _capture(
    tmp: Path,
    depth: np.ndarray,
    label: np.ndarray | None,
    pose=DOWN,
    n: int = 1,
    classes=None,
    ignore=(),
) -> Path:
    """Write n identical frames (image, depth, optional label) and their frames.json."""
    root = tmp / "cap"
    frames = []
    for i in range(n):
        for sub in ("images", "depth", "labels"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        img, dep = root / "images" / f"{i}.png", root / "depth" / f"{i}.png"
        write_image(img, np.zeros((6, 8, 3), np.uint8))
        write_depth_png(dep, depth)
        lab = None
        if label is not None:
            lab = root / "labels" / f"{i}.png"
            write_label_png(lab, label)
        frames.append(Frame(str(i), img, INTR, dep, lab, np.asarray(pose)))
    cap = Capture(root, tuple(frames), classes=classes or {}, ignore=tuple(ignore))
    cap.save(tmp / "frames.json")
    return tmp / "frames.json"


def _run(tmp: Path, frames: Path, **kw):
    out = tmp / "out"
    out.mkdir()
    outs = IMPLS["pinhole"](ProjectConfig(**kw), ProjectInputs(frames), out)
    return outs, out


def test_camera_looking_down_lands_every_pixel_on_the_floor_footprint(tmp_path):
    depth = np.full((6, 8), 2.0)
    depth[0, 0] = 0.0  # missing depth: dropped
    label = np.where(np.arange(8)[None, :] < 4, 1, 2).repeat(6, 0)  # west half 1, east half 2
    label[5, 7] = 255  # unknown: dropped
    label[5, 6] = 3  # ignored class: dropped
    frames = _capture(
        tmp_path, depth, label, n=2, classes={1: "floor", 2: "rug", 3: "ceiling"}, ignore=(3,)
    )
    outs, out = _run(tmp_path, frames, stride=1, cell=0.25, pad=0.1, bounds_pct=0.0)
    xyz, lab, view, classes = read_points(outs.points)
    # 48 pixels - 3 dropped = 45 per view, two views
    assert len(xyz) == 90 and xyz.dtype == np.float64 and lab.dtype == np.uint8
    np.testing.assert_array_equal(view, np.repeat([0, 1], 45))
    np.testing.assert_allclose(xyz[:, 2], 0.0, atol=1e-6)
    uu, vv = np.meshgrid(np.arange(8), np.arange(6))
    keep = np.ones((6, 8), bool)
    keep[0, 0] = keep[5, 7] = keep[5, 6] = False
    expect = np.stack([1 + (uu[keep] - 3.5) / 2, 2 - (vv[keep] - 2.5) / 2], -1)  # row-major
    np.testing.assert_allclose(xyz[:45, :2], expect, atol=1e-6)
    np.testing.assert_array_equal(lab[:45], np.where(expect[:, 0] < 1, 1, 2))
    # grid: bounds [-0.75, 2.75] x [0.75, 3.25] padded by 0.1 -> [-0.85, 2.85] x [0.65, 3.35];
    # origin floored to 0.25 m: (-1.0, 0.5); W = ceil(3.85 / 0.25) = 16, H = ceil(2.85 / 0.25) = 12
    grid = read_grid(outs.grid)
    assert grid.origin == (-1.0, 0.5) and grid.cell == 0.25 and grid.shape == (12, 16)
    assert classes == {1: "floor", 2: "rug"}  # the ignored class is not in the plan's table
    table = json.loads((out / "classes.json").read_text())
    assert table == {"classes": {"1": "floor", "2": "rug"}, "labelling": "labels"}
    stats = json.loads((out / "project.json").read_text())
    assert (stats["no_depth"], stats["dropped_label"], stats["points"]) == (2, 4, 90)


def test_points_carry_the_instance_of_their_pixel(tmp_path):
    depth = np.full((6, 8), 2.0)
    depth[0, 0] = 0.0  # missing depth: dropped with its instance
    label = np.ones((6, 8), np.uint8)
    label[5, 7] = 255  # unknown: dropped with its instance
    inst = (np.arange(48).reshape(6, 8) % 5).astype(np.uint16) * 300  # ids beyond uint8
    frames = _capture(tmp_path, depth, label, n=2, classes={1: "object"})
    cap = Capture.load(frames)
    (tmp_path / "cap" / "instances").mkdir()
    with_inst = []
    for f in cap.frames:
        path = tmp_path / "cap" / "instances" / f"{f.stem}.png"
        write_label_png(path, inst)
        with_inst.append(replace(f, instance=path))
    cap.with_frames(with_inst).save(frames)
    outs, out = _run(tmp_path, frames, stride=1, cell=0.25, occlusion="none")
    xyz, lab, view, _ = read_points(outs.points)
    got = read_instances(outs.points)
    keep = np.ones((6, 8), bool)
    keep[0, 0] = keep[5, 7] = False
    assert got.dtype == np.int32 and len(got) == len(lab) == 2 * 46
    np.testing.assert_array_equal(got, np.tile(inst[keep], 2))  # row-major per view
    assert json.loads((out / "project.json").read_text())["instances"] == 4  # 300 .. 1200
    # points written before points carried instances read as "no instance"
    with np.load(outs.points) as z:
        old = {k: z[k] for k in z.files if k != "instance"}
    np.savez(tmp_path / "old.npz", **old)
    np.testing.assert_array_equal(read_instances(tmp_path / "old.npz"), np.zeros(92, np.int32))
    assert len(read_points(tmp_path / "old.npz")[0]) == 92


def test_instance_map_size_mismatch_is_named(tmp_path):
    frames = _capture(tmp_path, np.full((6, 8), 2.0), np.ones((6, 8), np.uint8))
    cap = Capture.load(frames)
    bad = tmp_path / "cap" / "0-instances.png"
    write_label_png(bad, np.ones((6, 7), np.uint8))
    cap.with_frames([replace(cap.frames[0], instance=bad)]).save(frames)
    with pytest.raises(BlunfError, match=r"0-instances\.png: instance map is 7x6"):
        _run(tmp_path, frames, stride=1)


def test_stride_keeps_every_other_pixel_from_stride_half(tmp_path):
    frames = _capture(tmp_path, np.full((6, 8), 2.0), np.ones((6, 8), np.uint8))
    outs, _ = _run(tmp_path, frames, stride=2, cell=0.25, bounds_pct=0.0)
    xyz, _, _, _ = read_points(outs.points)
    # stride 2 samples u = 1, 3, 5, 7 and v = 1, 3, 5: x = -0.25, 0.75, 1.75, 2.75, y = 2.75,
    # 1.75, 0.75
    assert sorted(set(np.round(xyz[:, 0], 6))) == [-0.25, 0.75, 1.75, 2.75]
    assert sorted(set(np.round(xyz[:, 1], 6))) == [0.75, 1.75, 2.75]


def test_height_labelling_without_labels(tmp_path):
    depth = np.full((6, 8), 2.0)
    depth[:, 2:4] = 1.0  # z = 2 - 1 = 1.0 m: occupied
    depth[:, 4:5] = 0.5  # z = 1.5 m: above ceiling_cut 1.2, dropped
    depth[:, 5:6] = 1.97  # z = 0.03 m: below floor_band 0.05, floor
    frames = _capture(tmp_path, depth, None)
    outs, out = _run(tmp_path, frames, stride=1, cell=0.25, ceiling_cut=1.2)
    xyz, lab, _, classes = read_points(outs.points)
    assert classes == {0: "floor", 1: "occupied"}
    assert len(lab) == 48 - 6  # one column of 6 pixels dropped
    np.testing.assert_array_equal(lab, np.where(np.abs(xyz[:, 2] - 1.0) < 1e-6, 1, 0))
    assert int((lab == 1).sum()) == 12  # two columns of 6 pixels at z = 1
    assert json.loads((out / "classes.json").read_text())["labelling"] == "height"


def test_label_size_mismatch_is_named(tmp_path):
    frames = _capture(tmp_path, np.full((6, 8), 2.0), np.ones((5, 8), np.uint8))
    with pytest.raises(BlunfError, match=r"0\.png: label map is 8x5"):
        _run(tmp_path, frames, stride=1)


def test_no_surviving_point_is_an_error(tmp_path):
    frames = _capture(tmp_path, np.full((6, 8), 2.0), np.full((6, 8), 255, np.uint8))
    with pytest.raises(BlunfError, match="no labelled pixel with depth in"):
        _run(tmp_path, frames, stride=1)


def test_labelling_labels_without_labels_is_an_error(tmp_path):
    frames = _capture(tmp_path, np.full((6, 8), 2.0), None)
    with pytest.raises(BlunfError, match="has no label map"):
        _run(tmp_path, frames, labelling="labels")


def test_undistort_inverts_the_opencv_model():
    # forward OpenCV model on normalised points, then back: the ideal pixels come out again
    intr = Intrinsics(500.0, 480.0, 320.0, 240.0, 640, 480, (-0.2, 0.05, 0.001, -0.002, 0.01))
    k1, k2, p1, p2, k3 = intr.dist
    gx, gy = np.meshgrid(np.linspace(-0.5, 0.5, 7), np.linspace(-0.4, 0.4, 5))
    x, y = gx.ravel(), gy.ravel()
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    uv_d = np.stack([xd * intr.fx + intr.cx, yd * intr.fy + intr.cy], -1)
    ideal = np.stack([x * intr.fx + intr.cx, y * intr.fy + intr.cy], -1)
    np.testing.assert_allclose(undistort_pixels(uv_d, intr), ideal, atol=1e-6)


def _frames(tmp: Path, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], classes) -> Path:
    """frames.json of views given as (pose, depth [6, 8], label [6, 8])."""
    root = tmp / "cap"
    for sub in ("images", "depth", "labels"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (pose, depth, label) in enumerate(views):
        img, dep, lab = (root / s / f"{i}.png" for s in ("images", "depth", "labels"))
        write_image(img, np.zeros((6, 8, 3), np.uint8))
        write_depth_png(dep, depth)
        write_label_png(lab, label)
        frames.append(Frame(str(i), img, INTR, dep, lab, pose))
    Capture(root, tuple(frames), classes=classes).save(tmp / "frames.json")
    return tmp / "frames.json"


def test_top_view_drops_floor_seen_under_a_table(tmp_path):
    # Two views of the floor (DOWN, 2 m up, depth 2: z = 0) and two views of a table top at
    # z = 0.75 from 2.75 m up with depth 2: the same (x, y) as the floor points, 0.5 m apart.
    # The table is labelled in the west half (u < 4: x < 1) only, the east half unknown.
    # Top-view cells of 0.3 m hold one (x, y) each (no x or y lands on a cell edge: they are
    # odd multiples of 0.25, not multiples of 0.3), i.e. 2 table and 2 floor points in the west
    # half: top = 0.75 (2nd highest), the floor reaches 0 < 0.75 - 0.1: dropped.
    up = DOWN.copy()
    up[2, 3] = 2.75
    depth = np.full((6, 8), 2.0)
    table = np.where(np.arange(8)[None, :] < 4, 3, 255).repeat(6, 0).astype(np.uint8)
    floor = np.zeros((6, 8), np.uint8)
    views = [(up, depth, table), (up, depth, table), (DOWN, depth, floor), (DOWN, depth, floor)]
    frames = _frames(tmp_path, views, {0: "floor", 3: "table"})
    kw = dict(stride=1, cell=0.25, occlusion_cell=0.3, top_band=0.1, top_min_points=2)
    outs, out = _run(tmp_path, frames, occlusion="top", occlusion_shifts=1, **kw)
    xyz, lab, view, _ = read_points(outs.points)
    # kept: 2 x 24 table points, 2 x 24 floor points of the east half (x > 1)
    assert len(lab) == 96 and int((lab == 3).sum()) == 48
    assert (xyz[lab == 0, 0] > 1).all() and (view[lab == 0] >= 2).all()
    assert json.loads((out / "project.json").read_text())["dropped_occluded"] == 48
    # the plan grid is that of all the points: the culling does not move it
    grid = read_grid(outs.grid)
    tmp2 = tmp_path / "none"
    tmp2.mkdir()
    outs2, _ = _run(tmp2, frames, occlusion="none", **kw)
    assert len(read_points(outs2.points)[1]) == 144  # the paper's Π keeps every point
    assert read_grid(outs2.grid) == grid


def test_bounds_of_the_points_are_recorded_with_the_grid(tmp_path):
    frames = _capture(tmp_path, np.full((6, 8), 2.0), np.ones((6, 8), np.uint8))
    outs, _ = _run(tmp_path, frames, stride=1, cell=0.25, pad=0.3, bounds_pct=0.0)
    # points span x in [-0.75, 2.75], y in [0.75, 3.25] (first test); the grid adds the pad
    lo, hi = read_bounds(outs.grid)
    np.testing.assert_allclose([*lo, *hi], [-0.75, 0.75, 2.75, 3.25], atol=1e-6)
    grid = read_grid(outs.grid)
    # origin floor((-0.75 - 0.3) / 0.25) * 0.25 = -1.25 and floor(0.45 / 0.25) * 0.25 = 0.25;
    # W = ceil((3.05 + 1.25) / 0.25) = 18 (17.2), H = ceil((3.55 - 0.25) / 0.25) = 14 (13.2)
    assert grid.origin == (-1.25, 0.25) and grid.shape == (14, 18)


def test_auto_stride_puts_about_one_sample_of_each_view_in_a_plan_cell(tmp_path):
    # fx = 4 px at 2 m: neighbouring pixels land 0.5 m apart on the floor, so a 1 m cell
    # takes every 2nd pixel and a 2 m cell every 4th; a 0.25 m cell every pixel (at least 1)
    frames = _capture(tmp_path, np.full((6, 8), 2.0), None)
    for cell, stride in ((1.0, 2), (2.0, 4), (0.25, 1)):
        folder = tmp_path / f"c{cell}"
        folder.mkdir()
        outs, out = _run(folder, frames, stride=0, cell=cell, pad=0.1, bounds_pct=0.0)
        facts = json.loads((out / "project.json").read_text())
        assert facts["stride"] == stride
        assert facts["sampled"] == len(range(stride // 2, 6, stride)) * len(
            range(stride // 2, 8, stride)
        )


def test_observed_cells_come_from_the_points_and_the_rays(tmp_path):
    # the camera looking down sees the floor footprint x -0.75..2.75, y 0.75..3.25 (a point
    # every 0.5 m); the plan is padded 0.3 m past it, in 5 cm cells
    frames = _capture(tmp_path, np.full((6, 8), 2.0), np.ones((6, 8), np.uint8), n=1)
    kw = {"stride": 1, "cell": 0.05, "pad": 0.3, "bounds_pct": 0.0, "ray_every": 1}
    outs, _ = _run(tmp_path, frames, **kw, seen_radius=0.25, fill_radius=0.4)
    grid = read_grid(outs.grid)
    z = np.load(outs.observed)
    near, free, inside, lab = (z[k] > 0 for k in ("near", "free", "inside", "labelled"))
    assert not (near & ~lab).any() and not (lab & ~inside).any()
    at = lambda x, y: tuple(int(v[0]) for v in grid.cell_of(np.array([[x, y]]))[:2])  # noqa: E731
    assert near[at(0.25, 1.25)]  # a point there
    # midway between four points: 0.35 m from each, too far to be seen, near enough to fill
    assert not near[at(0.5, 1.5)] and lab[at(0.5, 1.5)] and inside[at(0.5, 1.5)]
    assert free[at(1.0, 2.0)]  # under the camera: every ray starts there
    # the pad's outer cells lie 0.3 m past the last points: no view observed them
    assert not inside[0].any() and not inside[-1].any()
    assert not inside[:, 0].any() and not inside[:, -1].any()

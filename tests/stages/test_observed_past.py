"""observed.looked_past and blueprint.blunf.free_floor on a rendered room: the floor round the
cameras' path (below every frame) becomes floor; a cabinet whose top no view sees stays out."""

from __future__ import annotations

import numpy as np

from stages.blueprint.blunf import add_free_floor
from stages.common.blueprint import Grid
from stages.common.camera import Intrinsics, unproject
from stages.common.capture import Capture, Frame, readings_of
from stages.common.io import write_depth_npy
from stages.project.observed import looked_past, observed, past_height
from stages.project.points import _read

ROOM = (6.0, 4.0, 2.6)  # x, y, ceiling (metres)
CABINET = ((0.0, 1.5), (1.2, 2.4), 2.0)  # x range, y range, height: against the wall x = 0,
#                                           taller than the cameras: its top is never seen
CAM_Z = 1.4
PATH = np.linspace(2.4, 5.0, 5)  # x of the spots the views are taken from, at y = 2
CLASSES = {0: "floor", 1: "wall", 6: "cabinet"}
INTR = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)  # 65 x 51 degrees


def _pose(pos: np.ndarray, yaw: float, tilt: float = np.radians(8)) -> np.ndarray:
    """Camera-to-world (OpenCV axes) at pos looking along yaw, tilted down by `tilt`."""
    fwd = np.array([np.cos(yaw) * np.cos(tilt), np.sin(yaw) * np.cos(tilt), -np.sin(tilt)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, fwd], 1)
    c2w[:3, 3] = pos
    return c2w


def _render(c2w: np.ndarray, cabinet: bool = True, box=CABINET) -> np.ndarray:
    """z-depth [48, 64] of the room (floor, walls, ceiling) and the cabinet `box` (or the
    room alone)."""
    u, v = np.meshgrid(np.arange(64.0), np.arange(48.0))
    d_cam = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1)
    d = d_cam.reshape(-1, 3) @ c2w[:3, :3].T  # [P, 3] world, camera-frame z = 1
    o = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_room = np.full(len(d), np.inf)  # inside the room: the nearest exit through a side
        for k, (lo, hi) in enumerate([(0.0, ROOM[0]), (0.0, ROOM[1]), (0.0, ROOM[2])]):
            t = np.where(d[:, k] > 0, (hi - o[k]) / d[:, k], (lo - o[k]) / d[:, k])
            t_room = np.minimum(t_room, np.where(np.isfinite(t) & (t > 0), t, np.inf))
        (x0, x1), (y0, y1), zt = box
        lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, zt])
        t1, t2 = (lo - o) / d, (hi - o) / d
        near = np.nanmax(np.minimum(t1, t2), 1)
        far = np.nanmin(np.maximum(t1, t2), 1)
        t_box = np.where((near <= far) & (near > 0) & cabinet, near, np.inf)
    return np.minimum(t_room, t_box).reshape(48, 64)


def _poses() -> list[np.ndarray]:
    """Forty views from five spots along a path through the room, each turning round."""
    spots = [np.array([x, 2.0, CAM_Z]) for x in PATH]
    return [_pose(p, y) for p in spots for y in np.radians(np.arange(0, 360, 45) + 10)]


def _points(poses: list[np.ndarray], depths: list[np.ndarray]):
    """World points [N, 3] of every pixel of the depths, and their views [N]."""
    uv = np.stack(np.meshgrid(np.arange(64.0), np.arange(48.0)), -1).reshape(-1, 2)
    xyz = [unproject(uv, d.reshape(-1), INTR.K, c2w) for c2w, d in zip(poses, depths, strict=True)]
    view = [np.full(len(uv), i) for i in range(len(poses))]
    return np.concatenate(xyz), np.concatenate(view)


def _scene():
    """The forty views' depths and points (not the ceiling's), labelled by class."""
    poses = _poses()
    depths = [_render(c2w) for c2w in poses]
    xyz, view = _points(poses, depths)
    (x0, x1), (y0, y1), zt = CABINET
    on_box = (xyz[:, 0] <= x1 + 1e-6) & (xyz[:, 1] >= y0 - 1e-6) & (xyz[:, 1] <= y1 + 1e-6)
    on_box &= xyz[:, 2] <= zt + 1e-6
    label = np.where(xyz[:, 2] < 1e-3, 0, np.where(on_box, 6, 1)).astype(np.uint8)
    keep = xyz[:, 2] < ROOM[2] - 1e-3  # the ceiling is not projected
    return poses, depths, xyz[keep], label[keep], view[keep]


def _observed(poses: list[np.ndarray], xyz: np.ndarray, view: np.ndarray):
    """(grid, camera centres [C, 3], near, free, the free cells holding no point, the
    height looked past) of the scene's points on a 0.1 m grid."""
    grid = Grid((0.0, 0.0), 0.1, (40, 60))
    cams = np.array([p[:3, 3] for p in poses])
    near, free, _ = observed(grid, xyz[:, :2], cams[:, :2], view, 0.15, 1)
    row, col, inside = grid.cell_of(xyz[:, :2])
    empty = free.copy()
    empty[row[inside], col[inside]] = False
    return grid, cams, near, free, empty, past_height(cams[:, 2])


def test_the_floor_round_the_path_is_looked_past_and_the_cabinet_is_not(tmp_path) -> None:
    poses, depths, xyz, label, view = _scene()
    assert ((label == 6) & (xyz[:, 2] > CABINET[2] - 1e-3)).sum() <= 2  # its top: unseen
    grid, cams, near, free, empty, height = _observed(poses, xyz, view)
    row, col, inside = grid.cell_of(xyz[:, :2])
    assert height == 0.5 * CAM_Z
    views = [(INTR, c2w, d, None) for c2w, d in zip(poses, depths, strict=True)]
    past = looked_past(grid, empty, views, height)
    assert past.dtype == np.uint16 and not past[~empty].any()

    xy = grid.centers()
    (x0, x1), (y0, y1), _ = CABINET
    box = (xy[..., 0] > x0) & (xy[..., 0] < x1) & (xy[..., 1] > y0) & (xy[..., 1] < y1)
    along = np.clip(xy[..., 0], PATH[0], PATH[-1])  # the nearest point of the cameras' path
    path = np.hypot(xy[..., 0] - along, xy[..., 1] - 2.0) < 0.5  # the floor round it
    # the case: rays crossed both, no point fell in either
    assert (empty & box).sum() >= 0.8 * box.sum() and (empty & path).sum() >= 100
    assert not past[box].any()  # no view looked past the cabinet's inside
    assert (past[empty & path] >= 2).mean() > 0.85  # views along the path looked past it

    # the plan's samples: floor on the path, none in the cabinet
    np.savez(tmp_path / "observed.npz", near=near, free=free, past=past)
    args = (grid, CLASSES, xyz, label, row, col, inside)
    out = add_free_floor(tmp_path / "observed.npz", *args)
    added = np.zeros(grid.shape, bool)
    added[out[2][len(xyz) :], out[3][len(xyz) :]] = True
    assert out[-1] > 0 and (out[1][len(xyz) :] == 0).all()
    assert not (added & box).any()
    assert added[empty & path].mean() > 0.85
    # without the test of the column above, the cabinet's back takes floor samples (its
    # nearest points are the wall's beside it): what the discriminator is for
    np.savez(tmp_path / "blind.npz", near=near, free=free, past=np.where(free, 99, 0))
    blind = add_free_floor(tmp_path / "blind.npz", *args)
    wrong = np.zeros(grid.shape, bool)
    wrong[blind[2][len(xyz) :], blind[3][len(xyz) :]] = True
    assert (wrong & box).any()


def test_a_hole_in_the_surface_is_not_looked_through_where_the_view_read_nothing() -> None:
    # the fused surface lacks the cabinet (no view read its plain front): its depth runs
    # through to the wall behind. Each view's own reading is the cabinet's, with no reading
    # on its front (stereo matched nothing there) and a half-size copy (the depth stage's
    # working size).
    poses, depths, xyz, label, view = _scene()
    grid, cams, near, free, empty, height = _observed(poses, xyz, view)
    holey = [_render(c2w, cabinet=False) for c2w in poses]
    read = []
    for whole, d in zip(holey, depths, strict=True):
        r = np.where(np.abs(whole - d) > 1e-6, 0.0, d)  # nothing read on the cabinet
        read.append(r[::2, ::2])  # 32 x 24: at its own resolution
    xy = grid.centers()
    (x0, x1), (y0, y1), _ = CABINET
    box = (xy[..., 0] > x0) & (xy[..., 0] < x1) & (xy[..., 1] > y0) & (xy[..., 1] < y1)
    along = np.clip(xy[..., 0], PATH[0], PATH[-1])
    path = np.hypot(xy[..., 0] - along, xy[..., 1] - 2.0) < 0.5
    assert (empty & box).sum() >= 0.8 * box.sum()

    blind = looked_past(
        grid, empty, [(INTR, c, d, None) for c, d in zip(poses, holey, strict=True)], height
    )
    assert (blind[empty & box] >= 2).mean() > 0.5  # through the hole: the case
    views = [(INTR, c, d, r) for c, d, r in zip(poses, holey, read, strict=True)]
    past = looked_past(grid, empty, views, height)
    assert not past[box].any()
    assert (past <= blind).all()
    # the floor round the path is still looked past, but by fewer views: those that saw the
    # cabinet's front behind it read nothing there (0.80 here; 0.85+ with whole readings)
    assert (past[empty & path] >= 2).mean() > 0.75
    whole = [(INTR, c, d, r) for c, d, r in zip(poses, holey, depths, strict=True)]
    assert (looked_past(grid, empty, whole, height)[empty & path] >= 2).mean() > 0.85


def test_rays_through_a_hole_in_the_surface_do_not_free_what_they_cross(tmp_path) -> None:
    # a cabinet up to the ceiling: no ray crosses its footprint. The fused surface lacks
    # it (no view read its plain front), so the depth runs through it to the wall behind and
    # those rays cross its footprint; the views' own readings (the cabinet's front, with no
    # reading on most of it) say they did not read that far
    tall = (CABINET[0], CABINET[1], ROOM[2])
    poses = _poses()
    true = [_render(c2w, box=tall) for c2w in poses]
    holey = [_render(c2w, cabinet=False) for c2w in poses]
    xyz, view = _points(poses, holey)
    keep = xyz[:, 2] < ROOM[2] - 1e-3
    xyz, view = xyz[keep], view[keep]
    root = tmp_path / "cap"
    root.mkdir()
    surf, read = [], []
    for i, (c2w, t, h) in enumerate(zip(poses, true, holey, strict=True)):
        r = np.where(np.abs(t - h) > 1e-6, 0.0, t)  # nothing read on the cabinet ...
        r[::4, ::4] = t[::4, ::4]  # ... but a few readings on its front
        write_depth_npy(root / f"s{i}.npy", h.astype(np.float32))
        write_depth_npy(root / f"r{i}.npy", r[::2, ::2].astype(np.float32))  # half size
        surf.append(Frame(f"{i}", root / "x.png", INTR, root / f"s{i}.npy", None, c2w))
        read.append(Frame(f"{i}", root / "x.png", INTR, root / f"r{i}.npy", None, c2w))
    Capture(root, tuple(read)).save(tmp_path / "readings.json")
    got = _read(Capture(root, tuple(surf)), readings_of(tmp_path / "readings.json"), xyz, view)

    grid = Grid((0.0, 0.0), 0.1, (40, 60))
    cams = np.array([p[:3, 3] for p in poses])[:, :2]
    xy = grid.centers()
    (x0, x1), (y0, y1), _ = tall
    x, y = xy[..., 0], xy[..., 1]  # its inside, a cell off its faces:
    box = (x > x0 + 0.05) & (x < x1 - 0.1) & (y > y0 + 0.1) & (y < y1 - 0.1)
    # what each view truly reads that far along its ray: the points in front of the cabinet
    vis = np.concatenate([(t >= 0.9 * h).reshape(-1) for t, h in zip(true, holey, strict=True)])[
        keep
    ]
    assert (~vis).sum() > 1000 and got.mean() > 0.7
    assert (got & ~vis).sum() < 0.01 * len(got)  # at half size a few land on an edge
    assert (vis & ~got).sum() < 0.05 * vis.sum()

    txyz, tview = _points(poses, true)
    truth = observed(grid, txyz[:, :2], cams, tview, 0.15, 1)[1]  # rays to what is there
    assert not truth[box].any()
    blind = observed(grid, xyz[:, :2], cams, view, 0.15, 1)[1]
    assert blind[box].mean() > 0.9  # through the hole: the case
    free = observed(grid, xyz[:, :2], cams, view, 0.15, 1, got)[1]
    # a few rays leak by the cabinet's edge (the readings' half size): 8 of its 130 cells
    assert free[box].mean() < 0.1
    assert free[truth].mean() > 0.97  # the rest of the room is still looked through


def test_a_point_projected_through_the_lens_comes_back_through_its_undistortion() -> None:
    # camera.project with distortion (what looked_past reads depth through) is the inverse
    # of the project stage's undistortion of a distorted photo's pixels
    from stages.common.camera import Intrinsics, depth_at, project, undistort_pixels

    intr = Intrinsics(300.0, 310.0, 160.0, 118.0, 320, 240, (-0.2, 0.05, 0.001, -0.002, 0.01))
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-1.2, 1.2, (200, 2)), rng.uniform(2, 4, (200, 1))], 1)
    uv, z = project(pts, intr.K, np.eye(4), intr.dist)
    pin, _ = project(pts, intr.K, np.eye(4))
    assert np.abs(uv - pin).max() > 5  # the lens moves them
    np.testing.assert_allclose(undistort_pixels(uv, intr), pin, atol=1e-6)
    depth = np.full((240, 320), 9.0)
    d, _ = depth_at(pts, depth, intr.K, np.eye(4), intr.dist)
    ok = (uv[:, 0] >= -0.5) & (uv[:, 0] < 319.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < 239.5)
    assert np.array_equal(d > 0, ok) and np.allclose(z, pts[:, 2])

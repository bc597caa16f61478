"""The procedural room generator: layout, determinism and exactness of its ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stages.common.blueprint import Blueprint
from stages.common.camera import pixel_grid, project, unproject
from stages.common.capture import UNKNOWN, read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_json, read_label
from stages.synth import make_room
from stages.synth.render import Tracer, render
from stages.synth.room import CLASSES, build_room

SMALL = {"views": 8, "seed": 3, "size": (64, 48)}


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_room(tmp_path_factory.mktemp("small") / "cap", **SMALL)


@pytest.fixture(scope="module")
def medium(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 24 views: consecutive cameras 15 degrees apart on the loop, so views 0 and 1 overlap
    return make_room(tmp_path_factory.mktemp("medium") / "cap", views=24, seed=5, size=(160, 120))


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _view(cap: Path, stem: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(depth metres [H, W], labels [H, W], K [3, 3], c2w [4, 4]) of one frame."""
    c = read_layout(cap)
    f = next(f for f in c.frames if f.stem == stem)
    return read_depth(f.depth), read_label(f.label), f.intrinsics.K, f.pose


def _points(cap: Path, stem: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [N, 3] of the pixels with depth, their labels [N] and instances [N]."""
    depth, labels, k, pose = _view(cap, stem)
    h, w = depth.shape
    uv = pixel_grid(w, h).reshape(-1, 2)
    d = depth.reshape(-1)
    keep = d > 0
    inst = read_label(cap / "gt" / "instances" / f"{stem}.png").reshape(-1)
    return unproject(uv[keep], d[keep], k, pose), labels.reshape(-1)[keep], inst[keep]


def test_layout_formats_and_intrinsics(small: Path) -> None:
    c = read_layout(small)
    assert [f.stem for f in c.frames] == [f"{i:04d}" for i in range(8)]
    assert c.has_poses and c.has_depth and c.has_labels
    assert c.classes == CLASSES and c.ignore == (2,)
    assert c.gravity == (0.0, 0.0, -1.0) and c.depth_scale == 1000
    intr = c.frames[0].intrinsics
    # hfov 65 deg: fx = (64 / 2) / tan(32.5 deg) = 32 / 0.63707 = 50.23; centre at (W-1)/2
    assert intr.fx == pytest.approx(50.23, abs=0.01) and intr.fy == intr.fx
    assert (intr.cx, intr.cy, intr.width, intr.height) == (31.5, 23.5, 64, 48)
    assert read_image(c.frames[0].image).shape == (48, 64, 3)
    assert np.asarray(__import__("PIL.Image").Image.open(c.frames[0].depth)).dtype == np.uint16
    gt_poses = read_json(small / "gt" / "poses.json")
    for f in c.frames:
        assert np.array_equal(np.asarray(gt_poses[f.stem]), f.pose)
        assert 1.2 <= f.pose[2, 3] <= 1.7  # camera height
        assert f.pose[2, 2] < -0.2  # optical axis tilted down (z of the forward axis)
    for name in ("mesh.ply", "blueprint.npz", "instances.json"):
        assert (small / "gt" / name).is_file()


def test_same_seed_same_bytes_other_seed_other_room(small: Path, tmp_path: Path) -> None:
    again = _files(make_room(tmp_path / "again", **SMALL))
    assert again == _files(small)
    other = make_room(tmp_path / "other", **{**SMALL, "seed": 4})
    ra, rb = read_json(small / "gt" / "room.json"), read_json(other / "gt" / "room.json")
    assert ra["interior"] != rb["interior"]
    assert (small / "images" / "0000.png").read_bytes() != (
        other / "images" / "0000.png"
    ).read_bytes()


def test_photos_only_is_the_same_capture_without_what_a_phone_lacks(
    small: Path, tmp_path: Path
) -> None:
    phone = make_room(tmp_path / "phone", **SMALL, photos_only=True)
    assert sorted(p.name for p in phone.iterdir()) == ["cameras.json", "gt", "images"]
    assert read_json(phone / "cameras.json") == {
        "intrinsics": read_json(small / "cameras.json")["intrinsics"]
    }
    for sub in ("images", "gt"):  # the same photos and the same ground truth, byte for byte
        files = sorted(p.relative_to(small) for p in (small / sub).rglob("*") if p.is_file())
        assert files == sorted(
            p.relative_to(phone) for p in (phone / sub).rglob("*") if p.is_file()
        )
        assert all((small / f).read_bytes() == (phone / f).read_bytes() for f in files)
    cap = read_layout(phone)
    assert not cap.has_poses and not cap.has_depth and not cap.has_labels and cap.gravity is None


def test_surfaces_lie_where_the_room_says(small: Path) -> None:
    """Floor pixels unproject to z = 0, walls to their planes, furniture into its bbox."""
    room = read_json(small / "gt" / "room.json")
    _, _, lx, ly = room["interior"]
    boxes = {
        int(k): np.asarray(v["bbox"]) for k, v in read_json(small / "gt" / "instances.json").items()
    }
    for i in range(8):
        p, lab, inst = _points(small, f"{i:04d}")
        # depth is in whole mm, so a point is off by at most 0.5 mm along its ray
        assert np.abs(p[lab == 0, 2]).max(initial=0) < 0.005 and np.any(lab == 0)
        assert np.abs(p[lab == 2, 2] - room["height"]).max(initial=0) < 0.005
        w = p[lab == 1]
        to_plane = np.min(np.abs(np.stack([w[:, 0], w[:, 0] - lx, w[:, 1], w[:, 1] - ly])), axis=0)
        assert to_plane.max(initial=0) < 0.005
        for k, b in boxes.items():
            q = p[inst == k]
            assert np.all(q >= b[:3] - 0.005) and np.all(q <= b[3:] + 0.005)


def test_depth_round_trip_between_views(medium: Path) -> None:
    """View 0's depth, unprojected and projected into view 1, lands on view 1's depth."""
    d0, _, k, pose0 = _view(medium, "0000")
    d1, l1, _, pose1 = _view(medium, "0001")
    h, w = d0.shape
    uv = pixel_grid(w, h).reshape(-1, 2)
    keep = d0.reshape(-1) > 0
    pts = unproject(uv[keep], d0.reshape(-1)[keep], k, pose0)
    uv1, z1 = project(pts, k, pose1)
    u0, v0 = np.floor(uv1[:, 0]).astype(int), np.floor(uv1[:, 1]).astype(int)
    ok = (z1 > 0) & (u0 >= 0) & (v0 >= 0) & (u0 < w - 1) & (v0 < h - 1)
    u0, v0, uv1, z1 = u0[ok], v0[ok], uv1[ok], z1[ok]
    quad = np.stack([d1[v0, u0], d1[v0, u0 + 1], d1[v0 + 1, u0], d1[v0 + 1, u0 + 1]])  # [4, N]
    same = np.stack([l1[v0, u0], l1[v0, u0 + 1], l1[v0 + 1, u0], l1[v0 + 1, u0 + 1]])
    valid = np.all(quad > 0, axis=0) & np.all(same == same[0], axis=0)
    assert valid.sum() > 0.3 * h * w  # the two views overlap a lot
    # inverse depth is affine in (u, v) over a plane: its bilinear interpolation is exact
    fu, fv = uv1[:, 0] - u0, uv1[:, 1] - v0
    inv = 1 / np.where(quad > 0, quad, 1)
    top = inv[0] * (1 - fu) + inv[1] * fu
    bot = inv[2] * (1 - fu) + inv[3] * fu
    err = np.abs(1 / (top * (1 - fv) + bot * fv) - z1)[valid]
    # the rest: occluded in view 1, or the 2x2 pixels straddle a crease between two planes
    assert np.median(err) < 0.001 and np.mean(err < 0.005) > 0.9


def test_pixel_labels_agree_with_plan(small: Path) -> None:
    plan = Blueprint.load(small / "gt" / "blueprint.npz")
    lab = plan.labels.astype(int)
    # cells within 2 cells (4 cm) of another label are "near an edge": a point 0.5 mm off
    # or on a vertical face there may read either side
    pad = np.pad(lab, 2, mode="edge")
    edge = np.zeros(lab.shape, bool)
    for dy in range(5):
        for dx in range(5):
            edge |= pad[dy : dy + lab.shape[0], dx : dx + lab.shape[1]] != lab
    boxes = [np.asarray(v["bbox"]) for v in read_json(small / "gt" / "instances.json").values()]
    checked = 0
    for i in range(8):
        p, pl, _ = _points(small, f"{i:04d}")
        keep = pl != 2  # the ceiling is never in the plan
        p, pl = p[keep], pl[keep]
        row, col, inside = plan.grid.cell_of(p[:, :2])
        assert inside.all()
        # floor seen under a table or between chair legs: the plan shows the furniture there
        under = np.zeros(len(p), bool)
        for b in boxes:
            under |= np.all((p[:, :2] >= b[:2]) & (p[:, :2] <= b[3:5]), axis=1) & (pl == 0)
        test = ~edge[row, col] & ~under
        assert np.array_equal(lab[row, col][test], pl[test])
        checked += int(test.sum())
    # wall pixels all project onto the wall's inner line (an edge): the floor and furniture
    # away from edges still make up over a quarter of all pixels
    assert checked > 0.25 * 8 * 64 * 48


def test_plan_walls_margin_and_classes(small: Path) -> None:
    plan = Blueprint.load(small / "gt" / "blueprint.npz")
    room = read_json(small / "gt" / "room.json")
    _, _, lx, ly = room["interior"]
    t = room["wall"]
    assert plan.grid.cell == 0.02 and plan.classes == CLASSES
    assert set(np.unique(plan.labels)) <= {0, 1, 3, 4, 5, 6, 7, 8, UNKNOWN}
    # along the line y = Ly / 2: outside the wall (unknown), in the west wall, on the floor
    # just inside it, in the east wall, outside again
    xs = [-t - 0.05, -t / 2, 0.01, lx + t / 2, lx + t + 0.05]
    got = plan.sample(np.array([[x, ly / 2] for x in xs]))
    assert got[0] == UNKNOWN and got[1] == 1 and got[2] not in (1, UNKNOWN)
    assert got[3] == 1 and got[4] == UNKNOWN
    # every cell whose centre is inside the interior is known
    c = plan.grid.centers().reshape(-1, 2)
    interior = (c[:, 0] > 0.01) & (c[:, 0] < lx - 0.01) & (c[:, 1] > 0.01) & (c[:, 1] < ly - 0.01)
    assert np.all(plan.labels.reshape(-1)[interior] != UNKNOWN)


def test_instances_and_two_chairs(small: Path) -> None:
    inst = {int(k): v for k, v in read_json(small / "gt" / "instances.json").items()}
    chairs = [k for k, v in inst.items() if v["class"] == 4]
    assert len(chairs) >= 2 and len({inst[k]["name"] for k in chairs}) == len(chairs)
    plan = Blueprint.load(small / "gt" / "blueprint.npz")
    for k in chairs:  # a chair's bbox centre is its seat centre, which the plan sees
        b = np.asarray(inst[k]["bbox"])
        assert plan.sample(((b[:2] + b[3:5]) / 2)[None])[0] == 4
    lut = np.full(256, -1)
    lut[0] = -2
    for k, v in inst.items():
        lut[k] = v["class"]
    for i in range(8):
        ids = read_label(small / "gt" / "instances" / f"{i:04d}.png")
        labels = read_label(small / "labels" / f"{i:04d}.png")
        furn = ids > 0
        assert np.array_equal(lut[ids[furn]], labels[furn])  # each instance has one class
        assert set(np.unique(labels[~furn])) <= {0, 1, 2, UNKNOWN}


def test_no_ceiling_same_plan(small: Path, tmp_path: Path) -> None:
    open_top = make_room(tmp_path / "open", **SMALL, ceiling=False)
    a = Blueprint.load(small / "gt" / "blueprint.npz")
    b = Blueprint.load(open_top / "gt" / "blueprint.npz")
    assert np.array_equal(a.labels, b.labels)  # the plan never sees the ceiling
    for i in range(8):
        stem = f"{i:04d}.png"
        la, lb = read_label(small / "labels" / stem), read_label(open_top / "labels" / stem)
        assert 2 not in lb
        # where the ceiling was, rays now leave the room: unknown label, no depth
        assert np.all(lb[la == 2] == UNKNOWN)
        assert np.all(read_depth(open_top / "depth" / stem)[la == 2] == 0)
        assert np.array_equal(la[la != 2], lb[la != 2])


def test_texture_is_rich(medium: Path) -> None:
    """Mean |Laplacian| of a textured view is far above the same view rendered flat."""
    room = build_room(5)
    c = read_layout(medium)
    f = c.frames[0]
    tracer = Tracer(room.parts)
    textured = read_image(f.image).astype(float).mean(-1)
    assert np.array_equal(render(tracer, f.pose, f.intrinsics).rgb, read_image(f.image))
    flat = render(tracer, f.pose, f.intrinsics, textured=False).rgb.astype(float).mean(-1)

    def lap(g: np.ndarray) -> float:
        return float(
            np.abs(
                4 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]
            ).mean()
        )

    # flat shading is constant per face: its Laplacian is non-zero only along edges
    assert lap(textured) > 4 * lap(flat)
    assert lap(textured) > 10  # grey levels per pixel, on a 0..255 scale


def test_bad_out_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(BlunfError, match="busy"):
        make_room(out, views=2, size=(16, 12))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    with pytest.raises(BlunfError, match="views"):
        make_room(tmp_path / "new", views=0)
    with pytest.raises(BlunfError, match="seed"):
        make_room(tmp_path / "new", seed=-1)
    assert not (tmp_path / "new").exists()


def test_camera_heading_math() -> None:
    # A camera at yaw 0, pitch 0 looks along +x: OpenCV x (right) is world -y, y (down) is -z.
    from stages.synth.render import look

    p = look(np.zeros(3), 0.0, 0.0)
    assert np.allclose(p[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    q = look(np.zeros(3), math.pi / 2, -math.pi / 6)
    assert np.allclose(q[:3, 2], [0, math.cos(math.pi / 6), -0.5])  # forward: +y, 30 deg down
    assert np.isclose(np.linalg.det(q[:3, :3]), 1.0)

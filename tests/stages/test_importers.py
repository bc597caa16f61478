"""Readers of other layouts: 7-Scenes, Replica (vMAP), nerfstudio, COLMAP; detection, import."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stages.common.camera import Intrinsics, project
from stages.common.capture import Capture, Frame, read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_json, read_label, write_depth_png
from stages.common.nerfstudio import write_transforms
from stages.ingest import IMPLS, detect, import_capture, load
from stages.ingest.config import IngestConfig, IngestInputs

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _img(path: Path, w: int, h: int, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(path)
    return path


def _rot_z(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = np.deg2rad(deg)
    p = np.eye(4)
    p[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    p[:3, 3] = t
    return p


# ---- 7-Scenes -------------------------------------------------------------------------------
def make_7scenes(root: Path, n: int = 3) -> Path:
    fr = root / "frames"
    for i in range(n):
        stem = f"frame-{10 * i:06d}"
        _img(fr / f"{stem}.color.jpg", 8, 6, i)
        d = np.full((6, 8), 1500 + i, np.uint16)
        d[0, 0], d[1, 1] = 65535, 0  # both mean "no reading"
        Image.fromarray(d).save(fr / f"{stem}.depth.png")
        np.savetxt(fr / f"{stem}.pose.txt", _rot_z(30 * i, (i, 0, 0)))
    np.savetxt(root / "camera-intrinsics.txt", [[7, 0, 4], [0, 7, 3], [0, 0, 1]])
    np.savetxt(root / "gravity-direction.txt", [0, 2, 0])
    return root


def test_7scenes_reader(tmp_path):
    src = make_7scenes(tmp_path / "7s")
    before = sorted(os.listdir(src / "frames"))
    cap = load(src, tmp_path / "work")
    assert cap.kind == "7scenes"
    assert [f.stem for f in cap.frames] == ["frame-000000", "frame-000010", "frame-000020"]
    assert cap.frames[0].intrinsics == Intrinsics(7.0, 7.0, 4.0, 3.0, 8, 6)
    assert cap.gravity == (0.0, 1.0, 0.0)  # (0, 2, 0) normalised
    np.testing.assert_allclose(cap.frames[2].pose, _rot_z(60, (2, 0, 0)), atol=1e-12)
    gt = read_json(cap.gt / "poses.json")
    np.testing.assert_allclose(gt["frame-000010"], _rot_z(30, (1, 0, 0)), atol=1e-12)
    d = read_depth(cap.frames[1].depth, cap.depth_scale, cap.depth_invalid)
    assert d[0, 0] == 0 and d[1, 1] == 0 and d[2, 2] == pytest.approx(1.501)
    assert sorted(os.listdir(src / "frames")) == before


def test_7scenes_unreadable_pose_and_missing_intrinsics(tmp_path):
    src = make_7scenes(tmp_path / "7s")
    (src / "frames" / "frame-000010.pose.txt").write_text("1 0 0\nnot a number\n")
    with pytest.raises(BlunfError, match=r"frame-000010\.pose\.txt: not a readable"):
        load(src, tmp_path / "w1")
    (src / "frames" / "frame-000010.pose.txt").write_text("1 0 0 0\n" * 3)  # 12 numbers
    with pytest.raises(BlunfError, match=r"frame-000010\.pose\.txt: expected 4x4 numbers"):
        load(src, tmp_path / "w2")
    (src / "camera-intrinsics.txt").unlink()
    with pytest.raises(BlunfError, match=r"camera-intrinsics\.txt: file not found"):
        load(src, tmp_path / "w3", kind="7scenes")


def test_stage_refuses_symlink_outside_in_any_layout(tmp_path):
    src = make_7scenes(tmp_path / "7s")
    depth = src / "frames" / "frame-000010.depth.png"
    os.replace(depth, tmp_path / "stolen.png")
    depth.symlink_to(tmp_path / "stolen.png")
    (tmp_path / "out").mkdir()
    with pytest.raises(BlunfError, match=r"frame-000010\.depth\.png: points outside the capture"):
        IMPLS["auto"](IngestConfig(), IngestInputs(src), tmp_path / "out")


def test_import_7scenes_to_project_layout(tmp_path):
    src = make_7scenes(tmp_path / "7s")
    out = import_capture("auto", src, tmp_path / "imported")
    cap = read_layout(out)
    assert [f.image.name for f in cap.frames] == [
        "frame-000000.jpg",
        "frame-000010.jpg",
        "frame-000020.jpg",
    ]
    np.testing.assert_allclose(cap.frames[1].pose, _rot_z(30, (1, 0, 0)), atol=1e-12)
    assert cap.depth_invalid == (65535,) and cap.gravity == (0.0, 1.0, 0.0)
    assert read_depth(cap.frames[0].depth, cap.depth_scale, cap.depth_invalid)[0, 0] == 0
    assert (out / "gt" / "poses.json").exists()


# ---- Replica (vMAP) -------------------------------------------------------------------------
def make_replica(root: Path, class_ids=(1, 2, 3)) -> Path:
    """60x34 frames (a tenth of 600x340); instances 0..5 laid out as 2x3 blocks."""
    a, b, c = class_ids
    info = {
        "classes": [
            {"id": a, "name": "chair"},
            {"id": b, "name": "ceiling"},
            {"id": c, "name": "wall"},
        ],
        "objects": [
            {"id": 1, "class_id": a, "class_name": "chair", "oriented_bbox": {"c": [1, 2, 3]}},
            {"id": 2, "class_id": b, "class_name": "ceiling", "oriented_bbox": None},
            {"id": 3, "class_id": -1, "class_name": "undefined", "oriented_bbox": None},
            {"id": 5, "class_id": c, "class_name": "wall", "oriented_bbox": None},
        ],
        "id_to_label": [-2, a, b, -1, c, c],  # instance 4 is only known from here
    }
    root.mkdir(parents=True)
    (root / "info_semantic.json").write_text(json.dumps(info))
    blocks = np.array([[0, 1, 2], [3, 4, 5]], np.uint8)
    inst = np.kron(blocks, np.ones((17, 20), np.uint8))  # [34, 60]
    for i in range(2):
        _img(root / "rgb" / f"{i:04d}.png", 60, 34, i)
        (root / "depth").mkdir(exist_ok=True)
        write_depth_png(root / "depth" / f"{i:04d}.png", np.full((34, 60), 2.0))
        (root / "instance").mkdir(exist_ok=True)
        Image.fromarray(inst).save(root / "instance" / f"{i:04d}.png")
    return root


def test_replica_reader(tmp_path):
    src = make_replica(tmp_path / "rep")
    cap = load(src, tmp_path / "work")
    assert cap.kind == "replica-vmap" and cap.gravity is None and not cap.has_poses
    # 600x340 -> 60x34 scales fx, fy = 300 by 1/10; pixel centres are integers, so the
    # principal point scales about (-0.5, -0.5): (300.5 / 10 - 0.5, 170.5 / 10 - 0.5)
    assert cap.frames[0].intrinsics == Intrinsics(30.0, 30.0, 29.55, 16.55, 60, 34)
    assert cap.classes == {1: "chair", 2: "ceiling", 3: "wall"} and cap.ignore == (2,)
    lab = read_label(cap.frames[1].label)
    assert cap.frames[1].label.is_relative_to(tmp_path / "work")
    # Instances [[0, 1, 2], [3, 4, 5]] -> classes: 0 unlabelled -> 255; 1 chair; 2 ceiling;
    # 3 has class_id -1 -> 255; 4 from id_to_label -> wall 3; 5 wall 3.
    np.testing.assert_array_equal(lab[::17, ::20], [[255, 1, 2], [255, 3, 3]])
    inst = read_label(cap.gt / "instances" / "0001.png")
    np.testing.assert_array_equal(inst[::17, ::20], [[0, 1, 2], [3, 4, 5]])
    objs = read_json(cap.gt / "objects.json")
    assert objs["1"] == {"class_id": 1, "class_name": "chair", "oriented_bbox": {"c": [1, 2, 3]}}
    assert objs["3"]["class_id"] == 255 and objs["3"]["class_name"] == "undefined"
    assert sorted(os.listdir(src)) == ["depth", "info_semantic.json", "instance", "rgb"]


def test_replica_class_ids_renumbered_when_too_large(tmp_path):
    src = make_replica(tmp_path / "rep", class_ids=(1000, 7, 300))
    cap = load(src, tmp_path / "work", kind="replica-vmap")
    # Sorted Replica ids 7 (ceiling), 300 (wall), 1000 (chair) -> 0, 1, 2, names kept.
    assert cap.classes == {0: "ceiling", 1: "wall", 2: "chair"} and cap.ignore == (0,)
    lab = read_label(cap.frames[0].label)
    np.testing.assert_array_equal(lab[::17, ::20], [[255, 2, 0], [255, 1, 1]])


def test_import_replica_to_project_layout(tmp_path):
    src = make_replica(tmp_path / "rep")
    cap = read_layout(import_capture("replica-vmap", src, tmp_path / "imported"))
    assert cap.has_labels and cap.has_depth and cap.ignore == (2,)
    assert read_label(cap.frames[0].label)[20, 25] == 3  # instance 4 block -> wall
    assert (cap.gt / "instances" / "0000.png").exists() and (cap.gt / "objects.json").exists()


# ---- nerfstudio ------------------------------------------------------------------------------
def test_nerfstudio_opengl_to_opencv_by_hand(tmp_path):
    _img(tmp_path / "ns" / "images" / "a.png", 64, 48)
    meta = {
        "fl_x": 40,
        "fl_y": 40,
        "cx": 32,
        "cy": 24,
        "w": 64,
        "h": 48,
        "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}],
    }
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    cap = load(tmp_path / "ns", tmp_path / "work")
    f = cap.frames[0]
    # Pixel centres: nerfstudio's (0.5, 0.5) is the project's (0, 0), so cx 32 -> 31.5.
    assert f.intrinsics == Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48)
    # An identity OpenGL camera looks down world -z (its -z axis) with world +y up. In
    # OpenCV axes the camera looks down its +z: the pose's z column must be world -z and its
    # y column (image down) world -y, x unchanged: diag(1, -1, -1, 1).
    np.testing.assert_array_equal(f.pose, np.diag([1.0, -1.0, -1.0, 1.0]))
    # So a point 2 m down world -z lands on the principal point at depth +2; 1 m to world +x
    # is right of it (u = cx + 40 * 1 / 2); 1 m to world +y (up) is above it (v smaller).
    pts = np.array([[0, 0, -2.0], [1, 0, -2.0], [0, 1, -2.0]])
    uv, z = project(pts, f.intrinsics.K, f.pose)
    np.testing.assert_allclose(z, [2, 2, 2])
    np.testing.assert_allclose(uv, [[31.5, 23.5], [51.5, 23.5], [31.5, 3.5]])


def test_nerfstudio_round_trip(tmp_path):
    ns = tmp_path / "ns"
    a, b = _img(ns / "images" / "a.png", 64, 48), _img(tmp_path / "outside" / "b.png", 32, 24)
    (ns / "depth").mkdir()
    write_depth_png(ns / "depth" / "a.png", np.ones((48, 64)))
    pose_b = _rot_z(45, (1, 2, 3)) @ _rot_x(20)
    frames = (
        Frame(
            "a",
            a,
            Intrinsics(40, 41, 31.5, 23.5, 64, 48, (0.1, -0.02, 0.001, 0.002)),
            depth=ns / "depth" / "a.png",
            pose=_rot_z(10, (0, 1, 0)),
        ),
        Frame("b", b, Intrinsics(20, 20, 15.0, 11.0, 32, 24), pose=pose_b),
    )
    path = write_transforms(Capture(ns, frames), ns / "transforms.json")
    meta = read_json(path)
    assert [f["file_path"] for f in meta["frames"]] == ["images/a.png", str(b)]
    assert meta["frames"][0]["depth_file_path"] == "depth/a.png"
    assert meta["frames"][0]["cx"] == 32.0 and meta["camera_model"] == "OPENCV"
    cap = load(path, tmp_path / "work")  # the .json file itself also works
    for f, g in zip(frames, cap.frames, strict=True):
        assert g.stem == f.stem and g.image == f.image and g.depth == f.depth
        assert g.intrinsics == f.intrinsics
        np.testing.assert_allclose(g.pose, f.pose, atol=1e-12)


def _rot_x(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    p = np.eye(4)
    p[1:3, 1:3] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return p


def test_nerfstudio_blender_style_fields(tmp_path):
    _img(tmp_path / "bl" / "train" / "r_0.png", 8, 6)
    # camera_angle_x = 2 atan(1/2) gives fl_x = 0.5 w / tan(atan(1/2)) = w = 8; no w, h in the
    # file (taken from the image), no cx, cy (image centre 4, 3 -> 3.5, 2.5), no extension.
    meta = {
        "camera_angle_x": 2 * np.arctan(0.5),
        "frames": [{"file_path": "./train/r_0", "transform_matrix": np.eye(4).tolist()}],
    }
    (tmp_path / "bl" / "transforms.json").write_text(json.dumps(meta))
    f = load(tmp_path / "bl", tmp_path / "work").frames[0]
    assert f.image.name == "r_0.png" and f.stem == "r_0"
    assert f.intrinsics.fx == pytest.approx(8.0) and f.intrinsics.fy == pytest.approx(8.0)
    assert (f.intrinsics.cx, f.intrinsics.cy, f.intrinsics.width) == (3.5, 2.5, 8)


def test_nerfstudio_errors(tmp_path):
    ns = tmp_path / "ns"
    _img(ns / "a.png", 8, 6)
    bad = {"fl_x": 5, "frames": [{"file_path": "missing.png", "transform_matrix": np.eye(4)}]}
    (ns / "transforms.json").write_text(json.dumps(bad, default=lambda o: o.tolist()))
    with pytest.raises(BlunfError, match=r"transforms\.json: file 'missing\.png' not found"):
        load(ns, tmp_path / "w")
    fish = {
        "camera_model": "OPENCV_FISHEYE",
        "fl_x": 5,
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}],
    }
    (ns / "transforms.json").write_text(json.dumps(fish))
    with pytest.raises(BlunfError, match=r"transforms\.json frame 'a\.png': camera_model"):
        load(ns, tmp_path / "w")


# ---- COLMAP ----------------------------------------------------------------------------------
def make_colmap(root: Path, model2: str = "SIMPLE_RADIAL 64 48 40 32 24 0.1") -> Path:
    m = root / "sparse" / "0"
    m.mkdir(parents=True)
    (m / "cameras.txt").write_text(
        f"# id model w h params\n1 PINHOLE 64 48 50 52 32 24\n2 {model2}\n"
    )
    # Image b: q = (cos 45, 0, 0, sin 45) is 90 degrees about z, t = (1, 2, 3).
    (m / "images.txt").write_text(
        "# id qw qx qy qz tx ty tz camera name\n"
        "1 1 0 0 0 0 0 0 1 a.png\n\n"
        f"2 {float(np.cos(np.pi / 4))!r} 0 0 {float(np.sin(np.pi / 4))!r} 1 2 3 2 b.png\n\n"
    )
    (m / "points3D.txt").write_text("")
    _img(root / "images" / "a.png", 64, 48)
    _img(root / "images" / "b.png", 64, 48)
    return root


def test_colmap_reader(tmp_path):
    src = make_colmap(tmp_path / "proj")
    assert detect(src) == "colmap"
    cap = load(src, tmp_path / "work")
    a, b = cap.frames
    # COLMAP pixel centres start at 0.5: cx, cy = 32, 24 -> 31.5, 23.5.
    assert a.intrinsics == Intrinsics(50.0, 52.0, 31.5, 23.5, 64, 48)
    assert b.intrinsics == Intrinsics(40.0, 40.0, 31.5, 23.5, 64, 48, (0.1, 0.0, 0.0, 0.0))
    np.testing.assert_allclose(a.pose, np.eye(4), atol=1e-12)
    # cam_from_world R = [[0,-1,0],[1,0,0],[0,0,1]], t = (1,2,3). Camera-to-world is
    # R^T = [[0,1,0],[-1,0,0],[0,0,1]] and centre -R^T t = -(2, -1, 3) = (-2, 1, -3).
    expect = np.eye(4)
    expect[:3, :3] = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]
    expect[:3, 3] = [-2, 1, -3]
    np.testing.assert_allclose(b.pose, expect, atol=1e-12)
    assert b.image == src / "images" / "b.png" and cap.root == src.resolve()


def test_colmap_errors(tmp_path):
    src = make_colmap(tmp_path / "fish", model2="OPENCV_FISHEYE 64 48 40 40 32 24 0 0 0 0")
    with pytest.raises(BlunfError, match=r"sparse/0 camera 2: camera model OPENCV_FISHEYE"):
        load(src, tmp_path / "w1")
    src = make_colmap(tmp_path / "gone")
    (src / "images" / "b.png").unlink()
    with pytest.raises(BlunfError, match=r"images/b\.png: image of the COLMAP model not found"):
        load(src, tmp_path / "w2")


# ---- detection -------------------------------------------------------------------------------
def test_detect(tmp_path):
    assert detect(make_7scenes(tmp_path / "7s")) == "7scenes"
    assert detect(make_replica(tmp_path / "rep")) == "replica-vmap"
    _img(tmp_path / "blunf" / "images" / "a.png", 8, 6)
    assert detect(tmp_path / "blunf") == "blunf"
    (tmp_path / "odd").mkdir()
    (tmp_path / "odd" / "notes.txt").write_text("?")
    msg = (
        "not a known capture layout .known: blunf, 7scenes, replica-vmap, nerfstudio, colmap, "
        r"photos, video\) and no .jpg or .png photos in it"
    )
    with pytest.raises(BlunfError, match=msg):
        detect(tmp_path / "odd")
    with pytest.raises(BlunfError, match="capture kind 'kinect' unknown"):
        load(tmp_path / "odd", tmp_path / "w", kind="kinect")


# ---- the real captures -----------------------------------------------------------------------
def _data(name: str) -> Path:
    p = DATA / name
    if not p.is_dir():
        pytest.skip(f"real capture {p} absent (see shared/data/README.md)")
    return p


@pytest.mark.slow
def test_real_7scenes(tmp_path):
    cap = load(_data("7scenes-redkitchen"), tmp_path / "work")
    assert cap.kind == "7scenes" and len(cap.frames) == 100 and cap.has_poses
    assert cap.has_depth and cap.gravity is not None
    k = cap.frames[0].intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (585, 585, 320, 240, 640, 480)
    f = next(f for f in cap.frames if f.stem == "frame-000880")  # has 65535 readings
    raw = np.asarray(Image.open(f.depth))
    d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
    assert (raw == 65535).sum() > 0 and np.all(d[raw == 65535] == 0)
    assert len(read_json(cap.gt / "poses.json")) == 100


@pytest.mark.slow
def test_real_replica(tmp_path):
    cap = load(_data("replica-office0"), tmp_path / "work")
    assert cap.kind == "replica-vmap" and len(cap.frames) == 81 and cap.has_labels
    k = cap.frames[0].intrinsics
    assert (k.width, k.height, k.fx, k.cx, k.cy) == (600, 340, 300, 300, 170)
    names = set(cap.classes.values())
    assert {"chair", "sofa", "table", "floor", "wall"} <= names
    assert [cap.classes[i] for i in cap.ignore] == ["ceiling"]
    lab = read_label(cap.frames[0].label)
    assert lab.shape == (340, 600) and set(np.unique(lab)) <= set(cap.classes) | {255}
    assert len(os.listdir(cap.gt / "instances")) == 81


@pytest.mark.slow
def test_real_captures_through_the_stage(tmp_path):
    for name, kind in (("7scenes-redkitchen", "7scenes"), ("replica-office0", "replica-vmap")):
        out = tmp_path / name
        out.mkdir()
        cfg = IngestConfig(frames=9, max_side=320)
        cap = Capture.load(IMPLS["auto"](cfg, IngestInputs(_data(name)), out).frames)
        assert cap.kind == kind and len(cap.frames) == 9
        assert max(cap.frames[0].intrinsics.width, cap.frames[0].intrinsics.height) == 320

"""The ingest stage: layout round trip, frame selection, validation errors, downscaling."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, read_layout, write_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label, write_depth_png, write_label_png
from stages.ingest import IMPLS
from stages.ingest.config import IngestConfig, IngestInputs, IngestOutputs
from stages.ingest.select import select_indices

W, H = 16, 12
INTR = Intrinsics(fx=10.0, fy=11.0, cx=8.0, cy=6.0, width=W, height=H)


def _pose(i: int) -> np.ndarray:
    """A rotation of 10*i degrees about z and a translation (i, 2i, 1)."""
    a = np.deg2rad(10.0 * i)
    p = np.eye(4)
    p[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    p[:3, 3] = [i, 2 * i, 1.0]
    return p


def _depth(i: int) -> np.ndarray:
    """Distinct millimetre values per pixel and frame, as metres. [H, W]"""
    return (1000 + 100 * i + np.arange(H * W).reshape(H, W)) / 1000.0


def _labels(i: int) -> np.ndarray:
    return ((np.arange(H * W).reshape(H, W) + i) % 3).astype(np.uint8)  # classes 0, 1, 2


def make_capture(root: Path, n: int = 5, depth: bool = True, labels: bool = True) -> Path:
    """A tiny capture in the project layout: n frames of 16x12 with poses."""
    (root / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    frames = {}
    for i in range(n):
        stem = f"{i:04d}"
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(
            root / "images" / f"{stem}.png"
        )
        if depth:
            (root / "depth").mkdir(exist_ok=True)
            write_depth_png(root / "depth" / f"{stem}.png", _depth(i))
        if labels:
            (root / "labels").mkdir(exist_ok=True)
            write_label_png(root / "labels" / f"{stem}.png", _labels(i))
        frames[stem] = {"pose": _pose(i).tolist()}
    cams = {"intrinsics": INTR.to_json(), "frames": frames, "gravity": [0, 0, -1]}
    (root / "cameras.json").write_text(json.dumps(cams))
    if labels:
        table = {"classes": {"0": "floor", "1": "wall", "2": "chair"}, "ignore": [1]}
        (root / "labels.json").write_text(json.dumps(table))
    return root


def run_stage(src: Path, out: Path, **cfg) -> Capture:
    out.mkdir()
    outputs = IMPLS["auto"](IngestConfig(**cfg), IngestInputs(src), out)
    assert outputs == IngestOutputs.at(out)
    return Capture.load(outputs.frames)


# ---- layout round trip ---------------------------------------------------------------------
def test_layout_round_trip(tmp_path):
    src = make_capture(tmp_path / "a", n=3)
    (src / "gt").mkdir()
    (src / "gt" / "note.txt").write_text("gt")
    cap = read_layout(src)
    back = read_layout(write_layout(cap, tmp_path / "b"))
    assert [f.stem for f in back.frames] == ["0000", "0001", "0002"]
    assert back.classes == {0: "floor", 1: "wall", 2: "chair"} and back.ignore == (1,)
    assert back.gravity == (0.0, 0.0, -1.0)
    assert (back.gt / "note.txt").read_text() == "gt"
    for i, (f, g) in enumerate(zip(cap.frames, back.frames, strict=True)):
        assert g.intrinsics == INTR
        np.testing.assert_allclose(g.pose, _pose(i), atol=1e-12)
        np.testing.assert_array_equal(read_image(g.image), read_image(f.image))
        # mm PNG: _depth is a whole number of mm, so it comes back exactly.
        np.testing.assert_allclose(read_depth(g.depth), _depth(i), atol=1e-6)
        np.testing.assert_array_equal(read_label(g.label), _labels(i))


# ---- frame selection ------------------------------------------------------------------------
def test_select_9_of_90_evenly_spread():
    # Positions i * 89 / 8 = 0, 11.125, 22.25, 33.375, 44.5, 55.625, 66.75, 77.875, 89,
    # rounded half up.
    idx = select_indices(90, 9)
    assert idx == [0, 11, 22, 33, 45, 56, 67, 78, 89]
    assert len(set(idx)) == 9 and idx[0] == 0 and idx[-1] == 89
    assert set(np.diff(idx)) <= {11, 12}  # 89 / 8 = 11.125 between neighbours


def test_select_edge_cases():
    assert select_indices(90, 1) == [44]  # the middle: (90 - 1) // 2
    assert select_indices(5, 1) == [2]
    assert select_indices(90, 2) == [0, 89]
    assert select_indices(7, 100) == list(range(7))  # more asked than there are: all
    assert select_indices(7, 0) == list(range(7))
    assert select_indices(10, 10) == list(range(10))
    for count in range(1, 40):
        for n in range(1, count + 1):
            idx = select_indices(count, n)
            assert len(set(idx)) == n and sorted(idx) == idx
            if n > 1:
                assert idx[0] == 0 and idx[-1] == count - 1


def test_stage_selects_frames_and_reports(tmp_path):
    src = make_capture(tmp_path / "cap", n=5)
    cap = run_stage(src, tmp_path / "out", frames=3)
    assert [f.stem for f in cap.frames] == ["0000", "0002", "0004"]  # 0, 4/2, 4
    np.testing.assert_allclose(cap.frames[1].pose, _pose(2))
    assert cap.classes[2] == "chair" and cap.gravity == (0.0, 0.0, -1.0)
    facts = json.loads((tmp_path / "out" / "ingest.json").read_text())
    assert facts["frames_total"] == 5 and facts["frames_selected"] == 3
    assert facts["indices"] == [0, 2, 4] and facts["kind"] == "blunf"
    assert facts["has_depth"] and facts["has_labels"] and facts["has_poses"]
    assert not (tmp_path / "out" / "resized").exists()
    assert sorted(p.name for p in src.iterdir()) == [  # nothing written into the capture
        "cameras.json",
        "depth",
        "images",
        "labels",
        "labels.json",
    ]


def test_stage_downscales_with_nearest_depth_and_labels(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    cap = run_stage(src, tmp_path / "out", max_side=8)
    f = cap.frames[1]
    # 16x12 -> longer side 8: factor 1/2, 8x6. Intrinsics.scaled halves f, and c about the
    # corner (-0.5, -0.5) (pixel centres are integers): (8 + 0.5) / 2 - 0.5, (6 + 0.5) / 2 - 0.5
    assert f.intrinsics == Intrinsics(5.0, 5.5, 3.75, 2.75, 8, 6)
    assert f.image.is_relative_to(tmp_path / "out") and read_image(f.image).shape == (6, 8, 3)
    assert f.original == src / "images" / "0001.png"  # full size, for SfM (frames.json keeps it)
    # Nearest neighbour at half size: output pixel j samples input floor((j + 0.5) * 2) = 2j + 1.
    np.testing.assert_allclose(read_depth(f.depth), _depth(1)[1::2, 1::2], atol=1e-6)
    np.testing.assert_array_equal(read_label(f.label), _labels(1)[1::2, 1::2])


def test_stage_keeps_frames_smaller_than_max_side(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    cap = run_stage(src, tmp_path / "out", max_side=64)
    assert cap.frames[0].image == src / "images" / "0000.png" and cap.frames[0].intrinsics == INTR
    assert cap.frames[0].original is None


def test_bad_config_values(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    for i, (cfg, word) in enumerate(
        [
            ({"frames": -1}, "ingest.frames"),
            ({"kind": "kinect"}, "ingest.kind"),
            ({"max_side": -5}, "ingest.max_side"),
        ]
    ):
        with pytest.raises(BlunfError, match=word):
            run_stage(src, tmp_path / f"out{i}", **cfg)


# ---- validation errors, each naming the file ------------------------------------------------
def test_corrupt_image_bytes(tmp_path):
    src = make_capture(tmp_path / "cap", n=3)
    (src / "images" / "0001.png").write_bytes(b"\x00garbage" * 20)
    with pytest.raises(BlunfError, match=r"0001\.png: not a readable image"):
        run_stage(src, tmp_path / "out", check="quick")


def test_truncated_image_caught_by_full_check_only(tmp_path):
    src = make_capture(tmp_path / "cap", n=3)
    p = src / "images" / "0002.png"
    p.write_bytes(p.read_bytes()[:60])  # header intact (size readable), pixel data cut
    run_stage(src, tmp_path / "quick", check="quick")  # headers only: passes
    with pytest.raises(BlunfError, match=r"0002\.png: not a readable image"):
        run_stage(src, tmp_path / "full", check="full")


def test_mismatched_depth_size(tmp_path):
    src = make_capture(tmp_path / "cap", n=3)
    write_depth_png(src / "depth" / "0001.png", np.ones((6, 8)))
    for check in ("quick", "full"):
        with pytest.raises(
            BlunfError, match=r"depth/0001\.png: depth is 8x6 but its image is 16x12"
        ):
            run_stage(src, tmp_path / check, check=check)


def test_image_size_differs_from_intrinsics(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    Image.fromarray(np.zeros((12, 15, 3), np.uint8)).save(src / "images" / "0001.png")
    with pytest.raises(BlunfError, match=r"0001\.png: image is 15x12 but its intrinsics say 16x12"):
        run_stage(src, tmp_path / "out")


def test_missing_depth_for_one_frame(tmp_path):
    src = make_capture(tmp_path / "cap", n=4)
    (src / "depth" / "0002.png").unlink()
    with pytest.raises(BlunfError, match=r"images/0002\.png: no depth for this frame"):
        run_stage(src, tmp_path / "out", frames=2)  # 0002 is not even selected


def test_symlink_outside_capture(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    outside = tmp_path / "elsewhere.png"
    os.replace(src / "images" / "0001.png", outside)
    (src / "images" / "0001.png").symlink_to(outside)
    with pytest.raises(BlunfError, match=r"0001\.png: points outside the capture folder"):
        run_stage(src, tmp_path / "out")


def test_symlink_inside_capture_is_fine(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    os.replace(src / "images" / "0001.png", src / "0001-real.png")
    (src / "images" / "0001.png").symlink_to(src / "0001-real.png")
    assert len(run_stage(src, tmp_path / "out").frames) == 2


def test_empty_folder(tmp_path):
    (tmp_path / "cap").mkdir()
    with pytest.raises(BlunfError, match=r"cap: capture folder is empty"):
        run_stage(tmp_path / "cap", tmp_path / "out")
    (tmp_path / "cap" / "images").mkdir()
    with pytest.raises(BlunfError, match=r"images: no \.jpg or \.png images"):
        run_stage(tmp_path / "cap", tmp_path / "out2")


def test_work_folder_inside_capture_refused(tmp_path):
    src = make_capture(tmp_path / "cap", n=2)
    with pytest.raises(BlunfError, match="work folder inside the capture"):
        run_stage(src, src / "run")

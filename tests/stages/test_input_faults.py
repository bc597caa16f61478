"""Inputs a hostile user would try, refused in one line at ingest (the table of
tests/test_bad_input.py runs each through the CLI), and the SfM model report by hand."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.checks import check_intrinsics
from stages.common.errors import BlunfError
from stages.common.io import check_exists, read_depth, write_depth_png
from stages.ingest.select import check_structure
from stages.poses.models import describe, spans
from tests.stages.test_ingest import H, W, make_capture, run_stage


# ---- intrinsics -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("intr", "match"),
    [
        # fx = 1e308 is finite and positive: a field of view of ~0 degrees
        (
            Intrinsics(1e308, 1e308, 319.5, 239.5, 640, 480),
            r"horizontal field of view 3\.67e-304 degrees \(fx = 1e\+308 px",
        ),
        # 2 * atan(320 / 25) = 171.1 degrees
        (Intrinsics(25, 25, 319.5, 239.5, 640, 480), r"horizontal field of view 171 degrees"),
        # horizontal 65 degrees, vertical 2 * atan(240 / 3000) = 9.1 degrees
        (Intrinsics(500, 3000, 319.5, 239.5, 640, 480), r"vertical field of view 9\.15 degrees"),
        # both views plausible (65 and 18 degrees), but pixels 3 times taller than wide
        (Intrinsics(500, 1500, 319.5, 239.5, 640, 480), r"fy / fx = 3 "),
        # the margin is a quarter of the size: cx up to 800 px, cy down to -120 px
        (Intrinsics(500, 500, 801, 239.5, 640, 480), r"principal point cx = 801 px"),
        (Intrinsics(500, 500, 319.5, -121, 640, 480), r"principal point cy = -121 px"),
    ],
)
def test_implausible_intrinsics_are_refused(intr: Intrinsics, match: str) -> None:
    with pytest.raises(BlunfError, match=r"^cams: " + match):
        check_intrinsics(intr, "cams")


def test_plausible_intrinsics_pass() -> None:
    for intr in (
        Intrinsics(585, 585, 320, 240, 640, 480),  # 7-Scenes
        Intrinsics(600, 600, 599.5, 339.5, 1200, 680),  # Replica
        Intrinsics(28, 28, 319.5, 239.5, 640, 480),  # 170 degrees: the widest allowed
        Intrinsics(500, 1000, 799, -119, 640, 480),  # 2:1 pixels, principal point off-centre
    ):
        check_intrinsics(intr, "cams")


def test_ingest_checks_intrinsics_of_every_layout(tmp_path: Path) -> None:
    # a frames.json from another reader (no cameras.json) is checked too, naming the image
    img = tmp_path / "a.png"
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(img)
    bad = Intrinsics(1e6, 1e6, 31.5, 23.5, 64, 48)
    from stages.ingest.select import check_frames

    with pytest.raises(BlunfError, match=r": intrinsics of a\.png: horizontal field of view"):
        check_frames(Capture(tmp_path, (Frame("a", img, bad),)), full=False)


# ---- depth ----------------------------------------------------------------------------------
def test_8bit_depth_png_is_refused_by_both_checks(tmp_path: Path) -> None:
    src = make_capture(tmp_path / "cap", n=2)
    p = src / "depth" / "0001.png"
    Image.fromarray(np.full((H, W), 200, np.uint8)).save(p)
    with pytest.raises(BlunfError, match=r"0001\.png: depth image is 8-bit \(mode L\)"):
        read_depth(p)
    for i, check in enumerate(("full", "quick")):  # quick: from the PNG header alone
        with pytest.raises(BlunfError, match=r"depth/0001\.png: depth image is 8-bit"):
            run_stage(src, tmp_path / f"out{i}", check=check)


def test_wide_integer_and_float_depth_images_still_read(tmp_path: Path) -> None:
    p = tmp_path / "d.tif"  # 32-bit float TIFF (mode F): divided by the scale like a PNG
    Image.fromarray(np.full((4, 4), 1500.0, np.float32)).save(p)
    np.testing.assert_allclose(read_depth(p), 1.5)


def test_empty_depth_everywhere_is_refused_naming_the_folder(tmp_path: Path) -> None:
    src = make_capture(tmp_path / "cap", n=3)
    for i in range(3):
        write_depth_png(src / "depth" / f"{i:04d}.png", np.zeros((H, W)))
    with pytest.raises(BlunfError, match=rf"^{src}/depth: the capture's depth is empty"):
        run_stage(src, tmp_path / "out")


def test_one_empty_depth_map_is_only_reported(tmp_path: Path) -> None:
    src = make_capture(tmp_path / "cap", n=3)
    write_depth_png(src / "depth" / "0001.png", np.zeros((H, W)))
    run_stage(src, tmp_path / "out")
    facts = json.loads((tmp_path / "out" / "ingest.json").read_text())
    assert facts["empty_depth"] == ["0001"]


# ---- names ----------------------------------------------------------------------------------
def test_two_images_of_one_stem_are_refused_naming_both(tmp_path: Path) -> None:
    src = make_capture(tmp_path / "cap", n=2)
    Image.open(src / "images" / "0001.png").save(src / "images" / "0001.jpg")
    with pytest.raises(BlunfError, match=r"images/0001\.jpg and .*images/0001\.png: two images"):
        run_stage(src, tmp_path / "out")
    (src / "images" / "0001.jpg").unlink()
    np.save(src / "depth" / "0001.npy", np.ones((H, W), np.float32))
    with pytest.raises(BlunfError, match=r"depth/0001\.png and .*depth/0001\.npy: two files"):
        run_stage(src, tmp_path / "out2")
    # any layout: two frames of one name
    a, b = src / "images" / "0000.png", src / "images" / "0001.png"
    intr = Intrinsics(10, 10, 7.5, 5.5, W, H)
    cap = Capture(src, (Frame("x", a, intr), Frame("x", b, intr)))
    with pytest.raises(BlunfError, match=r"0000\.png and .*0001\.png: two images of one frame"):
        check_structure(cap, (src,))


def test_check_exists_says_why_a_path_leads_nowhere(tmp_path: Path) -> None:
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    (tmp_path / "dangling").symlink_to(tmp_path / "gone")
    with pytest.raises(BlunfError, match=r"loop: capture folder is a symlink loop"):
        check_exists(tmp_path / "loop", "capture folder")
    with pytest.raises(BlunfError, match=r"loop/x: capture folder is a symlink loop"):
        check_exists(tmp_path / "loop" / "x", "capture folder")
    with pytest.raises(BlunfError, match=r"dangling: capture folder is a symlink to .*gone, wh"):
        check_exists(tmp_path / "dangling", "capture folder")
    with pytest.raises(BlunfError, match=r"nope: capture folder not found$"):
        check_exists(tmp_path / "nope", "capture folder")
    assert check_exists(tmp_path, "capture folder") == tmp_path


def test_colmap_project_with_an_empty_model_folder(tmp_path: Path) -> None:
    src = make_capture(tmp_path / "cap", n=2)
    (src / "cameras.json").unlink()
    (src / "sparse" / "0").mkdir(parents=True)
    with pytest.raises(BlunfError, match=r"sparse/0: COLMAP model folder holds no model"):
        run_stage(src, tmp_path / "out")


# ---- what SfM made of the photos ------------------------------------------------------------
def test_spans_of_capture_order() -> None:
    stems = [f"s{i}" for i in range(10)]
    assert spans([0, 1, 2, 5, 7, 8], stems) == ["s0..s2 (3)", "s5", "s7..s8 (2)"]
    assert spans([], stems) == []
    many = [f"f{i}" for i in range(100)]
    got = spans(list(range(0, 100, 2)), many)  # 50 lone frames: 20 listed, 30 counted
    assert got[:2] == ["f0", "f2"] and got[-1] == "+ 30 more frames" and len(got) == 21


def test_describe_warns_on_split_and_on_many_left_out() -> None:
    stems = [f"{r}{i}" for r in "ab" for i in range(5)]  # a0..a4, b0..b4
    # two models of 5: one warning naming both groups, and half the photos left out
    d = describe([[5, 6, 7, 8, 9], [0, 1, 2, 3, 4]], stems)
    assert [g["spans"] for g in d["groups"]] == [["b0..b4 (5)"], ["a0..a4 (5)"]]
    assert [g["kept"] for g in d["groups"]] == [True, False]
    assert d["left_out"] == ["a0..a4 (5)"]
    assert len(d["warnings"]) == 2
    assert "2 models" in d["warnings"][0] and "b0..b4 (5); a0..a4 (5)" in d["warnings"][0]
    assert d["warnings"][1].startswith("5 of 10 photos (50 %) are left out")
    assert d["warnings"][0].endswith("; poses.mapper=global may join them")
    # the global mapper's own split: no hint to run it
    assert (
        "mapper" not in describe([[5, 6, 7, 8, 9], [0, 1, 2, 3, 4]], stems, "global")["warnings"][0]
    )
    # a second model of 2 photos, 2 of 10 left out (20 %, not more): no warning
    d = describe([[0, 1, 2, 3, 4, 5, 6, 7], [8, 9]], stems)
    assert d["warnings"] == [] and d["left_out"] == ["b3..b4 (2)"]
    # one model, 3 of 10 dropped: warned
    d = describe([[0, 1, 2, 3, 4, 5, 6]], stems)
    assert d["warnings"] == [
        "3 of 10 photos (30 %) are left out of the model (0 in other models, 3 in none): b2..b4 (3)"
    ]
    # nothing registered at all
    assert describe([], stems)["left_out"] == ["a0..b4 (10)"]

"""Stated intrinsics checked by bundle adjustment (poses.self_calibrate = "auto", stated.py):
a wrong stated focal is replaced by SfM's estimate, a right one is kept as it is, and a
sensor depth map follows its frame's new camera."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.evaluate.poses import pose_metrics
from stages.poses import IMPLS, PosesConfig, PosesInputs
from stages.poses.stated import register_depth


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """16 photos (22.5 degrees apart on a loop) of a procedural room at 160x120, exact K."""
    from stages.synth import make_room

    out = tmp_path_factory.mktemp("stated") / "room"
    return make_room(out, views=16, seed=0, size=(160, 120), photos_only=True)


def _sfm(cap: Capture, work: Path, **cfg) -> tuple[Capture, dict]:
    work.mkdir()
    cap.save(work / "frames.json")
    (work / "out").mkdir()
    outs = IMPLS["sfm"](
        PosesConfig(threads=1, max_features=2048, **cfg),
        PosesInputs(work / "frames.json"),
        work / "out",
    )
    return Capture.load(outs.frames), json.loads(outs.sfm.read_text())


def _stated(room: Path, factor: float) -> tuple[Capture, Intrinsics]:
    """The room's photos with every frame's focal stated `factor` times the true one."""
    cap = read_layout(room)
    true = cap.frames[0].intrinsics
    wrong = replace(true, fx=true.fx * factor, fy=true.fy * factor)
    return cap.with_frames([replace(f, intrinsics=wrong) for f in cap.frames]), true


def test_a_focal_stated_10_percent_long_is_replaced_by_the_estimate(
    room: Path, tmp_path: Path
) -> None:
    # True focal 80 / tan(32.5 deg) = 125.6 px, stated 138.1. The check's adjustment moves it
    # by -9.6 % (beyond 3 %); the photos are mapped again with the focal estimated. Measured:
    # adopted 126.4 px, +0.7 % off the true focal. Without the check it stays at 138.1.
    cap, true = _stated(room, 1.10)
    got, facts = _sfm(cap, tmp_path / "w")
    k = facts["intrinsics"]
    assert k["source"] == "self-calibrated" and k["check"] == "auto"
    assert k["stated"]["fx"] == pytest.approx(1.10 * true.fx)
    assert k["refined_change"] < -0.03 and "beyond 3 %" in k["reason"]
    assert k["adopted"]["fx"] == pytest.approx(true.fx, rel=0.02)
    assert all(f.intrinsics.fx == pytest.approx(true.fx, rel=0.02) for f in got.frames)
    assert {f.calib for f in got.frames} == {"self-calibrated"}
    gt = {s: np.asarray(p) for s, p in read_json(room / "gt" / "poses.json").items()}
    assert pose_metrics({f.stem: f.pose for f in got.frames}, gt)["registered"] == 16


def test_a_right_stated_focal_is_kept_as_it_is(
    room: Path, tmp_path: Path, capfd: pytest.CaptureFixture
) -> None:
    # Measured: the check's adjustment moves the exact focal by -0.56 % (160x120 photos;
    # <= 0.08 % on the 320x240 demo room and the Replica office), within the 3 % tolerance.
    cap, true = _stated(room, 1.0)
    got, facts = _sfm(cap, tmp_path / "w")
    # the check's adjustment is silent: pycolmap.bundle_adjustment's glog heading and timer
    # got through minloglevel 1 (four lines per run)
    assert "bundle adjustment" not in capfd.readouterr().err
    k = facts["intrinsics"]
    assert k["source"] == "given" and k["adopted"] == "stated"
    assert abs(k["refined_change"]) < 0.01
    assert facts["camera"]["fixed"] is True and "depth_registered" not in facts
    assert all(f.intrinsics == true and f.calib == "given" for f in got.frames)
    # false: no check at all, the same poses
    kept, off = _sfm(cap, tmp_path / "off", self_calibrate=False)
    assert off["intrinsics"] == {"source": "given"}
    for a, b in zip(got.frames, kept.frames, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)


def test_depth_follows_its_frame_into_the_new_camera(tmp_path: Path) -> None:
    # A slanted plane seen by a 585 px camera (the 7-Scenes depth camera), resampled into a
    # 526 px camera at the same place: the map must be the plane as the 526 px camera sees
    # it (to the nearest reading: < 0.5 % here), with no reading where it sees beyond the
    # 585 px image.
    def plane(k: Intrinsics) -> np.ndarray:
        u, v = np.meshgrid(np.arange(k.width) - k.cx, np.arange(k.height) - k.cy)
        return 2.0 / (1.0 + 0.3 * u / k.fx + 0.1 * v / k.fy)  # n . X = 2 m, n ~ (0.3, 0.1, 1)

    old = Intrinsics(585.0, 585.0, 319.5, 239.5, 640, 480)
    new = Intrinsics(526.5, 526.5, 319.5, 239.5, 640, 480)
    np.save(tmp_path / "d.npy", plane(old).astype(np.float32))
    register_depth(tmp_path / "d.npy", old, new, tmp_path / "r.npy", 1000.0, (65535,))
    got, want = np.load(tmp_path / "r.npy"), plane(new)
    inside = got > 0
    assert inside[240, 33:606].all() and not inside[240, :31].any()  # 585 px sees less
    np.testing.assert_allclose(got[inside], want[inside], rtol=5e-3)


@pytest.mark.parametrize("bad", [{"self_calibrate": "yes"}, {"stated_focal_tolerance": 0.0}])
def test_bad_auto_settings_name_the_key(bad: dict) -> None:
    with pytest.raises(BlunfError, match=f"poses.{next(iter(bad))}"):
        PosesConfig(**bad)

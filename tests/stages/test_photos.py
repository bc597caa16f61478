"""Any photos in: a plain folder of JPEGs (with or without EXIF) or a video, no intrinsics.

The synthetic room's true focal at 200x150 is 100 / tan(32.5 deg) = 156.97 px. Its photos
are written as JPEGs carrying a 35 mm-equivalent focal (27 mm, rounded as EXIF stores it:
156.01 px) or no EXIF at all (prior 1.2 x 200 = 240 px), and as an mp4.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image, ImageFilter

from pipeline.cli import main
from pipeline.config import load_config
from pipeline.planner import make_plan
from pipeline.report import Report
from pipeline.runner import Runner
from stages.common.capture import Capture, read_layout
from stages.common.errors import BlunfError
from stages.ingest import detect, exif, import_capture, load
from stages.ingest.config import IngestConfig, IngestInputs
from stages.ingest.select import run as ingest
from stages.ingest.video import VideoOptions
from stages.poses.config import PosesConfig, PosesInputs
from stages.poses.sfm import run as sfm

SIZE = (200, 150)
TRUE_F = 100 / np.tan(np.radians(32.5))  # 156.97 px
EVERY = 3  # photos: every third view of the room; the video: all, two of three blurred


def write_jpegs(frames: list[np.ndarray], out: Path, f35: int | None, make: str = "Synth") -> Path:
    """Frames as JPEGs named 0000.jpg..., with EXIF Make/Model and FocalLengthIn35mmFilm."""
    out.mkdir(parents=True)
    for i, a in enumerate(frames):
        e = Image.Exif()
        if f35 is not None:
            e[exif.MAKE], e[exif.MODEL] = make, "Room"
            e.get_ifd(exif.EXIF_IFD)[exif.FOCAL_35MM] = f35
        Image.fromarray(a).save(out / f"{i:04d}.jpg", quality=95, exif=e)
    return out


def write_mp4(path: Path, frames: list[np.ndarray], fps: int = 12, rotation: int = 0) -> Path:
    """An H.264 mp4 of RGB frames; crf 8, as 160x120 frames at crf 18 lose SIFT matches."""
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=fps)
        h, w = frames[0].shape[:2]
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.options = {"crf": "8"}
        if rotation:
            s.set_display_rotation(rotation)
        for a in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(a, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """The room's photos with EXIF, without, and as a video; and the room itself."""
    from stages.synth import make_room

    d = tmp_path_factory.mktemp("photos")
    room = make_room(d / "room", views=16 * EVERY, seed=0, size=SIZE, photos_only=True)
    views = [np.asarray(Image.open(f.image).convert("RGB")) for f in read_layout(room).frames]
    f35 = round(TRUE_F * exif.FILM_DIAGONAL_MM / np.hypot(*SIZE))  # 27
    video = []
    for i, a in enumerate(views):
        blur = 1.5 if i % EVERY != 1 else 0.0  # the sharp one: the middle of each window
        blur = 3.0 if i >= 45 else blur  # the last window: all blurred
        im = Image.fromarray(a)
        video.append(np.asarray(im.filter(ImageFilter.GaussianBlur(blur)) if blur else im))
    return {
        "room": room,
        "exif": write_jpegs(views[1::EVERY], d / "exif", f35),
        "plain": write_jpegs(views[1::EVERY], d / "plain", None),
        "video": write_mp4(d / "room.mp4", video),
    }


def _sfm(src: Path, out: Path, **ingest_cfg: int) -> tuple[dict, dict, Capture]:
    """Ingest + SfM stages; returns (ingest facts, sfm facts, the posed capture)."""
    (out / "ingest").mkdir(parents=True)
    (out / "poses").mkdir()
    frames = ingest(IngestConfig(**ingest_cfg), IngestInputs(src), out / "ingest").frames
    posed = sfm(PosesConfig(threads=2), PosesInputs(frames), out / "poses")
    facts = json.loads((out / "ingest" / "ingest.json").read_text())
    return facts, json.loads(posed.sfm.read_text()), Capture.load(posed.frames)


# ---- SfM estimates the focal -----------------------------------------------------------------
def test_exif_focal_is_the_prior_and_sfm_refines_it(inputs, tmp_path):
    facts, sfm_facts, cap = _sfm(inputs["exif"], tmp_path)
    assert facts["kind"] == "photos" and facts["intrinsics"]["source"] == "exif"
    (cam,) = facts["intrinsics"]["cameras"]
    assert cam["camera"] == "Synth Room 200x150" and cam["images"] == 16
    assert cam["fx"] == pytest.approx(27 / exif.FILM_DIAGONAL_MM * 250)  # 156.01
    assert sfm_facts["registered"] == 16
    (est,) = sfm_facts["intrinsics"]["cameras"]
    assert sfm_facts["intrinsics"]["source"] == "self-calibrated"
    assert est["prior_source"] == "exif" and (est["cx"], est["cy"]) == (99.5, 74.5)
    assert est["fx"] == pytest.approx(TRUE_F, rel=0.02)  # measured 156.93 (-0.03 %)
    assert {f.calib for f in cap.frames} == {"self-calibrated"}
    assert cap.frames[0].intrinsics.fx == est["fx"]


def test_without_exif_sfm_self_calibrates_from_the_prior(inputs, tmp_path):
    facts, sfm_facts, _ = _sfm(inputs["plain"], tmp_path)
    (cam,) = facts["intrinsics"]["cameras"]
    assert (cam["source"], cam["fx"], cam["camera"]) == ("prior", 240.0, "unknown device 200x150")
    (est,) = sfm_facts["intrinsics"]["cameras"]
    assert est["prior_fx"] == 240.0
    assert est["fx"] == pytest.approx(TRUE_F, rel=0.05)  # measured 156.88 (-0.05 %)
    assert "weak" not in sfm_facts["intrinsics"]  # 16 views around a room


def test_video_sharpest_frames_then_self_calibration(inputs, tmp_path):
    facts, sfm_facts, _ = _sfm(inputs["video"], tmp_path, video_frames=16)
    v = facts["video"]
    assert (v["frames_total"], v["windows"], v["rotation_deg"]) == (48, 16, 0)
    # the sharp frame of each window of three, except the last, where all three are blurred
    assert v["picked"][:15] == list(range(1, 45, EVERY))
    assert v["blurred"] == [f"frame-{v['picked'][15]:06d}"]
    assert facts["kind"] == "video" and facts["intrinsics"]["source"] == "prior"
    assert sfm_facts["registered"] >= 15
    (est,) = sfm_facts["intrinsics"]["cameras"]
    assert est["fx"] == pytest.approx(TRUE_F, rel=0.05)  # measured 156.74 (-0.14 %)


def test_few_views_are_reported_as_weak(inputs, tmp_path):
    src = tmp_path / "few"
    src.mkdir()
    for p in sorted(inputs["plain"].iterdir())[4:10]:
        shutil.copy(p, src / p.name)
    _, sfm_facts, _ = _sfm(src, tmp_path / "run")
    (why,) = sfm_facts["intrinsics"]["weak"]
    assert "registered views (< 10)" in why


# ---- EXIF, cameras, layouts ------------------------------------------------------------------
def _jpeg(path: Path, size: tuple[int, int], tags: dict[int, object], ifd0: dict | None = None):
    e = Image.Exif()
    for k, v in (ifd0 or {}).items():
        e[k] = v
    for k, v in tags.items():
        e.get_ifd(exif.EXIF_IFD)[k] = v
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (90, 120, 150)).save(path, exif=e)
    return path


def test_exif_focal_from_35mm_or_sensor_pitch(tmp_path):
    g = exif.guess(_jpeg(tmp_path / "a.jpg", (300, 200), {exif.FOCAL_35MM: 26}))
    assert g.calib == "exif" and g.intrinsics.fx == pytest.approx(26 / 43.2666 * np.hypot(300, 200))
    assert (g.intrinsics.cx, g.intrinsics.cy) == (149.5, 99.5)
    # a phone: 4.2 mm on a sensor of 7000 px per cm, recorded for a 4000 px wide original
    tags = {
        exif.FOCAL_LENGTH: 4.2,
        exif.FOCAL_PLANE_XRES: 7000.0,
        exif.FOCAL_PLANE_UNIT: 3,
        exif.PIXEL_X_DIMENSION: 4000,
    }
    g = exif.guess(_jpeg(tmp_path / "b.jpg", (400, 300), tags))
    assert g.intrinsics.fx == pytest.approx(4.2 * 700 * 400 / 4000)  # 294 px at 400 px wide
    g = exif.guess(_jpeg(tmp_path / "c.jpg", (300, 200), {exif.FOCAL_LENGTH: 4.2}))
    assert g.calib == "prior" and g.intrinsics.fx == 360.0  # no pitch: the prior
    g = exif.guess(_jpeg(tmp_path / "d.jpg", (300, 200), {exif.FOCAL_35MM: 0}))  # 0 = unknown
    assert g.calib == "prior"


@pytest.mark.parametrize(
    "tags",
    [{exif.FOCAL_35MM: 2}, {exif.FOCAL_35MM: 900}, {exif.FOCAL_LENGTH: -4.0}],
)
def test_nonsense_exif_focal_fails_naming_the_file(tmp_path, tags):
    p = _jpeg(tmp_path / "odd.jpg", (300, 200), tags)
    with pytest.raises(BlunfError, match=r"odd\.jpg: EXIF .*focal length .* makes no sense"):
        exif.guess(p)


def test_two_devices_or_two_sizes_get_two_cameras(tmp_path):
    src = tmp_path / "two"
    for i in range(3):
        _jpeg(src / f"a{i}.jpg", (80, 60), {exif.FOCAL_35MM: 26}, {exif.MAKE: "A"})
        _jpeg(src / f"b{i}.jpg", (80, 60), {exif.FOCAL_35MM: 26}, {exif.MAKE: "B"})
        _jpeg(src / f"c{i}.jpg", (60, 80), {exif.FOCAL_35MM: 26}, {exif.MAKE: "B"})
    cap = load(src, tmp_path / "w")
    assert cap.kind == "photos"
    assert sorted({f.camera for f in cap.frames}) == ["A 80x60", "B 60x80", "B 80x60"]
    _jpeg(src / "odd.jpg", (100, 50), {})
    with pytest.raises(BlunfError, match=r"odd\.jpg: only 1 photo.* need intrinsics in cameras"):
        load(src, tmp_path / "w2")


def test_large_photos_are_downscaled_once_with_their_intrinsics(tmp_path):
    src = tmp_path / "big"
    for i in range(3):
        _jpeg(src / f"{i}.jpg", (1280, 960), {exif.FOCAL_35MM: 26})
    out = tmp_path / "ingest"
    out.mkdir()
    cap = Capture.load(ingest(IngestConfig(), IngestInputs(src), out).frames)
    f = cap.frames[0]
    assert Image.open(f.image).size == (640, 480) and f.image.is_relative_to(out)
    assert f.intrinsics.fx == pytest.approx(26 / exif.FILM_DIAGONAL_MM * 800)  # 1600 / 2
    assert (f.intrinsics.cx, f.intrinsics.cy, f.calib) == (319.5, 239.5, "exif")


def test_layouts_of_photos_and_their_errors(tmp_path, inputs):
    assert detect(inputs["plain"]) == "photos" and detect(inputs["video"]) == "video"
    # the project's layout without cameras.json: intrinsics from the photos, no longer an error
    shutil.copytree(inputs["exif"], tmp_path / "cap" / "images")
    cap = load(tmp_path / "cap", tmp_path / "w")
    assert cap.kind == "blunf" and {f.calib for f in cap.frames} == {"exif"}
    # ... but poses without intrinsics are refused
    (tmp_path / "cap" / "cameras.json").write_text(
        json.dumps({"frames": {"0000": {"pose": np.eye(4).tolist()}}})
    )
    with pytest.raises(BlunfError, match="cameras.json: poses given but no intrinsics"):
        load(tmp_path / "cap", tmp_path / "w3")
    (tmp_path / "none").mkdir()
    (tmp_path / "none" / "notes.txt").write_text("?")
    with pytest.raises(BlunfError, match="no .jpg or .png photos in it"):
        detect(tmp_path / "none")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video" * 100)
    with pytest.raises(BlunfError, match=r"bad\.mp4: cannot decode the video"):
        load(bad, tmp_path / "w4")


def test_poses_without_intrinsics_are_refused_by_the_planner(inputs, tmp_path):
    cap = load(inputs["plain"], tmp_path / "w")
    cap = cap.with_frames([replace(f, pose=np.eye(4)) for f in cap.frames])
    with pytest.raises(BlunfError, match=r"0000\.jpg: the capture gives poses but no intrinsics"):
        make_plan(cap, load_config())
    assert make_plan(cap, load_config(None, ["poses.impl=sfm"])).runs("poses")


def test_video_rotation_is_honoured(tmp_path):
    a = np.zeros((48, 64, 3), np.uint8)
    a[:10, :20] = 255  # a white block at the top left
    src = write_mp4(tmp_path / "turned.mp4", [a] * 4, rotation=90)
    cap = load(src, tmp_path / "w", opts=VideoOptions(frames=2))
    b = np.asarray(Image.open(cap.frames[0].image))
    assert b.shape == (64, 48, 3) and cap.frames[0].intrinsics.width == 48
    assert np.abs(b.astype(int) - np.rot90(a)).mean() < 2  # turned 90 degrees anticlockwise


def test_import_writes_the_layout_and_no_half_written_folder(inputs, tmp_path):
    out = import_capture("video", inputs["video"], tmp_path / "cap", VideoOptions(frames=8))
    cap = read_layout(out, exif.guess_all)
    assert len(cap.frames) == 8 and {f.calib for f in cap.frames} == {"prior"}
    assert (
        not (out / "cameras.json").exists()
        or "intrinsics" not in (out / "cameras.json").read_text()
    )
    # an undecodable video leaves no output folder, and `run` fails in one line, exit 2
    bad = tmp_path / "bad.mov"
    bad.write_bytes(b"\x00" * 512)
    assert main(["import", "video", str(bad), str(tmp_path / "cap2")]) == 2
    assert not (tmp_path / "cap2").exists()
    assert main(["run", str(bad), "--out", str(tmp_path / "run")]) == 2
    assert not list((tmp_path / "run").glob("ingest/*/frames.json"))


def test_video_frames_are_cached_like_a_stage(inputs, tmp_path):
    cfg = load_config(None, ["ingest.video_frames=6"])
    statuses = []
    for _ in range(2):
        report = Report(scene="v", capture=str(inputs["video"]), config={})
        Runner(tmp_path, cfg, report).stage("ingest", "auto", IngestInputs(inputs["video"]))
        statuses.append(report.stages[0].status)
    assert statuses == ["ran", "cached"]
    assert len(list(tmp_path.glob("ingest/*/import/video/frame-*.jpg"))) == 6


# ---- the whole path (slow: the photos-only NeRF depth stage takes minutes) -------------------
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["exif", "plain", "video"])
def test_photos_or_video_run_to_a_plan(inputs, tmp_path, kind):
    fast = ["blueprint.blunf.steps=60", "fusion.voxel=0.05", "nerf.train.max_steps=20"]
    args = ["run", str(inputs[kind]), "--out", str(tmp_path / "run")]
    args += [x for s in fast + ["ingest.video_frames=16"] for x in ("--set", s)]
    assert main(args) == 0
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    poses = next(s for s in report["stages"] if s["name"] == "poses")
    (est,) = poses["facts"]["intrinsics"]["cameras"]
    assert est["fx"] == pytest.approx(TRUE_F, rel=0.02 if kind == "exif" else 0.05)
    assert (tmp_path / "run" / "blueprint.png").is_file() and report["plan"]["components"]

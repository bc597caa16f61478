"""The poses stage: metric scale by hand, config checks, `given`, and real pycolmap runs."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame, read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_json
from stages.evaluate.poses import pose_metrics
from stages.poses import IMPLS, PosesConfig, PosesInputs, PosesOutputs
from stages.poses.config import (
    BundleAdjustmentConfig,
    KeyframesConfig,
    MatchingConfig,
    RetrievalConfig,
)
from stages.poses.matching import keyframe_stride
from stages.poses.models import metric_scale
from stages.poses.scale import (
    depth_ratios,
    scale_from_camera_height,
    scale_from_depth,
    scale_from_distance,
    scale_from_priors,
)
from stages.poses.sfm import _colmap_camera, first_octave

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def shared_capture(name: str) -> Path:
    """A real capture beside the project, or a clean skip when this checkout lacks it."""
    p = SHARED_DATA / name
    if not p.is_dir():
        pytest.skip(f"real capture {p} not present (it lives beside the project, not in it)")
    return p


# ---- metric scale, worked out by hand -------------------------------------------------------


def test_depth_ratios_read_the_depth_pixel_under_each_keypoint() -> None:
    # An 8x8 image with a 4x4 depth map: image pixel u covers [u - 0.5, u + 0.5), i.e. depth
    # column floor((u + 0.5) / 2). Keypoint (5, 2) -> column floor(2.75) = 2, row
    # floor(1.25) = 1: depth 3.0 m over SfM depth 1.5 gives ratio 2. Keypoint (1, 1) ->
    # cell (0, 0) = 2.0 m over 4.0 gives 0.5. Dropped: a keypoint on a missing reading
    # (cell (3, 3) = 0), one with SfM depth <= 0, one outside the image.
    depth = np.zeros((4, 4), np.float32)
    depth[1, 2], depth[0, 0] = 3.0, 2.0
    uv = np.array([[5.0, 2.0], [1.0, 1.0], [7.0, 7.0], [5.0, 2.0], [9.0, 1.0]])
    z = np.array([1.5, 4.0, 1.0, -1.0, 1.0])
    np.testing.assert_allclose(depth_ratios(uv, z, depth, (8, 8)), [2.0, 0.5])


def test_scale_from_depth_is_the_pooled_median() -> None:
    # Pooled ratios [1, 2, 3, 10]: median 2.5. Relative deviations |r / 2.5 - 1| =
    # [0.6, 0.2, 0.2, 3.0]: median 0.4. The empty image is not counted.
    s, facts = scale_from_depth([np.array([1.0, 2.0, 3.0]), np.array([10.0]), np.array([])])
    assert s == pytest.approx(2.5)
    assert facts["spread_rel_mad"] == pytest.approx(0.4)
    assert (facts["ratios"], facts["images"]) == (4, 2)
    with pytest.raises(BlunfError, match="no sparse point"):
        scale_from_depth([np.array([])])


def test_scale_from_distance() -> None:
    # Centres 5 SfM units apart (3-4-5 triangle) that are 2.5 m apart: scale 0.5.
    s, _ = scale_from_distance(np.zeros(3), np.array([3.0, 4.0, 0.0]), 2.5, ("a", "b"))
    assert s == pytest.approx(0.5)
    with pytest.raises(BlunfError, match="same camera centre"):
        scale_from_distance(np.ones(3), np.ones(3), 2.5, ("a", "b"))


def test_scale_from_camera_height_ignores_stray_low_points() -> None:
    # Cameras look horizontally with image-down = world -z, so up = +z. 99 floor points at
    # z = 0 plus one stray at z = -50: the 2nd percentile is still 0. Camera heights 1, 1.5,
    # 2 -> median 1.5 SfM units; a true height of 3 m gives scale 2 (the lowest point would
    # have given 3 / 51.5).
    centers = np.array([[0, 0, 1.0], [1, 0, 1.5], [2, 0, 2.0]])
    x_axes, y_axes = np.tile([1.0, 0.0, 0.0], (3, 1)), np.tile([0.0, 0.0, -1.0], (3, 1))
    points = np.zeros((100, 3))
    points[:, 0] = np.arange(100)
    points[0, 2] = -50.0
    s, facts = scale_from_camera_height(centers, x_axes, y_axes, points, 3.0)
    assert s == pytest.approx(2.0)
    assert facts["sfm_height"] == pytest.approx(1.5)


# ---- config and camera ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("bad", "field"),
    [
        ({"mapper": "hierarchical"}, "mapper"),
        ({"scale_from": "gps"}, "scale_from"),
        ({"scale_from": "distance"}, "known_distance"),
        ({"scale_from": "camera_height", "camera_height": -1.0}, "camera_height"),
        ({"min_registered_frac": 1.5}, "min_registered_frac"),
        ({"double_below": -1}, "double_below"),
        ({"max_features": 0}, "max_features"),
    ],
)
def test_bad_config_names_the_field(bad: dict, field: str) -> None:
    with pytest.raises(BlunfError, match=f"^poses.{field}:"):
        PosesConfig(**bad)


@pytest.mark.parametrize(
    ("cls", "bad", "field"),
    [
        (MatchingConfig, {"kind": "vocabtree"}, "matching.kind"),
        (MatchingConfig, {"overlap": 0}, "matching.overlap"),
        (KeyframesConfig, {"register_refinements": 0}, "keyframes.register_refinements"),
        (KeyframesConfig, {"register_iterations": 0}, "keyframes.register_iterations"),
        (RetrievalConfig, {"neighbours": 0}, "matching.retrieval.neighbours"),
        (RetrievalConfig, {"words": 64, "sample": 10}, "matching.retrieval.sample"),
        (BundleAdjustmentConfig, {"global_max_refinements": 0}, "ba.global_max_refinements"),
        (BundleAdjustmentConfig, {"global_growth": 1.0}, "ba.global_growth"),
        (BundleAdjustmentConfig, {"global_growth": float("nan")}, "ba.global_growth"),
        (KeyframesConfig, {"at_least": 5}, "keyframes.at_least"),
        (KeyframesConfig, {"hold": 0.0}, "keyframes.hold"),
    ],
)
def test_bad_nested_config_names_the_field(cls: type, bad: dict, field: str) -> None:
    with pytest.raises(BlunfError, match=f"^poses.{field}:"):
        cls(**bad)


def test_colmap_camera_shifts_the_principal_point() -> None:
    # COLMAP puts the top-left pixel centre at (0.5, 0.5), the project at (0, 0).
    intr = Intrinsics(500.0, 501.0, 319.5, 239.5, 640, 480)
    assert _colmap_camera(intr) == ("PINHOLE", "500.0,501.0,320.0,240.0")
    model, params = _colmap_camera(Intrinsics(500, 500, 10, 20, 640, 480, (0.1, -0.05)))
    assert (model, params) == ("OPENCV", "500.0,500.0,10.5,20.5,0.1,-0.05,0.0,0.0")


def test_sift_doubles_only_images_below_double_below(tmp_path: Path) -> None:
    # SIFT reads the larger image capped at max_image_size: 640 px is not below 640 (octave
    # 0); 320 px is (octave -1, doubled); a 640 px image read at most 400 px long is too.
    big = _write_png(tmp_path / "big.png", np.zeros((480, 640, 3), np.uint8))
    small = _write_png(tmp_path / "small.png", np.zeros((240, 320, 3), np.uint8))
    intr = Intrinsics(500, 500, 319.5, 239.5, 640, 480)
    frames = (Frame("a", small, intr.scaled(320, 240)), Frame("b", big, intr))
    assert first_octave(PosesConfig(), frames) == 0
    assert first_octave(PosesConfig(), frames[:1]) == -1
    assert first_octave(PosesConfig(max_image_size=400), frames) == -1
    assert first_octave(PosesConfig(double_below=0), frames[:1]) == 0


# ---- given ----------------------------------------------------------------------------------


def _write_png(path: Path, rgb: np.ndarray) -> Path:
    Image.fromarray(rgb).save(path)
    return path


def test_given_copies_poses_and_refuses_missing_ones(tmp_path: Path) -> None:
    intr = Intrinsics(20, 20, 15.5, 11.5, 32, 24)
    img = _write_png(tmp_path / "a.png", np.zeros((24, 32, 3), np.uint8))
    p = np.eye(4)
    p[:3, 3] = [1, 2, 3]
    cap = Capture(tmp_path, (Frame("a", img, intr, pose=p), Frame("b", img, intr, pose=np.eye(4))))
    cap.save(tmp_path / "frames.json")
    (tmp_path / "out").mkdir()
    cfg = PosesConfig(impl="given")
    outs = IMPLS["given"](cfg, PosesInputs(tmp_path / "frames.json"), tmp_path / "out")
    assert outs == PosesOutputs.at(tmp_path / "out")
    np.testing.assert_array_equal(Capture.load(outs.frames).frames[0].pose, p)
    assert read_json(outs.sfm)["registered"] == 2
    cap.with_frames([Frame("c", img, intr)]).save(tmp_path / "nopose.json")
    (tmp_path / "out2").mkdir()
    with pytest.raises(BlunfError, match="'c' has no pose"):
        IMPLS["given"](cfg, PosesInputs(tmp_path / "nopose.json"), tmp_path / "out2")


# ---- real pycolmap runs ---------------------------------------------------------------------


def _run_sfm(cap: Capture, work: Path, **cfg) -> tuple[Capture, dict]:
    cap.save(work / "frames.json")
    (work / "out").mkdir()
    outs = IMPLS["sfm"](PosesConfig(**cfg), PosesInputs(work / "frames.json"), work / "out")
    assert outs == PosesOutputs.at(work / "out")
    return Capture.load(outs.frames), json.loads(outs.sfm.read_text())


def _run_sfm_on_off(
    cap: Capture, tmp_path: Path, setting: Callable[[bool], dict], **cfg
) -> dict[bool, tuple[Capture, dict]]:
    """_run_sfm on one thread (2048 features) with `setting(on)` beside cfg, for on True and
    False, each in its own folder under tmp_path."""
    runs = {}
    for on in (True, False):
        work = tmp_path / str(on)
        work.mkdir()
        runs[on] = _run_sfm(cap, work, threads=1, max_features=2048, **setting(on), **cfg)
    return runs


def test_blank_images_do_not_register(tmp_path: Path) -> None:
    # Uniform grey photos have no SIFT features: nothing can register.
    intr = Intrinsics(40, 40, 31.5, 23.5, 64, 48)
    frames = tuple(
        Frame(
            f"b{i}", _write_png(tmp_path / f"b{i}.png", np.full((48, 64, 3), 128, np.uint8)), intr
        )
        for i in range(4)
    )
    with pytest.raises(BlunfError, match=r"sfm: only 0 of 4 images registered"):
        _run_sfm(Capture(tmp_path, frames), tmp_path, threads=1, scale_from="none")


def _two_rooms(root: Path, views: int) -> Capture:
    """Photos of two procedural rooms (seeds 2 and 4, `views` each, 160x120) in one capture,
    named a_* and b_*. The generator's textures depend on the surface and its world
    position, not on the seed, so two synthetic rooms look alike wherever their floors and
    walls overlap and SfM rightly joins them; room b's photos are mirrored (as a mirrored
    room would look; SIFT tells mirror images apart) so that the rooms share nothing."""
    from stages.synth import make_room

    (root / "images").mkdir(parents=True)
    for tag, seed in (("a", 2), ("b", 4)):
        room = make_room(root.parent / tag, views=views, seed=seed, size=(160, 120))
        for p in sorted((room / "images").iterdir()):
            im = Image.open(p)
            if tag == "b":
                im = im.transpose(Image.Transpose.FLIP_LEFT_RIGHT)  # cx = (W - 1) / 2 stays
            im.save(root / "images" / f"{tag}_{p.name}")
    cams = read_json(root.parent / "a" / "cameras.json")
    (root / "cameras.json").write_text(json.dumps({"intrinsics": cams["intrinsics"]}))
    return read_layout(root)


def test_sfm_names_the_groups_when_photos_of_two_rooms_make_two_models(tmp_path: Path) -> None:
    """Photos of two rooms with poses.min_registered_frac lowered: the run goes on with the
    larger model, and sfm.json (the stage's record in report.json) says which photos went
    into which model and warns. Measured: one model per room, 14 photos each (and a third of
    3 of room a's photos), ~25 s on one thread."""
    from pipeline.runner import _facts

    cap = _two_rooms(tmp_path / "both", views=14)
    got, facts = _run_sfm(
        cap, tmp_path, threads=1, max_features=2048, min_registered_frac=0.3, scale_from="none"
    )
    assert facts["models"] >= 2
    whole = {g["spans"][0] for g in facts["groups"] if g["frames"] >= 12 and len(g["spans"]) == 1}
    rooms = {s[0] for s in whole}  # "a_0000..a_0013 (14)" -> "a"
    assert rooms == {"a", "b"}, facts["groups"]
    for span in whole:  # each room's model holds only that room's photos
        assert span.split("..")[1].startswith(span[0]), span
    kept = next(g for g in facts["groups"] if g["kept"])
    assert kept["frames"] == len(got.frames) == facts["registered"]
    room_kept = kept["spans"][0][0]
    assert {f.stem[0] for f in got.frames} == {room_kept}
    # the warnings name both rooms' photos, and what was left out
    split = next(w for w in facts["warnings"] if w.startswith("SfM made"))
    assert all(s in split for s in whole), split
    other = ({"a", "b"} - {room_kept}).pop()
    assert facts["left_out"] and all(s.startswith(other) for s in facts["left_out"])
    assert any("left out of the model" in w for w in facts["warnings"])
    # the facts reach the report: small enough for the runner to copy them
    assert _facts(tmp_path / "out" / "sfm.json")["warnings"] == facts["warnings"]


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """24 views (15 degrees apart on a loop) of a procedural room at 192x144, exact GT."""
    from stages.synth import make_room

    return make_room(tmp_path_factory.mktemp("sfm") / "room", views=24, seed=0, size=(192, 144))


def _with_blanks(cap: Capture, n: int, tmp_path: Path) -> Capture:
    """`cap` with n blank photos blank0.. (with the first frame's depth) after its 12th view:
    no features, so they cannot register."""
    blank = _write_png(tmp_path / "blank.png", np.full((144, 192, 3), 90, np.uint8))
    f0 = cap.frames[0]
    blanks = [Frame(f"blank{i}", blank, f0.intrinsics, depth=f0.depth) for i in range(n)]
    return cap.with_frames([*cap.frames[:12], *blanks, *cap.frames[12:]])


def _gt_poses(root: Path) -> dict[str, np.ndarray]:
    return {s: np.asarray(p) for s, p in read_json(root / "gt" / "poses.json").items()}


def test_sfm_incremental_on_a_synthetic_room(room: Path, tmp_path: Path) -> None:
    """Registration, accuracy and metric scale from depth; then the other scale sources."""
    gt = _gt_poses(room)
    cap = read_layout(room)
    # Two blank photos (with blank depth) slipped into the middle cannot register: they must
    # be named in sfm.json and dropped from frames.json.
    cap = _with_blanks(cap, 2, tmp_path)
    got, facts = _run_sfm(cap, tmp_path, threads=1, max_features=2048)
    est = {f.stem: f.pose for f in got.frames}
    m = pose_metrics(est, gt)
    assert facts["matching"] == "exhaustive"  # auto: 26 images <= 40
    assert (facts["registered"], facts["total"]) == (24, 26)
    assert facts["unregistered"] == ["blank0", "blank1"]
    assert [f.stem for f in got.frames] == sorted(gt) and m["registered"] == 24
    # Measured: ATE 0.4-1.8 cm and 0.1-0.3 degrees (as the synthetic textures evolved) in a
    # 6.7 x 4.9 m room seen at 192x144, where a pixel spans ~0.4 degrees; alignment scale
    # within 0.2 % of 1 (depth gives metres).
    assert m["ate_rmse_m"] < 0.03
    assert m["rot_err_deg_median"] < 0.6
    assert m["align_scale"] == pytest.approx(1.0, abs=0.01)
    assert facts["scale_from"]["method"] == "depth" and facts["points3D"] > 100
    assert (tmp_path / "out" / "sparse.ply").is_file()

    # The written model is metric now, so re-scaling it from the true camera height must
    # give ~1 (floor = 2nd percentile of sparse points, not exact: 5 %). A wrong "up" would
    # put the cameras below the floor and fail.
    rec = pycolmap.Reconstruction(tmp_path / "out" / "sparse")
    by_name = {im.name: im.image_id for im in rec.images.values()}
    names = sorted(by_name)  # "000000_0000.png", ...: capture order
    ids, kept = [by_name[n] for n in names], list(range(len(names)))
    height = float(np.median([p[2, 3] for p in gt.values()]))  # floor at z = 0 in GT
    cfg = PosesConfig(scale_from="camera_height", camera_height=height)
    s, _ = metric_scale(cfg, got, rec, ids, kept)
    assert s == pytest.approx(1.0, abs=0.05)
    # No length given: the hand-held camera height prior (1.45 m; the room's cameras are at
    # 1.25-1.65 m, median 1.43) over the floor found in the sparse points (these views do not
    # see the ceiling). Measured: scale 1.010.
    s, facts = metric_scale(PosesConfig(scale_from="priors"), got, rec, ids, kept)
    assert facts["method"] == "priors" and facts["source"] == "camera_height", facts
    assert s == pytest.approx(1.0, rel=0.05)
    assert 0.0 < facts["uncertainty_rel"] <= 0.1
    # Known distance between the first and last camera centres: exactly known / estimated.
    c0, c1 = got.frames[0].pose[:3, 3], got.frames[-1].pose[:3, 3]  # type: ignore[index]
    cfg = PosesConfig(scale_from="distance", known_distance=1.7)
    s, facts = metric_scale(cfg, got, rec, ids, kept)
    assert s == pytest.approx(1.7 / np.linalg.norm(c1 - c0), rel=1e-6)


def test_sfm_global_on_a_synthetic_room(room: Path, tmp_path: Path) -> None:
    got, facts = _run_sfm(
        read_layout(room), tmp_path, threads=1, max_features=2048, mapper="global"
    )
    m = pose_metrics({f.stem: f.pose for f in got.frames}, _gt_poses(room))
    assert facts["mapper"] == "global"
    assert m["registered"] == 24
    assert m["ate_rmse_m"] < 0.03
    assert m["align_scale"] == pytest.approx(1.0, abs=0.01)


def test_sfm_self_calibration_on_a_synthetic_room(room: Path, tmp_path: Path) -> None:
    # COLMAP starts the principal point at the image centre (96, 72) in its convention and
    # does not refine it: (95.5, 71.5) in ours, which is also the true one (synth puts it at
    # ((W - 1) / 2, (H - 1) / 2)). The focal is estimated: true 96 / tan(32.5 deg) = 150.69;
    # measured 150.63.
    got, facts = _run_sfm(
        read_layout(room), tmp_path, threads=1, max_features=2048, self_calibrate=True
    )
    true = read_layout(room).frames[0].intrinsics
    assert facts["camera"]["fixed"] is False and "unreliable" in facts["camera"]["warning"]
    (est,) = facts["camera"]["estimated"]
    assert (est["cx"], est["cy"]) == (true.cx, true.cy) == (95.5, 71.5)
    assert est["fx"] == pytest.approx(true.fx, rel=0.005)
    assert got.frames[0].intrinsics.fx == est["fx"]
    m = pose_metrics({f.stem: f.pose for f in got.frames}, _gt_poses(room))
    assert m["registered"] == 24 and m["ate_rmse_m"] < 0.03


# ---- 7-Scenes (slow) ------------------------------------------------------------------------


def _seven_scenes(n: int) -> tuple[Capture, dict[str, np.ndarray]]:
    root = shared_capture("7scenes-redkitchen")
    intr = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    stems = sorted(p.name.split(".")[0] for p in (root / "frames").glob("frame-*.color.jpg"))[:n]
    frames = tuple(
        Frame(s, root / "frames" / f"{s}.color.jpg", intr, depth=root / "frames" / f"{s}.depth.png")
        for s in stems
    )
    gt = {s: np.loadtxt(root / "frames" / f"{s}.pose.txt") for s in stems}
    return Capture(root, frames, depth_invalid=(65535,), kind="7scenes"), gt


@pytest.mark.slow
def test_sfm_seven_scenes_100_frames(tmp_path: Path) -> None:
    # 100 frames -> auto picks sequential matching; depth gives the metric scale.
    cap, gt = _seven_scenes(100)
    got, facts = _run_sfm(cap, tmp_path)
    m = pose_metrics({f.stem: f.pose for f in got.frames}, gt)
    assert facts["matching"] == "sequential"
    assert m["registered"] >= 95
    assert m["ate_rmse_m"] <= 0.05
    assert m["align_scale"] == pytest.approx(1.0, abs=0.05)
    # A real, blurred capture's model agrees with its own matches: the check raises no false
    # alarm, and the incremental mapper's model is kept (the whole photos run of these 100
    # views with configs/phone.yaml: 0 of 433 pairs contradicted).
    assert facts["agreement"]["agrees"] and facts["mapper"] == "incremental"
    assert facts["agreement"]["strong_contradicted"] == 0
    # The floor found among the (now metric) sparse points, with no length given: the
    # cameras' median height above it is the kitchen's, 1.39 m (Kinect depth and gravity;
    # measured: 1.42), so the hand-held prior (1.45 m) puts the scale within 10 %.
    _priors_find_the_floor(tmp_path / "out" / "sparse", got, cap, 1.39)


def _priors_find_the_floor(sparse: Path, got: Capture, cap: Capture, height: float) -> None:
    """scale_from=priors on a metric SfM model: the floor lies `height` metres (within 5 %)
    below the cameras' median, and the scale is within 10 % of 1."""
    rec = pycolmap.Reconstruction(sparse)
    by_name = {im.name: im.image_id for im in rec.images.values()}
    names = sorted(by_name)  # capture order
    stems = [f.stem for f in cap.frames]
    kept = [stems.index(f.stem) for f in got.frames]
    ids = [by_name[n] for n in names]
    s, facts = metric_scale(PosesConfig(scale_from="priors"), cap, rec, ids, kept)
    assert facts["method"] == "priors"
    assert facts["camera_height_m"] / s == pytest.approx(height, rel=0.05), facts
    assert s == pytest.approx(1.0, rel=0.1)


@pytest.mark.slow
def test_sfm_replica_office_priors_find_the_floor(tmp_path: Path) -> None:
    """Replica office (every other of the 81 frames, depth for the metric scale): the floor
    found in the sparse points lies 1.76 m below the cameras' median (their height in the
    office's plan from its depth; measured on all 81 frames at 320 px: 1.75). The hand-held
    prior (1.45 m) is 17 % short of that virtual camera's height, so only the floor is held."""
    from stages.ingest import load

    cap = load(shared_capture("replica-office0"), tmp_path / "work")
    cap = cap.with_frames(cap.frames[::2])
    got, facts = _run_sfm(cap, tmp_path)
    assert facts["scale_from"]["method"] == "depth" and facts["registered"] >= 38
    # The office's repeated furniture makes false pairs that the model rightly leaves out
    # (measured on all 81 views: 5 of 382 contradicted, 15-39 inliers each): none is strong
    # enough to count against it.
    assert facts["agreement"]["agrees"] and facts["mapper"] == "incremental"
    rec = pycolmap.Reconstruction(tmp_path / "out" / "sparse")
    ims = sorted(rec.images.values(), key=lambda im: im.name)
    rots = np.array([im.cam_from_world().rotation.matrix() for im in ims])  # [C, 3, 3]
    centres = np.array([im.projection_center() for im in ims])  # [C, 3]
    points = np.array([p.xyz for p in rec.points3D.values()])  # [N, 3]
    s, f = scale_from_priors(centres, rots[:, 0], rots[:, 1], points)
    assert f["camera_height_m"] / s == pytest.approx(1.76, rel=0.05), f


@pytest.mark.slow
def test_same_photos_same_poses_on_two_threads(tmp_path: Path) -> None:
    # poses.deterministic (the default): two SfM runs of the same photos on two threads give
    # the same poses and track depth bit for bit (SIFT and mapping on one thread, each
    # pair's RANSAC from the seed). Measured: with SIFT or mapping on two threads the two
    # runs' poses differed. Slow: two SfM runs (~20 s each on a busy machine)
    from stages.synth import make_room

    room = make_room(tmp_path / "room", views=20, seed=0, size=(160, 120), photos_only=True)
    got = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        cap, facts = _run_sfm(read_layout(room), tmp_path / name, threads=2, scale_from="none")
        assert facts["threads"] == 2 and facts["registered"] >= 16, facts
        got.append(cap)
    a, b = got
    assert [f.stem for f in a.frames] == [f.stem for f in b.frames]
    for fa, fb in zip(a.frames, b.frames, strict=True):
        assert (fa.pose is None) == (fb.pose is None)
        if fa.pose is not None:
            assert np.array_equal(np.asarray(fa.pose), np.asarray(fb.pose)), fa.stem
        if fa.depth is not None:
            assert np.array_equal(np.load(fa.depth), np.load(fb.depth)), fa.stem


def test_sfm_keyframes_map_every_other_view_and_register_the_rest(room: Path, tmp_path: Path):
    """keyframes.at_least 10 on 24 views (+ 2 blank ones): every 2nd view is mapped first,
    the others registered to that model with its poses held; as accurate as mapping all."""
    cap = _with_blanks(read_layout(room), 2, tmp_path)
    keyframes = KeyframesConfig(at_least=10, hold=0.9)
    got, facts = _run_sfm(cap, tmp_path, threads=1, max_features=2048, keyframes=keyframes)
    m = pose_metrics({f.stem: f.pose for f in got.frames}, _gt_poses(room))
    # 26 views: every 2nd is 13, blank0 among them; its model holds 12 >= 0.9 x 13
    assert facts["keyframes"] == {
        "tried": [{"every": 2, "views": 13, "held": 12}],
        "every": 2,
        "mapped": 13,
        "held": 12,
    }
    assert (facts["registered"], facts["unregistered"]) == (24, ["blank0", "blank1"])
    assert m["ate_rmse_m"] < 0.03 and m["rot_err_deg_median"] < 0.6
    assert facts["agreement"]["agrees"]


def test_sfm_keyframes_with_sequential_pairs_leave_out_those_between_registered_views(
    room: Path, tmp_path: Path
):
    """Sequential matching with keyframes: the pairs between two views registered to the
    keyframes' model, more than 2 apart, are not matched (keyframes.skip_pairs), and the
    model is the one all the pairs give, as accurate and with as many views."""
    cap = _with_blanks(read_layout(room), 2, tmp_path)
    got = _run_sfm_on_off(
        cap,
        tmp_path,
        lambda skip: {"keyframes": KeyframesConfig(at_least=10, hold=0.3, skip_pairs=skip)},
        matching=MatchingConfig(kind="sequential"),
    )
    (cap_s, skip), (cap_a, every) = got[True], got[False]
    # 26 views, steps 1 ... 16: those of 4, 8 and 16 steps between odd views, 11 + 9 + 5
    assert skip["match_pairs"]["pairs_left_out"] == 25
    assert "pairs_left_out" not in every["match_pairs"]
    assert skip["match_pairs"]["pairs"] == every["match_pairs"]["pairs"] - 25
    assert skip["keyframes"]["every"] == every["keyframes"]["every"] == 2
    assert skip["registered"] == every["registered"] >= 23  # the subset holds 5 of 13
    gt = _gt_poses(room)
    ms, ma = (pose_metrics({f.stem: f.pose for f in c.frames}, gt) for c in (cap_s, cap_a))
    assert ms["ate_rmse_m"] < ma["ate_rmse_m"] + 0.003 and ms["ate_rmse_m"] < 0.03
    assert ms["rot_err_deg_median"] < ma["rot_err_deg_median"] + 0.1


def test_sfm_keyframes_that_do_not_hold_map_every_view(room: Path, tmp_path: Path) -> None:
    """A subset whose model holds fewer than keyframes.hold of it (blank0 is in it) gives way
    to mapping every view, as without keyframes."""
    cap = _with_blanks(read_layout(room), 1, tmp_path)
    keyframes = KeyframesConfig(at_least=10, hold=1.0)
    got, facts = _run_sfm(cap, tmp_path, threads=1, max_features=2048, keyframes=keyframes)
    (tried,) = facts["keyframes"].pop("tried")  # measured: the subset's model held 10
    assert (tried["every"], tried["views"]) == (2, 13) and tried["held"] < 13
    assert facts["keyframes"] == {}  # no subset kept: every view mapped together
    assert facts["registered"] == 24


def test_keyframe_stride_leaves_at_least_so_many_views() -> None:
    assert [keyframe_stride(n, 200) for n in (100, 399, 400, 799, 800, 1600)] == [1, 1, 2, 2, 4, 8]
    assert keyframe_stride(5000, 0) == 1  # 0: always every view


# ---- a lens with distortion: the frames made pinhole -----------------------------------------


def _through_lens(rgb: np.ndarray, intr: Intrinsics, k1: float) -> np.ndarray:
    """The pinhole photo `rgb` as a lens with radial distortion k1 (same focal and principal
    point) takes it: each pixel of the result reads the pinhole photo where its ray lands
    (the ray undistorted by fixed-point iteration; bilinear)."""
    from scipy import ndimage

    h, w = rgb.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    x, y = xd.copy(), yd.copy()
    # by hand, not kornia's undistort_points: the product undistorts with kornia, and a
    # convention both shared would pass unseen
    for _ in range(30):
        r2 = x * x + y * y
        x, y = xd / (1 + k1 * r2), yd / (1 + k1 * r2)
    rows, cols = y * intr.fy + intr.cy, x * intr.fx + intr.cx
    return (
        np.stack(
            [
                ndimage.map_coordinates(
                    rgb[..., c].astype(np.float64), [rows, cols], order=1, mode="nearest"
                )
                for c in range(3)
            ],
            -1,
        )
        .round()
        .astype(np.uint8)
    )


def test_largest_shift_is_where_the_lens_moves_the_corners_most() -> None:
    from stages.poses.undistort import largest_shift_px

    intr = Intrinsics(100.0, 100.0, 49.5, 39.5, 100, 80)
    assert largest_shift_px(intr) == 0.0
    # corner (0, 0): x = -0.495, y = -0.395, r^2 = 0.4011; moved k1 r^2 of its radius
    r = np.hypot(49.5, 39.5)
    got = largest_shift_px(Intrinsics(100.0, 100.0, 49.5, 39.5, 100, 80, (-0.05, 0.0, 0.0, 0.0)))
    assert got == pytest.approx(0.05 * (r / 100) ** 2 * r, rel=1e-9)


def _one_track(model: str, params: list[float]) -> tuple[pycolmap.Reconstruction, pycolmap.Image]:
    """A model of one 64x48 camera at the origin seeing the point (0.2, 0.1, 1) detected at
    (40, 30) in COLMAP's pixels, where a pinhole of focal 50 and centre (32, 24) projects it to
    (42, 29): a keypoint 2.2 px off its point's projection."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model=model, width=64, height=48, params=params)
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    kp = pycolmap.Point2DList([pycolmap.Point2D(np.array([40.0, 30.0]))])
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name="a", points2D=kp, camera_id=1, image_id=1), pycolmap.Rigid3d()
    )
    track = pycolmap.Track()
    track.add_element(1, 0)
    rec.add_point3D(np.array([0.2, 0.1, 1.0]), track)
    return rec, rec.image(1)


def test_track_pixels_are_the_keypoints_unless_the_frame_was_made_pinhole() -> None:
    from stages.poses.models import track_pixels

    pinhole = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)  # the project's pixels
    lensed = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48, (-0.1, 0.0, 0.0, 0.0))
    # a pinhole camera (stated intrinsics): where the keypoint was detected
    xy, z = track_pixels(*_one_track("PINHOLE", [50, 50, 32, 24]), pinhole)
    assert xy.tolist() == [[39.5, 29.5]] and z.tolist() == [1.0]
    # SfM's lens kept by the frame: the detection, through that lens
    radial = [50, 32, 24, -0.1]
    xy, _ = track_pixels(*_one_track("SIMPLE_RADIAL", radial), lensed)
    assert xy.tolist() == [[39.5, 29.5]]
    # the frame made pinhole (poses.undistort): where that pinhole camera sees the point
    xy, z = track_pixels(*_one_track("SIMPLE_RADIAL", radial), pinhole)
    assert xy == pytest.approx(np.array([[41.5, 28.5]])) and z.tolist() == [1.0]


def _track_errors(got: Capture, cap: Capture, s: float) -> np.ndarray:
    """Relative error of every track depth (photos-only frames: the tracks are the depth, in
    SfM units times s) against the exact depth map of the pinhole render at its pixel."""
    exact = {f.stem: f.depth for f in cap.frames}
    errs = []
    for f in got.frames:
        t = np.load(f.depth) * s
        d = read_depth(exact[f.stem], cap.depth_scale, cap.depth_invalid)
        ok = (t > 0) & (d > 0)
        errs.append(np.abs(t[ok] - d[ok]) / d[ok])
    return np.concatenate(errs)


def test_photos_through_a_barrel_lens_become_pinhole_frames(room: Path, tmp_path: Path) -> None:
    """Photos taken through a barrel lens (k1 -0.08: the corners 6 px in at 192x144): SfM
    finds the lens, and with poses.undistort the frames take undistorted copies and pinhole
    intrinsics, so that the sweep, the plane fill and fusion (pinhole) read the rays SfM
    found; each track's depth lies where that pinhole camera sees it. Off, the frames keep
    SfM's k1 and the photos, and the tracks sit where the lens put them."""
    k1 = -0.08
    cap = read_layout(room)
    true = cap.frames[0].intrinsics
    (tmp_path / "lens").mkdir()
    frames = []
    for f in cap.frames:
        rgb = np.asarray(Image.open(f.image).convert("RGB"))
        path = _write_png(tmp_path / "lens" / f"{f.stem}.png", _through_lens(rgb, true, k1))
        frames.append(Frame(f.stem, path, true))  # photos only: the tracks are the depth
    lens = Capture(tmp_path / "lens", tuple(frames))
    runs = _run_sfm_on_off(
        lens, tmp_path, lambda on: {"undistort": on}, self_calibrate=True, scale_from="none"
    )
    got, facts = runs[True]
    (est,) = facts["camera"]["estimated"]
    assert est["dist"][0] == pytest.approx(k1, abs=0.01)  # SfM found the lens (-0.0797)
    assert facts["undistorted"] == len(got.frames) == 24
    rendered = {f.stem: f.image for f in cap.frames}
    inner = (slice(8, -8), slice(8, -8))  # away from the border the lens did not see
    for f in got.frames:
        assert (
            f.intrinsics.dist == ()
            and f.image == tmp_path / "True" / "out" / "images" / f"{f.stem}.png"
        )
        und, lensed, pinhole = (
            np.asarray(Image.open(p).convert("RGB")).astype(np.float64)
            for p in (f.image, tmp_path / "lens" / f"{f.stem}.png", rendered[f.stem])
        )
        # back where the pinhole render has it: mean |difference| ~1/4 of the lens's
        assert np.abs(und - pinhole)[inner].mean() < 0.5 * np.abs(lensed - pinhole)[inner].mean()
    off, facts_off = runs[False]
    assert facts_off["undistorted"] == 0
    assert (
        off.frames[0].intrinsics.dist[0] == est["dist"][0]
        and off.frames[0].image == lens.frames[0].image
    )
    # the same model both ways (one seed): its scale to metres from the exact poses
    s = pose_metrics({f.stem: f.pose for f in got.frames}, _gt_poses(room))["align_scale"]
    on_err, off_err = _track_errors(got, cap, s), _track_errors(off, cap, s)
    # measured: median 0.27 % against 0.37 %, 90th percentile 1.0 % against 1.5 %
    assert np.median(on_err) < 0.005
    assert np.percentile(on_err, 90) < 0.8 * np.percentile(off_err, 90)

"""Poses from photos: pycolmap SIFT + matching + incremental or global mapping, metric scale.
SIFT reads the capture's full-size images when ingest downscaled them (fullsize.py).

Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), the project at
(0, 0) (camera.py), so principal points and keypoints are shifted by 0.5 at the boundary.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import image_size, write_depth_npy, write_json
from stages.common.progress import Progress, progress
from stages.poses import agreement, calib, fullsize, matching, stated
from stages.poses import models as models_detail
from stages.poses import undistort as lens
from stages.poses.config import PosesConfig, PosesInputs, PosesOutputs
from stages.poses.matching import keyframe_stride
from stages.poses.models import metric_scale, sparse_depth

log = logging.getLogger(__name__)

MIN_REGISTERED = 3  # fewer registered images than this is always a failure
SELF_CALIB_WARNING = (
    "self-calibration is unreliable indoors (short baselines, planar walls): focal length "
    "and distortion may be wrong, and poses with them"
)


def run(cfg: PosesConfig, inputs: PosesInputs, out: Path) -> PosesOutputs:
    """Register the capture's photos, scale the model to metres, write frames.json + sfm.json."""
    log.debug("poses: sfm %s", cfg)
    cap = Capture.load(inputs.frames)
    n = len(cap.frames)
    if n == 0:
        raise BlunfError(f"{inputs.frames}: the capture has no frames")
    stems = [f.stem for f in cap.frames]
    if len(set(stems)) != n:
        dup = next(s for s in stems if stems.count(s) > 1)
        raise BlunfError(f"{inputs.frames}: frame stem {dup!r} appears twice")
    out = Path(out)
    work = out / "work"
    img_dir = work / "images"
    db = work / "database.db"
    img_dir.mkdir(parents=True)
    threads = cfg.threads or len(os.sched_getaffinity(0))
    pycolmap.set_random_seed(cfg.seed)
    seen = fullsize.sfm_frames(cap.frames, cfg.full_size_images)  # the images SfM reads
    names = _link_images(seen, img_dir)  # COLMAP image name of each frame
    side = fullsize.max_side(cfg.max_image_size, cfg.full_size_max_side, seen, cap.frames)
    sift_cfg = replace(cfg, max_image_size=side)
    facts: dict = {"impl": "sfm", "total": n, "threads": threads}
    guessed = calib.unknown(cap.frames)  # intrinsics not given: SfM estimates them
    refine = cfg.self_calibrate is True or guessed
    checked = None  # auto: the stated intrinsics against bundle adjustment (stated.py)

    clock = [(time.perf_counter(), time.process_time())]  # (wall, CPU of all threads)
    with _colmap_log_level():  # pycolmap extracts and matches in one call each: elapsed only
        with progress("sfm extract"):
            facts["sift_first_octave"] = octave = first_octave(sift_cfg, seen)
            facts["camera"] = _extract(sift_cfg, octave, seen, names, db, img_dir, threads)
        clock.append((time.perf_counter(), time.process_time()))
        with progress("sfm match"):
            m = matching.match(cfg, db, names, threads)
            facts["matching"], facts["matching_detail"] = m.pop("kind"), m.pop("detail")
            facts["match_pairs"] = m
        clock.append((time.perf_counter(), time.process_time()))
        recs, facts["keyframes"] = _map(cfg, db, img_dir, work / "models", threads, refine)
        if cfg.self_calibrate == "auto" and not guessed and recs:
            biggest = max(recs, key=lambda r: r.num_reg_images())
            checked = stated.check(biggest, cfg.stated_focal_tolerance)
            if checked["adopt"]:
                log.warning("sfm: the stated focal does not fit the photos: estimating it")
                stated.to_self_calibration(db, checked)
                recs, facts["keyframes"] = _map(
                    cfg, db, img_dir, work / "models-refined", threads, True
                )
                refine = True
        named = dict(zip(names, stems, strict=True))  # COLMAP image name -> frame stem
        recs, facts["mapper"], facts["agreement"] = _agreeing(
            cfg, recs, named, db, img_dir, work, threads, refine
        )
        clock.append((time.perf_counter(), time.process_time()))
    spans = list(zip(("extract", "match", "map"), clock[:-1], clock[1:], strict=True))
    facts["seconds"] = {k: b[0] - a[0] for k, a, b in spans}
    facts["cpu_seconds"] = {k: b[1] - a[1] for k, a, b in spans}
    facts["models"] = len(recs)
    facts["images"] = fullsize.facts(seen, cap.frames) | {"max_side": side}

    recs = sorted(recs, key=lambda r: r.num_reg_images(), reverse=True)  # largest first
    rec = recs[0] if recs else None
    index = {name: i for i, name in enumerate(names)}
    members = [sorted(index[im.name] for im in r.images.values() if im.has_pose) for r in recs]
    facts.update(models_detail.describe(members, stems, facts["mapper"]))
    if not facts["agreement"].get("agrees", True):
        facts["warnings"].append(agreement.warning(facts["agreement"]))
        log.warning("sfm: %s", facts["warnings"][-1])
    ids = {}  # COLMAP image name -> image id, registered images of the largest model
    if rec is not None:
        ids = {im.name: im.image_id for im in rec.images.values() if im.has_pose}
    kept = [i for i, name in enumerate(names) if name in ids]  # indices of registered frames
    k = len(kept)
    need = max(MIN_REGISTERED, int(np.ceil(cfg.min_registered_frac * n)))
    if k < need:
        split = "; ".join(", ".join(g["spans"]) for g in facts["groups"])
        raise BlunfError(
            f"sfm: only {k} of {n} images registered (need {need}; poses.min_registered_frac="
            f"{cfg.min_registered_frac}): too little texture or overlap between photos?"
            + (f" SfM made {len(recs)} models: {split}" if len(recs) > 1 else "")
        )
    assert rec is not None
    fullsize.to_working_size(rec, names, cap.frames)  # from here on, the frames' pixels
    unregistered = [stems[i] for i in sorted(set(range(n)) - set(kept))]
    if unregistered:
        log.warning("sfm: %d of %d images did not register: %s", n - k, n, unregistered)
    facts.update(registered=k, unregistered=unregistered)
    if refine:
        cams = sorted({rec.image(ids[names[i]]).camera_id for i in kept})
        facts["camera"]["estimated"] = [calib.intrinsics_of(rec.camera(c)).to_json() for c in cams]
    if guessed:
        facts["intrinsics"] = calib.report(rec, cap.frames, {i: ids[names[i]] for i in kept})
    elif checked is not None:
        first = rec.image(ids[names[kept[0]]]).camera_id
        adopted = calib.intrinsics_of(rec.camera(first)) if refine else None
        facts["intrinsics"] = stated.facts(cap.frames[kept[0]].intrinsics, checked, adopted)
        log.info("sfm: intrinsics: %s", facts["intrinsics"]["reason"])
    else:
        facts["intrinsics"] = {"source": "self-calibrated" if refine else "given"}
    if refine:  # the frames take the estimate, their sensor depth follows it
        cap, facts["undistorted"] = _refined(
            cap, rec, [(i, ids[names[i]]) for i in kept], out, cfg.undistort
        )
        facts["depth_registered"] = (out / "depth").is_dir()

    t4 = time.perf_counter()
    s, facts["scale_from"] = metric_scale(cfg, cap, rec, [ids[names[i]] for i in kept], kept)
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(), np.zeros(3)))
    facts["seconds"]["scale"] = time.perf_counter() - t4
    facts["scale"] = s
    facts["mean_reproj_error_px"] = float(rec.compute_mean_reprojection_error())
    facts["points3D"] = int(rec.num_points3D())
    facts["mean_track_length"] = float(rec.compute_mean_track_length())

    frames = []
    sparse = out / "sparse_depth"
    for i in kept:
        im = rec.image(ids[names[i]])
        w2c = np.eye(4)
        w2c[:3] = im.cam_from_world().matrix()  # [3, 4]
        f = replace(cap.frames[i], pose=np.linalg.inv(w2c))
        intr = f.intrinsics
        if f.depth is None:  # photos only: the tracks' depths are all the depth there is
            sparse.mkdir(exist_ok=True)
            write_depth_npy(sparse / f"{f.stem}.npy", sparse_depth(rec, im, intr))
            f = replace(f, depth=sparse / f"{f.stem}.npy")
        frames.append(f)
    facts["sparse_depth"] = sparse.is_dir()
    outs = PosesOutputs.at(out)
    # The SfM world is not the capture's: a gravity vector given in the capture's frame means
    # nothing here, so alignment must find the floor itself.
    # SfM's own frame: nothing of the capture's world (its gravity, its offset) holds in it
    replace(cap, gravity=None, origin=(0.0, 0.0, 0.0)).with_frames(frames).save(outs.frames)
    (out / "sparse").mkdir()
    rec.write(out / "sparse")
    rec.export_PLY(out / "sparse.ply")
    # COLMAP binary model, metric; its images are named <capture index:06d>_<stem><ext>
    facts.update(sparse_ply="sparse.ply", sparse_model="sparse")
    shutil.rmtree(work)  # database and image links: large, and only needed while mapping
    write_json(outs.sfm, facts)
    log.info(
        "sfm: %d/%d registered, %d points, reproj %.2f px, scale %.4g (%s)",
        k,
        n,
        facts["points3D"],
        facts["mean_reproj_error_px"],
        s,
        facts["scale_from"]["method"],
    )
    return outs


def _refined(
    cap: Capture, rec: pycolmap.Reconstruction, kept: list, out: Path, undistort: bool
) -> tuple[Capture, int]:
    """(`cap` with each registered frame (kept: (capture index, image id)) taking SfM's
    estimate of its camera, the number of frames made pinhole). With `undistort`, a frame
    whose lens model moves its pixels by more than undistort.MIN_SHIFT_PX takes an
    undistorted copy of its photo under out/images and that camera without distortion
    (undistort.py). Its sensor depth map is resampled into the camera it takes, under
    out/depth (stated.register_depth: a depth map shares its frame's intrinsics)."""
    frames = list(cap.frames)
    made = 0
    folder = out / "depth"
    for i, iid in kept:
        f = frames[i]
        intr = calib.intrinsics_of(rec.camera(rec.image(iid).camera_id))
        if undistort and lens.largest_shift_px(intr) > lens.MIN_SHIFT_PX:
            photo = out / "images" / f"{f.stem}.png"
            intr = lens.undistorted_copy(Path(f.image), intr, photo)
            f = replace(f, image=photo)
            made += 1
        if f.depth is not None and intr != f.intrinsics:
            folder.mkdir(exist_ok=True)
            dst = folder / f"{f.stem}.npy"
            stated.register_depth(
                Path(f.depth), f.intrinsics, intr, dst, cap.depth_scale, cap.depth_invalid
            )
            f = replace(f, depth=dst)
        frames[i] = replace(f, intrinsics=intr, calib="self-calibrated")
    return cap.with_frames(tuple(frames)), made


@contextlib.contextmanager
def _colmap_log_level():
    """COLMAP's own (glog) INFO lines only when this module logs at DEBUG; restored after."""
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if log.isEnabledFor(logging.DEBUG) else 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _link_images(frames: tuple[Frame, ...], img_dir: Path) -> list[str]:
    """Symlink every frame's image into one folder, named so that sorting keeps capture order."""
    names = []
    for i, f in enumerate(frames):
        src = Path(f.image)
        if not src.is_file():
            raise BlunfError(f"{src}: image of frame {f.stem!r} not found")
        name = f"{i:06d}_{f.stem}{src.suffix.lower()}"
        os.symlink(src.resolve(), img_dir / name)
        names.append(name)
    return names


def _colmap_camera(intr: Intrinsics) -> tuple[str, str]:
    """COLMAP model name and parameter string for fixed intrinsics (principal point + 0.5)."""
    base = [intr.fx, intr.fy, intr.cx + 0.5, intr.cy + 0.5]
    dist = list(intr.dist)
    if not any(dist):
        model, extra = "PINHOLE", []
    elif len(dist) <= 4:
        model, extra = "OPENCV", dist + [0.0] * (4 - len(dist))
    elif len(dist) in (5, 8):
        model, extra = "FULL_OPENCV", dist + [0.0] * (8 - len(dist))
    else:
        raise BlunfError(f"intrinsics: {len(dist)} distortion coefficients (want 4, 5 or 8)")
    return model, ",".join(repr(float(v)) for v in base + extra)


def _extract(
    cfg: PosesConfig,
    octave: int,
    frames: tuple[Frame, ...],
    names: list[str],
    db: Path,
    img_dir: Path,
    threads: int,
) -> dict:
    """SIFT features into the database, from SIFT's first `octave` (first_octave); one fixed
    camera per distinct intrinsics."""
    eo = pycolmap.FeatureExtractionOptions()
    eo.num_threads = 1 if cfg.deterministic else threads  # see PosesConfig.deterministic
    eo.use_gpu = False
    eo.max_image_size = cfg.max_image_size
    eo.sift.max_num_features = cfg.max_features
    eo.sift.first_octave = octave
    log.info(
        "sfm: SIFT on %d images (%d threads, first octave %d)",
        len(frames),
        threads,
        eo.sift.first_octave,
    )
    if calib.unknown(frames):
        log.info("sfm: intrinsics not given: estimating them (%s)", SELF_CALIB_WARNING)
        return calib.extract(frames, names, db, img_dir, eo) | {"warning": SELF_CALIB_WARNING}
    if cfg.self_calibrate is True:
        log.warning("sfm: %s", SELF_CALIB_WARNING)
        sizes = {image_size(f.image) for f in frames}
        mode = pycolmap.CameraMode.SINGLE if len(sizes) == 1 else pycolmap.CameraMode.PER_IMAGE
        ro = pycolmap.ImageReaderOptions()
        ro.camera_model = "SIMPLE_RADIAL"
        pycolmap.extract_features(db, img_dir, names, mode, ro, eo, pycolmap.Device.cpu)
        cams = 1 if len(sizes) == 1 else len(frames)
        return {
            "fixed": False,
            "model": "SIMPLE_RADIAL",
            "cameras": cams,
            "warning": SELF_CALIB_WARNING,
        }
    groups: dict[Intrinsics, list[str]] = {}
    for f, name in zip(frames, names, strict=True):
        w, h = image_size(f.image)
        intr = f.intrinsics
        if (intr.width, intr.height) != (w, h):
            log.warning(
                "sfm: %s is %dx%d, intrinsics are for %dx%d: rescaling them",
                f.image,
                w,
                h,
                intr.width,
                intr.height,
            )
            intr = intr.scaled(w, h)
        groups.setdefault(intr, []).append(name)
    models = set()
    for intr, group in groups.items():
        ro = pycolmap.ImageReaderOptions()
        ro.camera_model, ro.camera_params = _colmap_camera(intr)
        models.add(ro.camera_model)
        pycolmap.extract_features(
            db, img_dir, group, pycolmap.CameraMode.SINGLE, ro, eo, pycolmap.Device.cpu
        )
    return {"fixed": True, "model": "/".join(sorted(models)), "cameras": len(groups)}


def first_octave(cfg: PosesConfig, frames: tuple[Frame, ...]) -> int:
    """SIFT's first octave: -1 (images doubled) when the longest side SIFT reads, the largest
    image's capped at max_image_size, is below cfg.double_below; else 0."""
    longest = min(cfg.max_image_size, max(max(image_size(f.image)) for f in frames))
    return -1 if longest < cfg.double_below else 0


def _agreeing(
    cfg: PosesConfig,
    recs: list[pycolmap.Reconstruction],
    stems: dict[str, str],
    db: Path,
    img_dir: Path,
    work: Path,
    threads: int,
    refine: bool,
) -> tuple[list[pycolmap.Reconstruction], str, dict]:
    """(the models, the mapper that made them, the largest one checked against the verified
    pairs: agreement.py). stems: COLMAP image name -> frame stem. With mapper "auto", an
    incremental model that contradicts the pairs is mapped again by the global mapper, which
    places every view at once from all the pairs' rotations, and the largest model that
    contradicts fewer strong pairs is kept (a tie keeps the incremental one)."""
    used = "incremental" if cfg.mapper == "auto" else cfg.mapper
    if not recs:
        return recs, used, {}
    largest = max(recs, key=lambda r: r.num_reg_images())
    with progress("sfm check"):
        facts = agreement.check(largest, db, stems)
    if facts["agrees"] or cfg.mapper != "auto":
        return recs, used, facts
    log.warning("sfm: %s; mapping again with the global mapper", agreement.warning(facts))
    glob = replace(cfg, mapper="global")
    other, _ = _map(glob, db, img_dir, work / "models-global", threads, refine)
    if not other:
        return recs, used, facts | {"global": "no model"}
    g = max(other, key=lambda r: r.num_reg_images())
    gfacts = agreement.check(g, db, stems)
    key = (gfacts["strong_contradicted"], -g.num_reg_images())
    if key < (facts["strong_contradicted"], -largest.num_reg_images()):
        gfacts["incremental"] = agreement.counts(facts)
        return other, "global", gfacts | {"remapped": agreement.warning(facts)}
    facts["global"] = agreement.counts(gfacts)
    return recs, used, facts


def _map(
    cfg: PosesConfig, db: Path, img_dir: Path, models: Path, threads: int, refine: bool
) -> tuple[list[pycolmap.Reconstruction], dict]:
    """Run the chosen mapper; returns every model it made (possibly none) and the keyframes'
    facts (_incremental; {} for the global mapper). refine: estimate the focal length and
    distortion too."""
    models.mkdir(parents=True)
    fixed = not refine
    if cfg.deterministic:  # a multi-threaded bundle adjustment sums in a varying order
        threads = 1
    if cfg.mapper in ("auto", "incremental"):
        names = sorted(os.listdir(img_dir))
        with progress("sfm map", len(names), "image") as bar:  # registered
            recs, facts = _incremental(cfg, db, img_dir, models, threads, fixed, names, bar)
        return recs, facts
    else:
        log.info("sfm: global mapping")
        g = pycolmap.GlobalPipelineOptions()
        g.num_threads = threads
        g.random_seed = cfg.seed
        g.min_model_size = MIN_REGISTERED
        ba = g.mapper.bundle_adjustment
        ba.ceres.use_gpu = False
        g.mapper.global_positioning.use_gpu = False
        if fixed:
            ba.refine_focal_length = False
            ba.refine_principal_point = False
            ba.refine_extra_params = False
        with progress("sfm map"):
            made = pycolmap.global_mapping(db, img_dir, models, g)
    return list(made.values()), {}


def _incremental_options(
    cfg: PosesConfig, threads: int, fixed: bool
) -> pycolmap.IncrementalPipelineOptions:
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = threads
    o.random_seed = cfg.seed
    o.mapper.random_seed = o.triangulation.random_seed = cfg.seed
    o.min_model_size = MIN_REGISTERED
    o.ba_global_max_refinements = cfg.ba.global_max_refinements
    o.ba_local_max_refinements = cfg.ba.local_max_refinements
    o.ba_global_frames_ratio = cfg.ba.global_growth
    o.ba_global_points_ratio = cfg.ba.global_growth
    if fixed:
        o.ba_refine_focal_length = False
        o.ba_refine_principal_point = False
        o.ba_refine_extra_params = False
        o.mapper.abs_pose_refine_focal_length = False
        o.mapper.abs_pose_refine_extra_params = False
    return o


def _incremental(
    cfg: PosesConfig,
    db: Path,
    img_dir: Path,
    models: Path,
    threads: int,
    fixed: bool,
    names: list[str],
    bar: Progress,
) -> tuple[list[pycolmap.Reconstruction], dict]:
    """The incremental mapper's models of the images `names` (capture order), and the facts of
    the keyframes (KeyframesConfig): every k-th view mapped first, the rest registered to
    that model with its poses held; every view at once when k is 1 or the subsets fail."""
    first, then = (lambda: bar.update(2)), (lambda: bar.update(1))  # views registered
    facts: dict = {}
    k = keyframe_stride(len(names), cfg.keyframes.at_least)
    while k > 1:
        sub = names[::k]
        o = _incremental_options(cfg, threads, fixed)
        o.image_names = sub
        part = models / f"every-{k}"
        part.mkdir()
        log.info("sfm: incremental mapping of one view in %d (%d views)", k, len(sub))
        recs = pycolmap.incremental_mapping(db, img_dir, part, o, "", first, then)
        best = max(recs, key=lambda i: recs[i].num_reg_images(), default=None)
        held = recs[best].num_reg_images() if best is not None else 0
        facts.setdefault("tried", []).append({"every": k, "views": len(sub), "held": held})
        if held >= cfg.keyframes.hold * len(sub):
            o = _incremental_options(cfg, threads, fixed)
            o.fix_existing_frames = True  # the subset's poses held: registering is local
            o.ba_local_max_refinements = cfg.keyframes.register_refinements
            o.ba_local_max_num_iterations = cfg.keyframes.register_iterations
            o.ba_global_frames_ratio = o.ba_global_points_ratio = NO_GROWTH
            o.ba_global_frames_freq = o.ba_global_points_freq = NO_FREQ
            rest = models / "rest"
            rest.mkdir()
            log.info("sfm: registering the other %d views to it", len(names) - len(sub))
            recs = pycolmap.incremental_mapping(
                db, img_dir, rest, o, str(part / str(best)), lambda: None, then
            )
            facts.update(every=k, mapped=len(sub), held=held)
            return list(recs.values()), facts
        log.warning(
            "sfm: one view in %d: its model holds %d of %d (keyframes.hold %.2f): fewer skipped",
            k,
            held,
            len(sub),
            cfg.keyframes.hold,
        )
        bar.moveto(0)
        k //= 2
    log.info("sfm: incremental mapping")
    o = _incremental_options(cfg, threads, fixed)
    recs = pycolmap.incremental_mapping(db, img_dir, models, o, "", first, then)
    return list(recs.values()), facts


NO_GROWTH = 1e6  # a global bundle adjustment when the model grows this many times: never
NO_FREQ = 1 << 30  # ...or after this many images or points

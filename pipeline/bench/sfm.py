"""The poses stage's SfM against plain pycolmap on the same photos, in the same run.

    python -m pipeline.bench.sfm CAPTURE [--frames N] [--repeats R] [--threads T]
                                 [--config configs/phone.yaml] [--set poses.key=v ...]

The reference is what pycolmap's documentation has a user run: `extract_features` with its
default options (SIFT, images up to 3200 px, 8192 features, one SIMPLE_RADIAL camera whose
focal length it estimates), `match_sequential` with its default pairing, and
`incremental_mapping` with its default options. The poses stage (stages/poses/sfm.py, the
whole stage: SfM, metric scale, sparse depth) runs on the same images with the capture's
intrinsics and no depth or poses, as a photos-only run gives it. Both take `threads` threads
and the same random seed; the two alternate, R times each, on one machine, so their ratio
holds when the machine is loaded. Poses are scored against the capture's ground truth
(gt/poses.json, else the frames' own poses) after a similarity (stages.evaluate.poses).
Prints a table of medians (wall and CPU seconds, ATE, registered views) and the ratios.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from pipeline.bench.target_runs import med
from pipeline.config import load_config
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.evaluate.poses import pose_metrics
from stages.ingest import load
from stages.ingest.select import select_indices
from stages.poses import sfm
from stages.poses.config import PosesConfig, PosesInputs

log = logging.getLogger(__name__)

SEED = 0  # random seed of both SfM runs
Poses = dict[str, np.ndarray]  # stem -> [4, 4] camera-to-world


def photos(capture: Path, frames: int, work: Path) -> tuple[Capture, Poses]:
    """The capture's N evenly spread frames with images and intrinsics only (no depth, poses,
    labels or gravity), and their ground-truth poses."""
    cap = load(Path(capture), work / "ingest")
    gt_file = Path(cap.gt) / "poses.json" if cap.gt is not None else None
    if gt_file is not None and gt_file.is_file():
        gt = {k: np.asarray(v, np.float64) for k, v in read_json(gt_file).items()}
    else:
        gt = {f.stem: np.asarray(f.pose, np.float64) for f in cap.frames if f.pose is not None}
    picked = [cap.frames[i] for i in select_indices(len(cap.frames), frames)]
    gt = {f.stem: gt[f.stem] for f in picked if f.stem in gt}
    if len(gt) < 3:
        raise BlunfError(f"{capture}: fewer than 3 of the chosen frames have ground-truth poses")
    bare = [replace(f, depth=None, pose=None, label=None, instance=None) for f in picked]
    return replace(cap.with_frames(bare), gravity=None, classes={}, ignore=(), gt=None), gt


def reference(cap: Capture, work: Path, threads: int) -> tuple[Poses, dict]:
    """Plain pycolmap, options at their defaults but the thread count and the seed.
    Returns (poses of the largest model's registered images, facts)."""
    img_dir, db, models = work / "images", work / "database.db", work / "models"
    img_dir.mkdir(parents=True)
    models.mkdir()
    stem_of = {}
    for f in cap.frames:
        name = f"{f.stem}{Path(f.image).suffix.lower()}"
        os.symlink(Path(f.image).resolve(), img_dir / name)
        stem_of[name] = f.stem
    pycolmap.set_random_seed(SEED)
    eo = pycolmap.FeatureExtractionOptions()
    eo.num_threads = threads
    pycolmap.extract_features(db, img_dir, extraction_options=eo, device=pycolmap.Device.cpu)
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = threads
    pycolmap.match_sequential(db, matching_options=mo, device=pycolmap.Device.cpu)
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = threads
    o.random_seed = SEED
    recs = pycolmap.incremental_mapping(db, img_dir, models, o)
    if not recs:
        return {}, {"models": 0}
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    poses = {}
    for im in rec.images.values():
        if im.has_pose:
            w2c = np.eye(4)
            w2c[:3] = im.cam_from_world().matrix()
            poses[stem_of[im.name]] = np.linalg.inv(w2c)
    focal = [float(c.focal_length) for c in rec.cameras.values()]
    return poses, {"models": len(recs), "focal_px": focal}


def poses_config(config: Path | None, sets: Sequence[str], threads: int) -> PosesConfig:
    """The poses stage's config of a run (defaults, `config`, then `sets`) on `threads`."""
    cfg = load_config(config, [*sets])["poses"]
    return replace(cfg, impl="sfm", threads=threads, seed=SEED)


def ours(cap: Capture, work: Path, cfg: PosesConfig) -> tuple[Poses, dict]:
    """The poses stage. Returns (poses, sfm.json facts)."""
    (work / "in").mkdir(parents=True)
    cap.save(work / "in" / "frames.json")
    outs = sfm.run(cfg, PosesInputs(work / "in" / "frames.json"), work / "out")
    done = Capture.load(outs.frames)
    poses = {f.stem: np.asarray(f.pose, np.float64) for f in done.frames if f.pose is not None}
    return poses, read_json(outs.sfm)


def _timed(fn: Callable[[], tuple[Poses, dict]], gt: Poses) -> dict:
    """Run fn; its wall and CPU seconds (all threads of this process) and its pose metrics."""
    t, c = time.perf_counter(), time.process_time()
    poses, facts = fn()
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    return {"wall_s": wall, "cpu_s": cpu, **pose_metrics(poses, gt), "facts": facts}


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b is not None and b > 0 else None


def compare(
    capture: Path,
    frames: int,
    repeats: int,
    threads: int,
    sets: Sequence[str],
    config: Path | None = Path("configs/phone.yaml"),
) -> dict:
    """Plain pycolmap and the poses stage on the capture's photos, alternating, `repeats`
    times each. Returns medians: ours_s / ref_s (wall), ours_cpu_s / ref_cpu_s,
    ours_ate_m / ref_ate_m, ours_registered / ref_registered, total, the ratios ours over
    pycolmap (ratio_s, ratio_cpu, ratio_ate) and every run ("runs": {"ours", "ref"})."""
    if repeats < 1 or threads < 1:
        raise BlunfError(f"bench sfm: repeats and threads must be >= 1, got {repeats}, {threads}")
    cfg = poses_config(config, sets, threads)
    runs: dict[str, list[dict]] = {"ref": [], "ours": []}
    with tempfile.TemporaryDirectory(prefix="blunf-bench-sfm-") as tmp:
        cap, gt = photos(capture, frames, Path(tmp))
        for r in range(repeats):
            order = ("ref", "ours") if r % 2 == 0 else ("ours", "ref")
            for who in order:
                work = Path(tmp) / f"{who}-{r}"
                if who == "ref":
                    fn = partial(reference, cap, work, threads)
                else:
                    fn = partial(ours, cap, work, cfg)
                res = _timed(fn, gt)
                shutil.rmtree(work)
                log.info(
                    "%s run %d: %.1f s (%.1f CPU-s), ATE %s, %d/%d registered",
                    who,
                    r,
                    res["wall_s"],
                    res["cpu_s"],
                    res["ate_rmse_m"],
                    res["registered"],
                    res["total"],
                )
                runs[who].append(res)
    out: dict = {"capture": str(capture), "frames": len(gt), "threads": threads, "sets": [*sets]}
    for who in ("ours", "ref"):
        out[f"{who}_s"] = med([r["wall_s"] for r in runs[who]])
        out[f"{who}_cpu_s"] = med([r["cpu_s"] for r in runs[who]])
        out[f"{who}_ate_m"] = med([r["ate_rmse_m"] for r in runs[who]])
        out[f"{who}_registered"] = med([r["registered"] for r in runs[who]])
    out["total"] = len(gt)
    out["ratio_s"] = _ratio(out["ours_s"], out["ref_s"])
    out["ratio_cpu"] = _ratio(out["ours_cpu_s"], out["ref_cpu_s"])
    out["ratio_ate"] = _ratio(out["ours_ate_m"], out["ref_ate_m"])
    out["runs"] = runs
    return out


def table(res: dict) -> str:
    """The medians as a markdown table: pycolmap, the poses stage, their ratio."""

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    def ate(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.2f}"

    n = res["total"]
    rows = [
        "| SfM | wall s | CPU s | ATE cm | registered |",
        "|---|---|---|---|---|",
        f"| pycolmap (defaults, sequential, incremental) | {num(res['ref_s'], '.1f')} | "
        f"{num(res['ref_cpu_s'], '.1f')} | {ate(res['ref_ate_m'])} | "
        f"{num(res['ref_registered'], '.0f')}/{n} |",
        f"| poses stage | {num(res['ours_s'], '.1f')} | {num(res['ours_cpu_s'], '.1f')} | "
        f"{ate(res['ours_ate_m'])} | {num(res['ours_registered'], '.0f')}/{n} |",
        f"| ratio | {num(res['ratio_s'], '.2f')}x | {num(res['ratio_cpu'], '.2f')}x | "
        f"{num(res['ratio_ate'], '.2f')}x | |",
    ]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.sfm", description=__doc__)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--frames", type=int, default=0, help="N views spread evenly (0 = all)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each, medians reported")
    ap.add_argument("--threads", type=int, default=1, help="threads of both SfM runs")
    ap.add_argument("--config", type=Path, default=Path("configs/phone.yaml"))
    ap.add_argument("--set", action="append", default=[], help="poses stage: poses.key=v")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        res = compare(a.capture, a.frames, a.repeats, a.threads, a.set, a.config)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(
        f"{res['capture']}: {res['total']} views, {a.threads} thread(s), medians of "
        f"{a.repeats} run(s) each{', ' + ' '.join(a.set) if a.set else ''}"
    )
    print(table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

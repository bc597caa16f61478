"""The oracle ladder: how much of the photos-only plan's gap is holes in its depth, and how
much of it a planar fill could close.

Each rung is a capture holding the colour images, the SfM poses (those of the measuring
stick's reference, metric from the sensor depth: pipeline.bench.real's sfm-ref run) and
some of the sensor's depth; its plan is scored against that reference's plan like the
photos-only plan (pipeline.bench.real.score):
  O1  the sensor's depth everywhere;
  O2  the sensor's depth only where stereo kept a reading (the photos-only run's depth
      stage: sources/ code 1 when it writes sources, else its depth/ maps);
  O3  O2 + the sensor's depth on the pixels lying within 3 cm of an axis-aligned plane
      found in that view's sensor points (per axis of the aligned room: peaks of the points'
      offsets in 1 cm bins holding >= 1 % of the view's readings; a pixel counts when its
      normal is within 30 degrees of the axis, so a slice through clutter is not a plane);
  O4  O2 + the reference's floor and wall pixels (its semantics labels).

    python -m pipeline.bench.oracle CAPTURE --real DIR --out OUT [--rungs O1,O2,O3,O4]
DIR is a finished `python -m pipeline.bench.real CAPTURE --out DIR`; writes OUT/oracle.json
(per rung: the plan's metrics against the reference and against O1's plan, which takes
the same path through the pipeline, poses given, and the share of the sensor's pixels
given depth) and keeps OUT/<rung>/ (the
capture) and OUT/<rung>-run/.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from pipeline.bench.depth import at_centres, depth_folder, sensor_views
from pipeline.bench.real import run_plan, score
from pipeline.bench.runs import run_poses
from stages.common.capture import Frame, write_layout
from stages.common.classes import FLOOR_NAME, KEPT, OBJECT_NAME, WALL_NAME
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_label, write_depth_png, write_json

log = logging.getLogger(__name__)

RUNGS = ("O1", "O2", "O3", "O4")
PLANE_DIST = 0.03  # O3: metres from a plane
BIN = 0.01  # O3: offset histogram bin (m)
MIN_SHARE = 0.01  # O3: a plane holds at least this share of the view's readings
MAX_TILT = 30.0  # O3: degrees between a pixel's normal and the plane's axis


def stereo_mask(folder: Path, stem: str, shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool: where the photos-only depth stage kept a stereo reading, read at the
    pixel centres of a sensor map of `shape` (the stage's maps are smaller)."""
    src = folder / "sources" / f"{stem}.png"
    if src.is_file():
        small = read_label(src) == 1
    else:
        path = folder / "depth" / f"{stem}.npy"
        if not path.is_file():
            raise BlunfError(f"{path}: no stereo depth map of view {stem!r}")
        d = np.load(path)
        small = np.isfinite(d) & (d > 0)
    h, w = small.shape
    rows = np.minimum((np.arange(shape[0]) + 0.5) * h / shape[0], h - 1).astype(np.int64)
    cols = np.minimum((np.arange(shape[1]) + 0.5) * w / shape[1], w - 1).astype(np.int64)
    return small[rows[:, None], cols[None, :]]


def plane_mask(depth: np.ndarray, frame: Frame, pose: np.ndarray) -> np.ndarray:
    """[H, W] bool: the pixels within PLANE_DIST of an axis-aligned plane of the view's own
    sensor points (see the module doc). `pose`: camera-to-world in the aligned room."""
    k = frame.intrinsics
    h, w = depth.shape
    # pixel centres in the intrinsics' pixels (integer = a pixel's centre)
    u, v = np.meshgrid(
        (np.arange(w) + 0.5) * k.width / w - 0.5, (np.arange(h) + 0.5) * k.height / h - 0.5
    )
    cam = np.stack([(u - k.cx) / k.fx * depth, (v - k.cy) / k.fy * depth, depth], -1)  # [H,W,3]
    world = cam @ pose[:3, :3].T + pose[:3, 3]  # [H, W, 3]
    valid = depth > 0
    # normals from the neighbours two pixels away, in the world
    dx = np.roll(world, -2, 1) - np.roll(world, 2, 1)
    dy = np.roll(world, -2, 0) - np.roll(world, 2, 0)
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1)
    ok = valid & (norm > 1e-12)
    ok &= ndimage.minimum_filter(valid.astype(np.uint8), size=5).astype(bool)
    n = n / np.maximum(norm, 1e-12)[..., None]
    out = np.zeros((h, w), bool)
    need = MIN_SHARE * max(int(valid.sum()), 1)
    cos_tilt = np.cos(np.radians(MAX_TILT))
    for a in range(3):
        cand = ok & (np.abs(n[..., a]) >= cos_tilt)
        x = world[..., a][cand]
        if x.size < need:
            continue
        lo = np.floor(x.min() / BIN) * BIN
        nbins = int(np.ceil((x.max() - lo) / BIN)) + 1
        hist = np.bincount(((x - lo) / BIN).astype(np.int64), minlength=nbins)  # [nbins]
        window = int(round(2 * PLANE_DIST / BIN)) + 1  # the points a plane at a bin would take
        held = np.convolve(hist, np.ones(window), mode="same").astype(np.float64)
        peaks = (held >= need) & (held == ndimage.maximum_filter1d(held, window))
        for b in np.flatnonzero(peaks):
            c = lo + (b + 0.5) * BIN
            near = np.abs(x - c) <= PLANE_DIST
            if not near.any():
                continue
            c = float(np.median(x[near]))  # refined offset
            out |= cand & (np.abs(world[..., a] - c) <= PLANE_DIST)
    return out


def build(real: Path, rung: str, out: Path) -> tuple[Path, float]:
    """Write rung's capture (see the module doc) to `out` (kept when already written).
    Returns (out, percent of the sensor's valid pixels given depth)."""
    if rung not in RUNGS:
        raise BlunfError(f"oracle rung {rung!r} is not one of {RUNGS}")
    done = out.parent / f"{out.name}.json"
    if (out / "cameras.json").is_file() and done.is_file():
        return out, float(json.loads(done.read_text())["kept"])
    ref_run, folder = real / "sfm-ref", depth_folder(real / "photos")
    cap, labels, classes = sensor_views(ref_run)
    poses = run_poses(ref_run)  # the reference's SfM poses, in its aligned room
    floor_wall = {c for c, n in classes.items() if n in KEPT}
    tmp = out.parent / f".{out.name}.depth"
    tmp.mkdir(parents=True, exist_ok=True)
    frames, kept, total = [], 0, 0
    for f in cap.frames:
        if f.stem not in poses or f.depth is None:
            continue
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        valid = d > 0
        keep = np.ones(d.shape, bool)
        if rung != "O1":
            keep = stereo_mask(folder, f.stem, d.shape)
            if rung == "O3":
                keep |= plane_mask(d, f, poses[f.stem])
            if rung == "O4" and f.stem in labels:
                lab = at_centres(read_label(labels[f.stem]), d.shape)
                keep |= np.isin(lab, list(floor_wall))
        d = np.where(keep, d, 0.0)
        kept += int((d > 0).sum())
        total += int(valid.sum())
        path = tmp / f"{f.stem}.png"
        write_depth_png(path, d)
        frames.append(_with(f, path, poses[f.stem]))
    if not frames:
        raise BlunfError(f"{ref_run}: no view with depth and an SfM pose")
    c = replace(cap.with_frames(frames), depth_scale=1000.0, depth_invalid=(), gravity=None)
    write_layout(c, out, with_poses=True)
    share = 100.0 * kept / max(total, 1)
    write_json(done, {"kept": share})
    return out, share


def _with(f: Frame, depth: Path, pose: np.ndarray) -> Frame:
    """The frame with the rung's depth map and the SfM pose, without labels."""
    return replace(f, depth=depth, pose=pose, label=None, instance=None)


def ladder(src: Path, real: Path, out: Path, rungs: tuple[str, ...], ref_args: list[str]) -> dict:
    """Build and run each rung, score it against real/sfm-ref; writes out/oracle.json."""
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"capture": str(src), "real": str(real), "rungs": {}}
    for r in rungs:
        t = time.perf_counter()
        cap, share = build(real, r, out / r)
        run_plan(cap, out / f"{r}-run", ref_args)
        s = score(real / "sfm-ref", out / f"{r}-run")
        res["rungs"][r] = {
            "plan": s["plan"],
            "depth_kept": share,
            "seconds": time.perf_counter() - t,
        }
        write_json(out / "oracle.json", res)
    if "O1" in rungs:  # the rungs against O1 too: the same path (given poses), less depth
        for r in rungs:
            res["rungs"][r]["plan_vs_O1"] = score(out / "O1-run", out / f"{r}-run")["plan"]
        write_json(out / "oracle.json", res)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.oracle", description=__doc__)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--real", type=Path, required=True, help="a pipeline.bench.real output")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rungs", default=",".join(RUNGS))
    ap.add_argument("--ref-set", action="append", default=[], help="the rungs' runs: k=v")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    rungs = tuple(x.strip() for x in a.rungs.split(",") if x.strip())
    args = [x for s in a.ref_set for x in ("--set", s)]
    try:
        res = ladder(a.capture, a.real, a.out, rungs, args)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for r, v in res["rungs"].items():
        p = v["plan"]
        per = " ".join(
            f"{c} {p['per_class'].get(c, float('nan')):.1f}"
            for c in (FLOOR_NAME, WALL_NAME, OBJECT_NAME)
        )
        o1 = v.get("plan_vs_O1", {}).get("fwiou", float("nan"))
        print(
            f"{r}: fwIoU {p['fwiou']:.1f} (against O1 {o1:.1f}) | IoU {per} | "
            f"depth on {v['depth_kept']:.1f} % of the sensor's pixels"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A real capture from photos alone against the same capture with its sensor depth.

For one capture with depth (7-Scenes, Replica/vMAP, the project's layout), three runs of
`blunf run`, each from a copy without per-pixel labels (so that every plan takes its classes
from the geometry the same way):
  photos-only  the colour images and intrinsics only (no depth, poses, labels or gravity):
               poses from SfM (scale from the priors), depth from the depth step;
  sfm-ref      the reference: the colour images, the sensor depth and the intrinsics (no
               poses or gravity): SfM finds the poses from the colour images, its scale
               comes from the sensor depth (poses.scale_from auto), and that depth gives the
               plan, so the poses it is read at are the photos-only run's but for the scale;
  ref          the old reference: the sensor depth at the dataset's poses (and gravity).
The references draw the plan as the photos-only run does (its blueprint.blunf.wall_face,
margin and fill: `drawn_alike`), then take --ref-set.
The photos-only plan is scored against each reference per class, on the reference's cells
within its projected points' bounds (`observed`; "padded" keeps the whole grid), through
the similarity between the two runs' whole poses (stages.common.gt_frame), so a wrong metric
scale is not counted twice; the poses are scored likewise (registration, rotation, ATE and
that similarity's scale: 1 = the photos-only scale is right). The two references against
each other give the pose disagreement that no depth method can remove (7-Scenes: depth
camera against colour camera, KinectFusion against SfM). The photos-only depth maps are
scored against the sensor's (pipeline.bench.depth: coverage, within 5 cm, AbsRel).

    python -m pipeline.bench.real CAPTURE --out DIR [--set k=v ...] [--ref-set k=v ...]
                                  [--frames N] [--config configs/phone.yaml]
writes DIR/real.json (figures, seconds), DIR/depth.json (per view) and keeps DIR/sfm-ref,
DIR/ref, DIR/photos and the three copies.
A run folder already finished under DIR is reused (the pipeline's caches): a second call
with other photos-only settings reruns only what they change. The depth stage's field fill
stops on its step count (depth.field.train.max_steps), so the figures do not depend on the
machine's load.
"""

from __future__ import annotations

import argparse
import glob
import json
import logging
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.bench.runs import run_poses
from pipeline.bench.walls import wall_offsets
from pipeline.config import load_config
from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN, write_layout
from stages.common.classes import GEOMETRY, GEOMETRY_IGNORE, UNKNOWN_NAME
from stages.common.errors import BlunfError
from stages.common.gt_frame import plan_frame
from stages.common.io import read_json, write_json
from stages.common.plan_metrics import class_map, coarse_gt, evaluate_plan, to_frame
from stages.evaluate.poses import pose_metrics
from stages.ingest import load

log = logging.getLogger(__name__)

CLASSES = tuple(n for k, n in GEOMETRY.items() if k not in GEOMETRY_IGNORE)  # on the plan


def stripped_copy(src: Path, out: Path, sensor: bool, poses: bool | None = None) -> Path:
    """Write `src` in the project's layout without labels: with `sensor`, colour, depth and
    (with `poses`, by default as `sensor`) the poses and gravity as the capture has them;
    else colour images and intrinsics only. Returns out (kept as it is when it already holds
    a copy). `sensor` without `poses` is the measuring stick's reference: SfM finds the poses
    from the colour images and the sensor depth gives the plan."""
    poses = sensor if poses is None else poses
    out = Path(out)
    if (out / "cameras.json").is_file():
        return out
    with tempfile.TemporaryDirectory(prefix="blunf-real-") as tmp:
        cap = load(Path(src), Path(tmp))
        bare = [
            replace(
                f,
                depth=f.depth if sensor else None,
                pose=f.pose if poses else None,
                label=None,
                instance=None,
            )
            for f in cap.frames
        ]
        cap = replace(cap.with_frames(bare), classes={}, ignore=(), gt=None)
        if not poses:
            cap = replace(cap, gravity=None)
        return write_layout(cap, out, with_poses=poses)


def run_plan(capture: Path, out: Path, args: list[str]) -> float:
    """`blunf run capture --out out args...`; returns the seconds it took. The command runs
    as a child process (`python -m pipeline`): pipeline.cli reaches this module through
    `blunf bench --targets`, so importing the CLI here would close a circle."""
    t = time.perf_counter()
    cmd = [sys.executable, "-m", "pipeline", "run", str(capture), "--out", str(out), *args]
    rc = subprocess.run(cmd, check=False).returncode
    if rc != 0:
        raise BlunfError(f"{out}: blunf run failed (exit code {rc}); see its report.json")
    return time.perf_counter() - t


def scale_facts(run: Path) -> dict:
    """How the run's poses stage found the metric scale (sfm.json "scale_from" with "scale"),
    {} without SfM."""
    found = sorted(glob.glob(str(Path(run) / "poses" / "*" / "sfm.json")))
    if not found:
        return {}
    sfm = read_json(Path(max(found, key=lambda p: Path(p).stat().st_mtime)))
    return {**sfm.get("scale_from", {}), "scale": sfm.get("scale")}


def observed(ref_run: Path, ref: Blueprint) -> Blueprint:
    """The reference plan with the cells beyond its projected points' bounds (the project
    stage's grid.json "bounds") made unknown. The plan's grid pads the bounds and the BluNF
    plan clamps the field there (blueprint.blunf.outside): a band of whatever class lies at
    the bounds, mostly wall. On Replica office0 (30 frames) that band is ~85 % of the
    reference's wall cells, and a plan from other depth has no cells there."""
    found = sorted(glob.glob(str(Path(ref_run) / "project" / "*" / "grid.json")))
    if not found:
        return ref
    bounds = read_json(Path(max(found, key=lambda p: Path(p).stat().st_mtime))).get("bounds")
    if not bounds:
        return ref
    xy = ref.grid.centers()  # [H, W, 2]
    inside = (xy >= np.asarray(bounds[:2])).all(-1) & (xy <= np.asarray(bounds[2:])).all(-1)
    return replace(ref, labels=np.where(inside, ref.labels, np.uint8(UNKNOWN)))


def score(ref_run: Path, pred_run: Path) -> dict:
    """The photos-only run's plan and poses against the reference run's (see the module doc).

    Returns {"plan": evaluate_plan metrics + "frame" + "confusion", "padded": the plan's
    metrics counting the reference's padding band too (see observed), "poses": pose_metrics,
    "scale": facts, "walls": how far each of the reference's walls lies from the photos-only
    run's (pipeline.bench.walls; left out when a run has no plan.json)}.
    """
    padded = Blueprint.load(Path(ref_run) / "blueprint.npz")
    ref = observed(ref_run, padded)
    pred = Blueprint.load(Path(pred_run) / "blueprint.npz")
    est, gt = run_poses(pred_run), run_poses(ref_run)
    m, frame = plan_frame(True, est, gt, ref.grid)
    plan = {**evaluate_plan(pred, ref, m), "frame": frame, "confusion": confusion(pred, ref, m)}
    res = {
        "plan": plan,
        "padded": evaluate_plan(pred, padded, m),
        "poses": pose_metrics(est, gt),
        "scale": scale_facts(pred_run),
    }
    walls = wall_offsets(ref_run, pred_run, np.eye(4) if m is None else m)
    if walls is not None:
        res["walls"] = walls
    return res


def confusion(pred: Blueprint, ref: Blueprint, pred_to_ref: np.ndarray | None) -> dict:
    """{reference class: {predicted class or "unknown": percent of its cells}}: where each
    class of the reference went in the prediction (read as evaluate_plan reads it)."""
    if pred_to_ref is None:
        labels = pred.resample(ref.grid)
    else:
        labels = pred.sample(to_frame(ref.grid.centers().reshape(-1, 2), pred_to_ref))
    ref = coarse_gt(pred, ref)
    got = class_map(pred, ref)[labels.reshape(-1)]  # [H * W] in the reference's ids
    want = ref.labels.reshape(-1)
    out: dict = {}
    for c in np.unique(want[want != UNKNOWN]):
        sel = got[want == c]
        ids, n = np.unique(sel, return_counts=True)
        name = ref.classes.get(int(c), str(int(c)))
        out[name] = {
            (UNKNOWN_NAME if i == UNKNOWN else ref.classes.get(int(i), str(int(i)))): round(
                100.0 * int(k) / sel.size, 1
            )
            for i, k in zip(ids, n, strict=True)
        }
    return out


def measure(
    src: Path,
    out: Path,
    photo_args: list[str],
    ref_args: list[str],
    frames: int = 0,
    ref_run: Path | None = None,
    depth_erode: int | None = None,
) -> dict:
    """The three runs of `src` under `out`, scored; writes and returns out/real.json.

    out/sfm-ref: the sensor's depth at SfM poses (the reference the photos-only plan is
    scored against: "plan", "padded", "poses", "scale"); out/ref: the sensor's depth at the
    dataset's poses (`ref_run`: a finished one to use instead), the old reference, under
    "dataset_poses"; "references": the two references against each other (the SfM
    reference's plan scored against the dataset-pose plan, its poses against the dataset's:
    the pose disagreement no depth method can remove); "depth": record_depth's.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pick = ["--frames", str(frames)] if frames else []
    t0 = time.perf_counter()
    bare = stripped_copy(src, out / "photos-capture", sensor=False)
    at_sfm = stripped_copy(src, out / "sensor-sfm-capture", sensor=True, poses=False)
    copy_s = time.perf_counter() - t0
    ref_s = 0.0
    if ref_run is None:
        sensor = stripped_copy(src, out / "sensor-capture", sensor=True)
        ref_run = out / "ref"
        ref_s = run_plan(sensor, ref_run, [*ref_args, *pick])
    sfm_s = run_plan(at_sfm, out / "sfm-ref", [*ref_args, *pick])
    photo_s = run_plan(bare, out / "photos", [*photo_args, *pick])
    res = score(out / "sfm-ref", out / "photos")
    res["dataset_poses"] = score(ref_run, out / "photos")
    both = score(ref_run, out / "sfm-ref")
    res["references"] = {k: both[k] for k in ("plan", "poses", "scale")}
    res["depth"] = record_depth(src, out / "photos", out / "sfm-ref", res, depth_erode)
    res["seconds"] = {"copy": copy_s, "ref": ref_s, "sfm_ref": sfm_s, "photos": photo_s}
    res["seconds"]["total"] = time.perf_counter() - t0
    res["capture"], res["photos_args"], res["ref_args"] = str(src), photo_args, ref_args
    res["ref_run"] = str(ref_run)
    write_json(out / "real.json", res)
    return res


def record_depth(src: Path, photos: Path, sfm_ref: Path, res: dict, erode: int | None) -> dict:
    """The photos-only depth maps against the sensor's (pipeline.bench.depth), their lengths
    taken to metres by the photos-only poses' scale against the SfM-pose reference's; written
    into the photos-only run's report.json as metrics.depth, the per-view figures beside
    real.json (depth.json). `erode` None: 4 px round the sensor's edges on a 7-Scenes capture
    (its colour and depth are not registered; ~1 % of the kitchen's pixels per px), else 0."""
    from pipeline.bench.depth import depth_metrics
    from stages.ingest import detect

    if erode is None:
        erode = 4 if Path(src).exists() and detect(Path(src)) == "7scenes" else 0
    m = depth_metrics(photos, sfm_ref, erode, res["poses"].get("align_scale"))
    write_json(Path(photos).parent / "depth.json", m.pop("per_view"))
    report = Path(photos) / "report.json"
    if report.is_file():
        doc = read_json(report)
        doc.setdefault("metrics", {})["depth"] = m
        write_json(report, doc)
    return m


def summary(res: dict) -> str:
    """Lines: the photos-only plan against the sensor depth at SfM poses and at the
    dataset's (fwIoU, per-class IoU, registration, the photos-only scale's error), then the
    two references against each other."""
    lines = []
    for name, r in (
        ("photos vs sensor at SfM poses", res),
        ("photos vs sensor at dataset poses", res.get("dataset_poses")),
        ("sensor at SfM poses vs at dataset poses", res.get("references")),
    ):
        if not r:
            continue
        p, q = r["plan"], r["poses"]
        per = " ".join(f"{c} {p['per_class'].get(c, float('nan')):.1f}" for c in CLASSES)
        lines.append(
            f"{name}: fwIoU {p['fwiou']:.1f} pAcc {p['pacc']:.1f} | IoU {per} | registered "
            f"{q['registered']}/{q['total']} rot {_num(q.get('rot_err_deg_median')):.2f}"
            f" deg ATE {_num(q.get('ate_rmse_m')):.3f} m | scale "
            f"x{_num(q.get('align_scale')):.3f} ({r['scale'].get('method', '?')})"
        )
        w = r.get("walls")
        if w:  # + = the photos-only wall lies inside the reference's room
            parts = [
                f"{k} {_num(w[k]['median_cm']):+.1f} cm ({w[k]['found']}/{w['walls']})"
                for k in ("layout", "plan_points", "sfm_points", "ref_points")
                if k in w
            ]
            lines.append("  walls off the reference's (median, + inward): " + ", ".join(parts))
    d = res.get("depth")
    if d:
        per = " ".join(
            f"{k} {v['coverage']:.1f}/{v['within_5cm'] or float('nan'):.1f}"
            for k, v in {**d["sources"], **d["classes"]}.items()
            if v["coverage"]
        )
        lines.append(
            f"depth: coverage {d['coverage']:.1f} % within 5 cm {d['within_5cm']:.1f} % AbsRel "
            f"{d['absrel']:.3f} (coverage/within 5 cm: {per}; erode {d['erode_px']} px)"
        )
        t = d.get("tracks")
        if t:  # the run's own geometry against the sensor: what no depth method can beat
            classes = t.get("classes", {}).items()
            by = " ".join(f"{n} {v['within_5cm']:.1f}" for n, v in classes if v["compared"])
            lines.append(
                f"SfM tracks vs sensor: within 5 cm {t['within_5cm']:.1f} % ({by}) AbsRel "
                f"{t['absrel']:.3f} median ratio {t['median_ratio']:.3f} ({t['compared']} tracks)"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.real", description=__doc__)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--config", default="configs/phone.yaml", help="photos-only run's config")
    ap.add_argument("--set", action="append", default=[], help="photos-only run: stage.key=v")
    ap.add_argument("--ref-set", action="append", default=[], help="reference run: stage.key=v")
    ap.add_argument("--frames", type=int, default=0, help="N views spread evenly (0 = all)")
    ap.add_argument("--ref-run", type=Path, help="a finished dataset-pose reference run")
    ap.add_argument("--depth-erode", type=int, help="px dropped round sensor depth edges")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    photo = ["--config", a.config, *(x for s in a.set for x in ("--set", s))]
    try:
        ref = [x for s in drawn_alike(Path(a.config), a.set) + a.ref_set for x in ("--set", s)]
        res = measure(a.capture, a.out, photo, ref, a.frames, a.ref_run, a.depth_erode)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(summary(res))
    print(json.dumps(res["seconds"]))
    return 0


def drawn_alike(config: Path, sets: list[str]) -> list[str]:
    """The photos-only run's choices of how a plan is drawn, as --set items for the
    references (before their own --ref-set): blueprint.blunf.wall_face, its margin and fill,
    and hidden_insides. The references must draw walls as the photos-only plan does, or the way
    of drawing is scored as depth error: with the default's wall_face against phone.yaml's
    plan without it, the office read 61.09 (wall 29.6) where both drawn without it read
    61.95 (wall 43.6)."""
    b = load_config(config, sets)["blueprint"].blunf
    return [
        f"blueprint.blunf.wall_face={str(b.wall_face).lower()}",
        f"blueprint.blunf.wall_face_margin={b.wall_face_margin}",
        f"blueprint.blunf.wall_face_fill={b.wall_face_fill}",
        f"blueprint.blunf.hidden_insides={str(b.hidden_insides).lower()}",
    ]


def _num(x: float | None) -> float:
    """A figure for printing: NaN only when it is missing (0.0 is a figure)."""
    return float("nan") if x is None else float(x)


if __name__ == "__main__":
    sys.exit(main())

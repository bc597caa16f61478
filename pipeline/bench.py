"""`blunf bench`: run time against error, measured side by side on one machine.

Each case runs the pipeline once (so upstream stages are cached), then times the stage under
study `repeats` times in fresh folders and reports the median wall and CPU seconds with the
error metrics. Reference points (the paper's BluNF recipe) are measured in the same run, so
ratios hold on a noisy machine.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.config import load_config
from pipeline.report import peak_rss_mb, peak_rss_reset
from pipeline.run import run as run_pipeline
from stages.blueprint import IMPLS as BLUEPRINT
from stages.blueprint import BlueprintInputs, paper_recipe
from stages.common.blueprint import Blueprint
from stages.common.io import read_json
from stages.evaluate.plan import evaluate_plan

log = logging.getLogger(__name__)

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FIELDS = [
    "scene",
    "frames",
    "stage",
    "method",
    "variant",
    "steps",
    "repeats",
    "wall_s",
    "cpu_s",
    "peak_rss_mb",
    "pacc",
    "fwiou",
    "miou",
    "completeness",
    "fps",
    "note",
]


def timed(fn: Callable[[Path], Any], repeats: int) -> tuple[list[float], list[float], float, Any]:
    """Run fn(fresh_folder) `repeats` times. Returns (wall s, cpu s, peak MB, last result)."""
    walls, cpus, peak, res = [], [], 0.0, None
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d:
            peak_rss_reset()
            t0, c0 = time.perf_counter(), time.process_time()
            res = fn(Path(d))
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            peak = max(peak, peak_rss_mb() or 0.0)
    return walls, cpus, peak, res


def _stage_folder(run_dir: Path, stage: str, impl: str | None = None) -> Path:
    rep = read_json(run_dir / "report.json")
    s = next(s for s in rep["stages"] if s["name"] == stage and (impl is None or s["impl"] == impl))
    return run_dir / stage / s["key"]


def bench_blueprint(
    capture: Path, out: Path, frames: int, repeats: int, paper_steps: tuple[int, ...]
) -> list[dict]:
    """BluNF (defaults), the paper's recipe at several step budgets, and MVR, on one budget."""
    run_dir = out / "runs" / f"{capture.name}-f{frames}"
    cfg = load_config(None, [f"ingest.frames={frames}"])
    run_pipeline(capture, run_dir, cfg)
    proj = _stage_folder(run_dir, "project")
    inputs = BlueprintInputs(points=proj / "points.npz", grid=proj / "grid.json")
    gt = Blueprint.load(capture / "gt" / "blueprint.npz")
    bcfg = cfg["blueprint"]
    variants: list[tuple[str, str, Any, int]] = [
        ("blunf", "default", bcfg, bcfg.blunf.steps),
        ("mvr", "default", bcfg, 0),
    ]
    for steps in paper_steps:
        pcfg = dataclasses.replace(bcfg, blunf=dataclasses.replace(paper_recipe(), steps=steps))
        variants.append(("blunf", "paper", pcfg, steps))
    rows = []
    for method, variant, vcfg, steps in variants:
        reps = repeats if variant == "default" else 1

        def once(d: Path, m: str = method, c: Any = vcfg) -> dict:
            return evaluate_plan(Blueprint.load(BLUEPRINT[m](c, inputs, d).blueprint), gt)

        walls, cpus, peak, metrics = timed(once, reps)
        rows.append(
            {
                "scene": capture.name,
                "frames": frames,
                "stage": "blueprint",
                "method": method,
                "variant": variant,
                "steps": steps,
                "repeats": reps,
                "wall_s": round(statistics.median(walls), 3),
                "cpu_s": round(statistics.median(cpus), 3),
                "peak_rss_mb": peak,
                **{k: round(metrics[k], 2) for k in ("pacc", "fwiou", "miou", "completeness")},
            }
        )
        log.info("bench %s", rows[-1])
    return rows


def bench_fusion(capture: Path, out: Path, repeats: int) -> list[dict]:
    """Fusion frames per second on a capture with depth (the pipeline's stage, rerun)."""
    from stages.fusion import IMPLS as FUSION
    from stages.fusion import FusionInputs

    run_dir = out / "runs" / capture.name
    cfg = load_config(None, ["run.methods=mvr"])
    run_pipeline(capture, run_dir, cfg)
    align = _stage_folder(run_dir, "align")
    inputs = FusionInputs(frames=align / "frames.json")
    walls, cpus, peak, _ = timed(lambda d: FUSION["tsdf"](cfg["fusion"], inputs, d), repeats)
    n = len(read_json(inputs.frames)["frames"])
    return [
        {
            "scene": capture.name,
            "frames": n,
            "stage": "fusion",
            "method": "tsdf",
            "variant": "default",
            "repeats": repeats,
            "wall_s": round(statistics.median(walls), 3),
            "cpu_s": round(statistics.median(cpus), 3),
            "peak_rss_mb": peak,
            "fps": round(n / statistics.median(walls), 2),
            "note": "integrate + mesh + ray-cast depth of every view",
        }
    ]


def _ensure_room(out: Path, views: int, size: tuple[int, int]) -> Path:
    from stages.synth import make_room

    cap = out / "captures" / f"room-s0-v{views}-{size[0]}x{size[1]}"
    return cap if cap.is_dir() else make_room(cap, views=views, seed=0, size=size)


def bench(out: Path, quick: bool = False, repeats: int = 3) -> Path:
    """Run the grid; write bench.csv and bench.md in `out`. Returns the markdown path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    room = _ensure_room(out, 90, (160, 120) if quick else (320, 240))
    budgets = (9,) if quick else (90, 45, 9)
    paper_steps = (250,) if quick else (250, 500, 1000, 2000)
    for n in budgets:
        rows += bench_blueprint(room, out, n, 1 if quick else repeats, paper_steps)
    kitchen = SHARED_DATA / "7scenes-redkitchen"
    if kitchen.is_dir() and not quick:
        rows += bench_fusion(kitchen, out, repeats)
    else:
        log.info("bench: %s absent or --quick: fusion on real frames not measured", kitchen)
        rows += bench_fusion(room, out, 1 if quick else repeats)
    with open(out / "bench.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in FIELDS})
    md = out / "bench.md"
    md.write_text(to_markdown(rows))
    return md


def to_markdown(rows: list[dict]) -> str:
    """The table, plus each frame budget's paper-recipe time to reach the default's fwIoU."""
    lines = [
        "| scene | frames | stage | method | variant | steps | wall s (median) | cpu s |"
        " peak MB | pAcc | fwIoU | compl. | fps |",
        "|" + "---|" * 13,
    ]
    for r in rows:
        lines.append(
            "| "
            + " | ".join(
                str(r.get(k, ""))
                for k in (
                    "scene",
                    "frames",
                    "stage",
                    "method",
                    "variant",
                    "steps",
                    "wall_s",
                    "cpu_s",
                    "peak_rss_mb",
                    "pacc",
                    "fwiou",
                    "completeness",
                    "fps",
                )
            )
            + " |"
        )
    lines.append("")
    for n in sorted({r["frames"] for r in rows if r["stage"] == "blueprint"}, reverse=True):
        ours = next(
            r
            for r in rows
            if r["frames"] == n and r["variant"] == "default" and r["method"] == "blunf"
        )
        paper = [r for r in rows if r["frames"] == n and r["variant"] == "paper"]
        hit = next((r for r in paper if r["fwiou"] >= ours["fwiou"] - 0.5), None)
        if hit:
            lines.append(
                f"- {n} frames: the paper recipe reaches fwIoU {hit['fwiou']} (ours "
                f"{ours['fwiou']}) after {hit['steps']} steps, {hit['wall_s']} s: "
                f"{hit['wall_s'] / ours['wall_s']:.1f}x our {ours['wall_s']} s."
            )
        elif paper:
            best = max(paper, key=lambda r: r["fwiou"])
            lines.append(
                f"- {n} frames: the paper recipe's best fwIoU is {best['fwiou']} after "
                f"{best['steps']} steps ({best['wall_s']} s), below ours "
                f"{ours['fwiou']} in {ours['wall_s']} s."
            )
    return "\n".join(lines) + "\n"

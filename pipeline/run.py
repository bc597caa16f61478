"""The recipe: capture in, blueprint out. Paths, then one call per stage."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

from pipeline.config import Config
from pipeline.planner import gt_files, make_plan
from pipeline.report import Report
from pipeline.runner import Runner, check_impl
from stages.align import AlignInputs
from stages.blueprint import BlueprintInputs
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.evaluate import EvaluateInputs
from stages.export.files import ExportInputs
from stages.fusion import FusionInputs
from stages.ingest.select import IngestInputs
from stages.poses import PosesInputs
from stages.project import ProjectInputs

log = logging.getLogger(__name__)


def run(capture: Path, out: Path, cfg: Config, edits: Path | None = None) -> Report:
    """Build the blueprint of `capture` into the run folder `out`; returns the report."""
    capture, out = Path(capture), Path(out)
    if not capture.exists():
        raise BlunfError(f"{capture}: capture folder not found")
    if out.resolve().is_relative_to(capture.resolve()):
        raise BlunfError(f"{out}: the run folder must not be inside the capture {capture}")
    for stage in ("ingest", "align", "fusion", "project"):  # fail before any work
        check_impl(stage, cfg[stage].impl)
    if cfg["poses"].impl != "auto":
        check_impl("poses", cfg["poses"].impl)
    for m in cfg.run.methods:
        check_impl("blueprint", m)
    if out.exists() and not out.is_dir():
        raise BlunfError(f"{out}: the run folder exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BlunfError(f"{out}: cannot create the run folder ({e.strerror})") from None
    report = Report(scene=out.name, capture=str(capture.resolve()), config=cfg.to_dict())
    r = Runner(out, cfg, report)
    try:
        _recipe(r, capture, cfg, edits)
    finally:
        report.write(out / "report.json")
    return report


def _recipe(r: Runner, capture: Path, cfg: Config, edits: Path | None) -> None:
    report = r.report
    frames = r.stage("ingest", cfg["ingest"].impl, IngestInputs(capture=capture)).frames
    cap = Capture.load(frames)
    plan = make_plan(cap, cfg, edits)

    step = plan.get("poses")
    if step.run:
        frames = r.stage("poses", step.impl, PosesInputs(frames=frames), step.reason).frames
    else:
        r.skip("poses", step.impl, step.reason)
    frames = r.stage("align", cfg["align"].impl, AlignInputs(frames=frames)).frames
    for name in ("depth",):
        r.skip(name, plan.get(name).impl, plan.get(name).reason)
    fused = r.stage("fusion", cfg["fusion"].impl, FusionInputs(frames=frames))
    for name in ("semantics", "nerf"):
        r.skip(name, plan.get(name).impl, plan.get(name).reason)
    pts = r.stage("project", cfg["project"].impl, ProjectInputs(frames=fused.frames))
    plans = {
        m: r.stage("blueprint", m, BlueprintInputs(points=pts.points, grid=pts.grid)).blueprint
        for m in cfg.run.methods
    }
    r.skip("edit", plan.get("edit").impl, plan.get("edit").reason)

    step = plan.get("evaluate")
    if step.run:
        gt = gt_files(cap)
        ev = r.stage(
            "evaluate",
            step.impl,
            EvaluateInputs(
                frames=fused.frames,
                gt=gt["blueprint"].parent if "blueprint" in gt else gt["poses"].parent,
                blueprints=tuple(plans.values()),
                methods=tuple(plans),
                poses_estimated=plan.runs("poses"),
            ),
            step.reason,
        )
        report.metrics.update(read_json(ev.metrics))
    else:
        r.skip("evaluate", step.impl, step.reason)

    ex = r.stage(
        "export",
        "files",
        ExportInputs(blueprint=plans[cfg.run.methods[0]], mesh=fused.mesh, frames=fused.frames),
    )
    for name in ex.files:
        _publish(ex.folder / name, r.out / name)
        report.outputs[name] = str(r.out / name)
    summary = read_json(ex.folder / "components.json")
    report.plan = {
        k: summary[k]
        for k in ("known_area_m2", "unknown_area_m2", "classes", "min_area_m2", "components")
    }


def _publish(src: Path, dst: Path) -> None:
    """Copy src to dst atomically (temp file beside dst, then rename): a run sharing the
    folder, or a reader, never sees a half-copied output."""
    tmp = dst.with_name(f".{dst.name}.tmp-{os.getpid()}")
    try:
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)

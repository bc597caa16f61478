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
from stages.blueprint import BlueprintInputs, NerfTopInputs
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import check_exists, read_json
from stages.edit import EditInputs, EditOutputs, spec_textures
from stages.evaluate import EvaluateInputs
from stages.export.files import ExportInputs
from stages.fusion import FusionInputs
from stages.ingest.select import IngestInputs
from stages.nerf.config import NerfInputs
from stages.poses import PosesInputs
from stages.project import ProjectInputs
from stages.semantics import SemanticsInputs

log = logging.getLogger(__name__)


def run(capture: Path, out: Path, cfg: Config, edits: Path | None = None) -> Report:
    """Build the blueprint of `capture` into the run folder `out`; returns the report."""
    capture, out = Path(capture), Path(out)
    check_exists(capture, "capture folder")
    if out.resolve().is_relative_to(capture.resolve()):
        raise BlunfError(f"{out}: the run folder must not be inside the capture {capture}")
    for stage in ("ingest", "align", "fusion", "project"):  # fail before any work
        check_impl(stage, cfg[stage].impl)
    if cfg["poses"].impl != "auto":
        check_impl("poses", cfg["poses"].impl)
    for m in cfg.run.methods:
        check_impl("blueprint", m)
    textures = spec_textures(edits) if edits is not None else ()  # a bad spec fails here
    if out.exists() and not out.is_dir():
        raise BlunfError(f"{out}: the run folder exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BlunfError(f"{out}: cannot create the run folder ({e.strerror})") from None
    report = Report(scene=out.name, capture=str(capture.resolve()), config=cfg.to_dict())
    r = Runner(out, cfg, report)
    try:
        _recipe(r, capture, cfg, edits, textures)
    finally:
        report.write(out / "report.json")
    return report


def _recipe(
    r: Runner, capture: Path, cfg: Config, edits: Path | None, textures: tuple[Path, ...]
) -> None:
    report = r.report
    frames = r.stage("ingest", cfg["ingest"].impl, IngestInputs(capture=capture)).frames
    cap = Capture.load(frames)
    plan = make_plan(cap, cfg, edits)

    step = plan.get("poses")
    if step.run:
        frames = r.stage("poses", step.impl, PosesInputs(frames=frames), step.reason).frames
    else:
        r.skip("poses", step.impl, step.reason)
    # SfM's world has an arbitrary turn about z: the first camera fixes the plan's frame then
    frames = r.stage("align", cfg["align"].impl, AlignInputs(frames, free_yaw=step.run)).frames
    step = plan.get("depth")
    nerf = None
    if step.run:  # photos only: the NeRF's rendered depth is what fusion integrates
        nerf = r.stage("nerf", cfg["nerf"].impl, NerfInputs(frames=frames), step.reason)
        frames = nerf.frames
    else:
        r.skip("depth", step.impl, step.reason)
    fused = r.stage("fusion", cfg["fusion"].impl, FusionInputs(frames=frames))
    labelled = fused.frames  # the frames the plan is projected from
    step = plan.get("semantics")
    if step.run:
        sem = SemanticsInputs(frames=fused.frames, mesh=fused.mesh)
        labelled = r.stage("semantics", step.impl, sem, step.reason).frames
    else:
        r.skip("semantics", step.impl, step.reason)
    step = plan.get("nerf")
    if step.run:  # on the fused (dense, clean) depth and the labels: semantics and edits
        nerf = r.stage("nerf", step.impl, NerfInputs(frames=labelled), step.reason)
    else:
        r.skip("nerf", step.impl, step.reason)
    pts = r.stage(
        "project",
        cfg["project"].impl,
        ProjectInputs(frames=labelled, holdout=plan.heldout),
    )
    gt = gt_files(cap)
    plans = {}
    for m in cfg.run.methods:
        if m == "nerf_top":
            assert nerf is not None
            ins: object = NerfTopInputs(
                nerf.model,
                pts.points,
                pts.grid,
                gt.get("blueprint"),
                frames=labelled,
                gt_poses=gt.get("poses"),
                poses_estimated=plan.runs("poses"),
            )
        else:
            ins = BlueprintInputs(points=pts.points, grid=pts.grid)
        plans[m] = r.stage("blueprint", m, ins).blueprint
    if nerf is not None:
        report.metrics["nerf"] = _nerf_metrics(read_json(nerf.stats))
    step = plan.get("edit")
    if step.run:
        assert nerf is not None and edits is not None
        gt_dir = (
            Path(cap.gt) if cap.gt is not None and (Path(cap.gt) / "instances").is_dir() else None
        )
        ed = r.stage(
            "edit",
            step.impl,
            EditInputs(
                spec=edits,
                blueprint=plans[cfg.run.methods[0]],
                model=nerf.model,
                mesh=fused.mesh,
                frames=labelled,
                gt=gt_dir,
                textures=textures,
            ),
            step.reason,
        )
        report.metrics.update(read_json(ed.stats).get("metrics", {}))
        _publish_edits(ed, r.out / "edits")
        report.outputs["edits"] = str(r.out / "edits")
    else:
        r.skip("edit", step.impl, step.reason)

    step = plan.get("evaluate")
    if step.run:
        ev = r.stage(
            "evaluate",
            step.impl,
            EvaluateInputs(
                frames=labelled,
                gt=cap.gt if gt else None,  # gt_files lie in cap.gt
                blueprints=tuple(plans.values()),
                methods=tuple(plans),
                poses_estimated=plan.runs("poses"),
                heldout=pts.heldout if plan.heldout else None,
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


def _nerf_metrics(stats: dict) -> dict:
    """metrics.nerf: the fixed names, plus how training ended."""
    keys = ("psnr_heldout", "depth_absrel", "steps", "seconds", "stop_reason")
    return {k: stats[k] for k in keys if stats.get(k) is not None}


def _publish_edits(ed: EditOutputs, dst: Path) -> None:
    """The edit stage's pictures, plan and mesh into the run's edits/ folder."""
    dst.mkdir(exist_ok=True)
    files = [ed.gif, ed.blueprint, ed.blueprint_png, ed.mesh, ed.stats]
    files += sorted(ed.views.glob("*.png")) if ed.views.is_dir() else []
    for f in files:
        if f.is_file():
            _publish(f, dst / f.name)


def _publish(src: Path, dst: Path) -> None:
    """Copy src to dst atomically (temp file beside dst, then rename): a run sharing the
    folder, or a reader, never sees a half-copied output."""
    tmp = dst.with_name(f".{dst.name}.tmp-{os.getpid()}")
    try:
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)

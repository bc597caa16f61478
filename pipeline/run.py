"""The recipe: capture in, blueprint out. Paths, then one call per step of the plan."""

from __future__ import annotations

import logging
from pathlib import Path

from pipeline.checks import check_capture, check_edit_classes, check_sizes
from pipeline.config import Config
from pipeline.planner import gt_files, make_plan
from pipeline.publish import Publication, writing
from pipeline.report import Report
from pipeline.runner import OnEvent, Runner, check_impl
from stages.align import AlignInputs
from stages.blueprint import BlueprintInputs, NerfTopInputs
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import check_exists, read_json
from stages.depth import DepthInputs
from stages.edit import EditInputs, EditOutputs, EditSpec, load_spec
from stages.evaluate import EvaluateInputs
from stages.export.config import ExportInputs
from stages.fusion import FusionInputs
from stages.ingest.config import IngestInputs
from stages.layout import LayoutInputs, LayoutOutputs
from stages.nerf.config import NerfInputs, NerfOutputs
from stages.poses import PosesInputs
from stages.project import ProjectInputs
from stages.semantics import SemanticsInputs

log = logging.getLogger(__name__)


def run(capture: Path, out: Path, cfg: Config, edits: Path | None = None,
        on_event: OnEvent | None = None) -> Report:  # fmt: skip
    """Build the blueprint of `capture` into the run folder `out`; returns the report.
    `on_event`: each stage's start, end and progress (`pipeline.runner.Runner`)."""
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
    spec = load_spec(edits) if edits is not None else None  # a bad spec fails here
    if out.exists() and not out.is_dir():
        raise BlunfError(f"{out}: the run folder exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BlunfError(f"{out}: cannot create the run folder ({e.strerror})") from None
    pub = Publication(out)  # a read-only run folder fails here, before any work
    report = Report(scene=out.name, capture=str(capture.resolve()), config=cfg.to_dict())
    try:
        _recipe(Runner(out, cfg, report, on_event), pub, capture, cfg, spec)
        pub.add_report(report.to_json())  # report.json and report.html
        with writing(out):
            pub.switch()
    finally:  # a failed run switches nothing in: the previous run's outputs stay whole
        if not pub.switched:
            pub.discard()
    return report


def _recipe(r: Runner, pub: Publication, capture: Path, cfg: Config, spec: EditSpec | None) -> None:
    report = r.report
    frames = r.stage("ingest", cfg["ingest"].impl, IngestInputs(capture=capture)).frames
    cap = Capture.load(frames)
    with writing(frames.parent):  # what the frames decide fails here, before any costly stage
        check_capture(cap, spec, frames.parent / ".labels-checked")
    check_sizes(cap, cfg["depth"].stereo)  # settings whose memory follows the photos' size
    check_edit_classes(cap, spec, cfg["project"].labelling)
    plan = make_plan(cap, cfg, spec.path if spec is not None else None)

    posed = r.step(plan.get("poses"), PosesInputs(frames=frames))
    frames = posed.frames if posed else frames
    # SfM's world has an arbitrary turn about z: the first camera fixes the plan's frame then
    frames = r.step(plan.get("align"), AlignInputs(frames, free_yaw=posed is not None)).frames
    depth = r.step(plan.get("depth"), DepthInputs(frames=frames))  # photos only: stereo, fills
    read = depth.frames if depth else frames  # the depth the fusion reads
    fused = r.step(plan.get("fusion"), FusionInputs(frames=read))
    # what the views saw, for the point walls: the SfM tracks (the aligned frames) and what
    # fusion read; the semantics stage alone decides whether to use it (semantics.point_walls)
    seen = (frames, depth.frames) if depth else ()
    sem = r.step(plan.get("semantics"), SemanticsInputs(fused.frames, fused.mesh, seen, read))
    labelled = sem.frames if sem else fused.frames  # the frames the plan is projected from
    # on the fused (dense, clean) depth and the labels: for the NeRF baseline and edits
    nerf = r.step(plan.get("nerf"), NerfInputs(frames=labelled))
    if nerf is None and depth is not None and (depth.field / "model.pt").is_file():
        nerf = NerfOutputs.at(depth.field)  # the depth step's field fill, when it trained
    pts = r.step(
        plan.get("project"), ProjectInputs(frames=labelled, holdout=plan.heldout, readings=read)
    )
    gt = gt_files(cap)
    plans = {}
    for step in plan.all("blueprint"):
        ins: object = BlueprintInputs(points=pts.points, grid=pts.grid, observed=pts.observed)
        if step.impl == "nerf_top":
            ins = NerfTopInputs(
                nerf.model,
                pts.points,
                pts.grid,
                gt.get("blueprint"),
                frames=labelled,
                gt_poses=gt.get("poses"),
                poses_estimated=plan.runs("poses"),
            )
        plans[step.impl] = r.step(step, ins).blueprint
    product = plans[cfg.run.methods[0]]
    if nerf is not None:
        report.metrics["nerf"] = _nerf_metrics(read_json(nerf.stats))

    gt_dir = Path(cap.gt) if cap.gt is not None and (Path(cap.gt) / "instances").is_dir() else None
    ed = r.step(
        plan.get("edit"),
        lambda: EditInputs(
            spec=spec.path if spec else Path(),
            blueprint=product,
            model=nerf.model,
            mesh=fused.mesh,
            frames=labelled,
            gt=gt_dir,
            depth=depth.frames if depth else frames,  # the depth fusion read
            textures=spec.textures if spec else (),
        ),
    )
    # the plan as an architect draws it: walls, rooms, openings, object footprints
    lay = r.step(plan.get("layout"), LayoutInputs(blueprint=product, mesh=fused.mesh))
    _publish_layout(lay, pub, "")
    for f in (lay.plan_json, lay.plan_svg, lay.plan_dxf):
        report.outputs[f.name] = str(r.out / f.name)
    if ed is not None:
        report.metrics.update(read_json(ed.stats).get("metrics", {}))
        _publish_edits(ed, pub)
        _publish_spec(spec, r.out, pub)
        # the edited plan drawn again, so that a removed object leaves plan.svg too
        step = plan.get("layout")
        edited = r.stage("layout", step.impl, LayoutInputs(blueprint=ed.blueprint, mesh=ed.mesh))
        _publish_layout(edited, pub, "edits/")
        report.outputs["edits"] = str(r.out / "edits")

    ev = r.step(
        plan.get("evaluate"),
        EvaluateInputs(
            frames=labelled,
            gt=cap.gt if gt else None,  # gt_files lie in cap.gt
            blueprints=tuple(plans.values()),
            methods=tuple(plans),
            poses_estimated=plan.runs("poses"),
            heldout=pts.heldout if plan.heldout else None,
            layout=lay.plan_json,
            points=pts.points,
            observed=pts.observed,
        ),
    )
    if ev is not None:
        report.metrics.update(read_json(ev.metrics))

    ex = r.step(
        plan.get("export"),
        ExportInputs(blueprint=product, mesh=fused.mesh, frames=fused.frames, layout=lay.plan_json),
    )
    for name in ex.files:
        pub.add(ex.folder / name, name)
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


def _publish_layout(lay: LayoutOutputs, pub: Publication, prefix: str) -> None:
    """plan.json / .svg / .dxf into the run folder (or its edits/ folder)."""
    for f in (lay.plan_json, lay.plan_svg, lay.plan_dxf):
        pub.add(f, f"{prefix}{f.name}")


def _publish_edits(ed: EditOutputs, pub: Publication) -> None:
    """The edit stage's pictures, plan and mesh into the run's edits/ folder."""
    files = [ed.gif, ed.blueprint, ed.blueprint_png, ed.mesh, ed.stats]
    files += sorted(ed.views.glob("*.png")) if ed.views.is_dir() else []
    for f in files:
        if f.is_file():
            pub.add(f, f"edits/{f.name}")


def _publish_spec(spec: EditSpec | None, out: Path, pub: Publication) -> None:
    """A spec kept in the run's own edits/ folder (the studio saves RUN/edits/studio.yaml)
    stays there, with its textures, when this run's edits/ replaces that folder."""
    folder = (out / "edits").resolve()
    if spec is None or not spec.path.resolve().is_relative_to(folder):
        return
    for f in (spec.path.resolve(), *spec.textures):
        pub.add(f, f"edits/{f.relative_to(folder)}")

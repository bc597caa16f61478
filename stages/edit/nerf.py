"""Edit stage, NeRF implementation: an edit spec applied on the plan, rendered through the field.

Everything the spec refers to is checked first (keys, textures, clicks on the plan, classes,
view indices, input files): a bad spec fails with one line and nothing written. Then each
selection becomes a 3-D extent over the fused mesh, the edits wrap the trained field while
rendering (no retraining), and the stage writes before | after pictures per requested view,
each selection's masks, an orbit GIF of the edited scene, the edited plan (removed cells
become floor, or unknown when `removed_label` says so or the selection was floor),
mesh_edited.ply, and edit.json with per-edit metrics (changed_iou against ground-truth
instance masks when the capture has them, psnr_outside always).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image

from stages.common.blueprint import Blueprint
from stages.common.camera import Intrinsics
from stages.common.capture import Capture
from stages.common.components import component_map
from stages.common.errors import BlunfError
from stages.common.io import (
    write_image,
    write_json,
    write_label_png,
)
from stages.common.plan_picture import plan_png
from stages.common.progress import track
from stages.common.threads import torch_threads
from stages.edit.config import EditConfig, EditInputs, EditOutputs
from stages.edit.metrics import EditScore, gt_instance_names, gt_instances
from stages.edit.ops import (
    FieldEdit,
    edit_mesh,
    reference_luminance,
)
from stages.edit.refine import boxes_of, refine_mesh
from stages.edit.render import orbit_poses
from stages.edit.select import edited_plan, select_cells
from stages.edit.spec import EditSpec, check_views, load_spec
from stages.edit.view import EditedView, load_mesh, load_model, scaled, tint, to_u8

log = logging.getLogger(__name__)

ORBIT_TARGET_Z = 0.5  # default orbit: cameras look at this height above the camera centroid
SEPARATOR = 4  # white pixels between before and after


@dataclass(frozen=True)
class View:
    name: str  # file name stem: the frame's stem, or orbit_<k>
    pose: np.ndarray  # [4, 4] camera-to-world
    intr: Intrinsics
    stem: str | None  # the frame's stem (ground truth lookup); None on an orbit


def run(cfg: EditConfig, inputs: EditInputs, out: Path) -> EditOutputs:
    """Apply the spec's edits; write renders, masks, GIF, edited plan and mesh, edit.json."""
    log.debug("edit/nerf: %s", cfg)  # the full config: meta.json
    t_start = time.perf_counter()
    out = Path(out)
    spec, bp, cap, cells, cmap = _checked(inputs)
    outs = EditOutputs.at(out)

    mesh = load_mesh(inputs.mesh)
    with torch_threads(cfg.render.threads):
        view = EditedView(cfg, load_model(inputs.model), mesh, bp, cmap)
        edits: list[FieldEdit] = []  # as applied to the field
        mesh_edits: list[FieldEdit] = []  # the same, shaded against the mesh's colours
        records: list[dict] = []
        for e, sel in zip(spec.edits, cells, strict=True):
            r = view.resolve(e, sel)
            ext, fill = r.edit.extent, r.edit.fill
            colors = view.colors
            ref_mesh = None if colors is None else reference_luminance(ext, view.verts, colors)
            edits.append(r.edit)
            mesh_edits.append(replace(r.edit, ref_lum=ref_mesh))
            records.append(
                {
                    "index": e.index,
                    "op": e.op,
                    "select": {"kind": e.select.kind, "value": e.select.value},
                    "cells": int(sel.sum()),
                    "footprint_cells": int(ext.footprint.sum()),
                    "components": r.components,
                    "ref_luminance": {"field": _round(r.edit.ref_lum), "mesh": _round(ref_mesh)},
                    "fill": None if fill is None else [round(float(v), 4) for v in fill],
                }
            )
        views = _views(spec, cap, cfg)
        cast_v, cast_f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        refined = None
        if cfg.render.path == "surface" and cfg.refine.voxel > 0 and inputs.depth is not None:
            objects = [
                e.extent
                for e, r in zip(edits, records, strict=True)
                if all(c["class"] != cfg.select.floor_class for c in r["components"])
            ]
            cast_v, cast_f, refined = refine_mesh(
                cast_v, cast_f, boxes_of(objects, view.verts, cfg.refine.margin), inputs.depth,
                cfg.refine.voxel, cfg.refine.trunc,
            )  # fmt: skip
        view.cast = (cast_v, cast_f)  # before the first fast render
        scored = _render_views(cfg, view, views, edits, outs, inputs.gt, records)
        t_gif = time.perf_counter()
        _gif(cfg, view, spec, cap, edits, scored["orbit_frames"], outs.gif)
        gif_seconds = time.perf_counter() - t_gif

    new_bp, n_changed = edited_plan(cfg, bp, spec, cells)
    new_bp.save(outs.blueprint)
    plan_png(new_bp, outs.blueprint_png, title="edited")
    mesh_new, mesh_stats = edit_mesh(mesh, mesh_edits)
    mesh_new.export(outs.mesh)

    metrics = [
        {"index": r["index"], "op": r["op"], **{k: r["metrics"][k] for k in METRIC_KEYS}}
        for r in records
    ]  # the report's metrics.edit
    write_json(
        outs.stats,
        {
            "spec": str(inputs.spec),
            "views": [v.name for v in views],
            "orbit": None if spec.orbit is None else asdict(spec.orbit),
            "edits": records,
            "blueprint": {
                "removed_to": cfg.removed_label,
                "cells_changed": n_changed,
            },
            "mesh": mesh_stats,
            "render": {
                "path": cfg.render.path,
                "size": [views[0].intr.width, views[0].intr.height],
                "renders": scored["renders"],
                "seconds": round(scored["seconds"], 3),
                "gif_seconds": round(gif_seconds, 3),
                "refined": refined,
            },
            "seconds": round(time.perf_counter() - t_start, 3),
            "metrics": {"edit": metrics},
        },
    )
    log.info("edit/nerf: %d edits, %d views in %.1f s", len(edits), len(views), scored["seconds"])
    return outs


METRIC_KEYS = ("changed_iou", "changed_iou_views", "psnr_outside")


# ---- checks: all before any work ---------------------------------------------------------
def _checked(
    inputs: EditInputs,
) -> tuple[EditSpec, Blueprint, Capture, list[np.ndarray], np.ndarray]:
    """The spec, plan, capture, each edit's selected cells and the plan's component map, or
    a one-line error."""
    spec = load_spec(inputs.spec)
    listed = {Path(p).resolve() for p in inputs.textures}
    for t in spec.textures:
        if t not in listed:
            raise BlunfError(
                f"{inputs.spec}: texture {t} is not in EditInputs.textures "
                "(pass spec_textures(spec), so that a changed texture reruns the stage)"
            )
    bp = Blueprint.load(inputs.blueprint)
    cap = Capture.load(inputs.frames)
    if not cap.frames:
        raise BlunfError(f"{inputs.frames}: no frames")
    check_views(spec, len(cap.frames))
    for i in spec.views:
        if cap.frames[i].pose is None:
            raise BlunfError(f"{inputs.frames}: frame {i} ({cap.frames[i].stem}) has no pose")
    cmap = component_map(bp)
    cells = [select_cells(e.select, bp, cmap) for e in spec.edits]
    for name in ("model", "mesh"):
        p = Path(getattr(inputs, name))
        if not p.is_file():
            raise BlunfError(f"{p}: {name} file not found")
    return spec, bp, cap, cells, cmap


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 4)


# ---- rendering ----------------------------------------------------------------------------
def _views(spec: EditSpec, cap: Capture, cfg: EditConfig) -> list[View]:
    if spec.orbit is None:
        return [
            View(
                cap.frames[i].stem,
                np.asarray(cap.frames[i].pose),
                scaled(cap.frames[i].intrinsics, cfg.render.scale),
                cap.frames[i].stem,
            )
            for i in spec.views
        ]
    o = spec.orbit
    intr = scaled(cap.frames[0].intrinsics, cfg.render.scale)
    poses = orbit_poses(o.center, o.radius, o.height, o.frames)
    return [View(f"orbit_{k:03d}", p, intr, None) for k, p in enumerate(poses)]


def _render_views(
    cfg: EditConfig,
    view: EditedView,
    views: list[View],
    edits: list[FieldEdit],
    outs: EditOutputs,
    gt: Path | None,
    records: list[dict],
) -> dict:
    """Before / after per view (written), each edit's masks, and the per-edit metrics."""
    outs.views.mkdir()
    outs.masks.mkdir()
    t0 = time.perf_counter()
    field_ops = [e for e in edits if e.op != "mask"]
    scores = [EditScore(cfg.change_threshold) for _ in edits]
    renders = 0
    orbit_frames = []
    for k, v in enumerate(track(views, "edit render", unit="view")):
        before = view.before(v.pose, v.intr, edits)
        after = view.render(v.pose, v.intr, edits, unedited=before)
        renders += before.renders + after.renders
        sel = before.masks  # [E, H, W]
        if v.stem is None:
            orbit_frames.append(after.image)
        pair = [before.rgb, np.ones((v.intr.height, SEPARATOR, 3)), after.rgb]
        write_image(outs.views / f"{v.name}.png", to_u8(np.concatenate(pair, axis=1)))
        inst = gt_instances(gt, v.stem, v.intr.width, v.intr.height) if gt and v.stem else None
        for i, e in enumerate(edits):
            write_label_png(outs.masks / f"{v.name}_{i}.png", sel[i].astype(np.uint8) * 255)
            if e.op == "mask":
                single = tint(before.rgb, sel[i])
            elif len(field_ops) == 1:  # rendered above already
                single = after.field_rgb
            else:  # this edit alone
                alone = view.render(v.pose, v.intr, [e])
                single, renders = alone.rgb, renders + alone.renders
            scores[i].add(before.rgb, single, sel[i], inst)
        log.info("edit/nerf: view %d/%d (%s) rendered", k + 1, len(views), v.name)
    names = gt_instance_names(gt)
    for rec, score in zip(records, scores, strict=True):
        rec["metrics"] = score.result(names)
    return {"renders": renders, "seconds": time.perf_counter() - t0, "orbit_frames": orbit_frames}


def _gif(
    cfg: EditConfig,
    view: EditedView,
    spec: EditSpec,
    cap: Capture,
    edits: list[FieldEdit],
    frames: list[np.ndarray],
    path: Path,
) -> None:
    """The edited scene along the spec's orbit (frames already rendered) or a default orbit
    around the cameras: centroid of their positions at ORBIT_TARGET_Z, their mean height and
    mean horizontal distance from the centroid."""
    if not frames:
        centers = cap.poses()[:, :3, 3]  # [C, 3]
        c = centers.mean(axis=0)
        radius = float(np.linalg.norm(centers[:, :2] - c[:2], axis=1).mean()) or 1.0
        poses = orbit_poses((c[0], c[1], ORBIT_TARGET_Z), radius, float(c[2]), cfg.gif.frames)
        intr = scaled(cap.frames[0].intrinsics, cfg.gif.scale)
        for pose in track(poses, "edit orbit", unit="frame"):
            frames.append(view.render(pose, intr, edits).image)
    imgs = [Image.fromarray(f) for f in frames]
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=cfg.gif.ms, loop=0)

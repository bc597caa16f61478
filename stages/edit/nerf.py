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
import pickle
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image
from scipy import ndimage

from stages.common.blueprint import Blueprint
from stages.common.camera import Intrinsics
from stages.common.capture import Capture
from stages.common.components import component_map
from stages.common.errors import BlunfError
from stages.common.io import (
    read_image,
    write_image,
    write_json,
    write_label_png,
)
from stages.common.plan_picture import plan_png
from stages.common.progress import track
from stages.common.radiance.field import load_field
from stages.common.threads import torch_threads
from stages.edit.config import EditConfig, EditInputs, EditOutputs
from stages.edit.metrics import EditScore, gt_instance_names, gt_instances
from stages.edit.ops import (
    FieldEdit,
    edit_mesh,
    field_color,
    field_luminance,
    reference_luminance,
    vertex_colors,
)
from stages.edit.refine import boxes_of, refine_mesh
from stages.edit.render import orbit_poses, render_view_edited
from stages.edit.select import Extent, edited_plan, extent_of, select_cells
from stages.edit.spec import Edit, EditSpec, check_views, load_spec
from stages.edit.surface import SurfaceRenderer

log = logging.getLogger(__name__)

MASK_TINT = np.array([1.0, 0.0, 1.0])  # mask edits: selected pixels blended half with magenta
ORBIT_TARGET_Z = 0.5  # default orbit: cameras look at this height above the camera centroid
SEPARATOR = 4  # white pixels between before and after
REF_POINTS = 20000  # surface points at most whose field colour sets a selection's reference
FILL_RING = 0.2  # metres round a removed footprint whose fused floor's colour fills under it


Draw = Callable[..., dict]  # (pose, intr, edits, masks=()) -> render_view_edited's dict


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

    mesh = _load_mesh(inputs.mesh)
    verts = np.asarray(mesh.vertices, np.float64)  # [V, 3]
    rgba = vertex_colors(mesh)  # [V, 4] or None
    colors = None if rgba is None else rgba[:, :3].astype(np.float64) / 255.0  # [V, 3]
    with torch_threads(cfg.threads):
        model = _load_model(inputs.model)
        edits: list[FieldEdit] = []  # as applied to the field
        mesh_edits: list[FieldEdit] = []  # the same, shaded against the mesh's colours
        records: list[dict] = []
        for e, sel in zip(spec.edits, cells, strict=True):
            ext, comps = extent_of(sel, bp, cmap, verts, cfg)
            inside = verts[ext.contains(verts)]  # [M, 3] fused surface inside the extent
            ref_field = field_luminance(model.fns(semantics=False), inside, REF_POINTS)
            ref_mesh = None if colors is None else reference_luminance(ext, verts, colors)
            fill = _fill(cfg, e, ext, comps, verts, colors, model)
            edits.append(_field_edit(e, ext, ref_field, fill))
            mesh_edits.append(replace(edits[-1], ref_lum=ref_mesh))
            records.append(
                {
                    "index": e.index,
                    "op": e.op,
                    "select": {"kind": e.select.kind, "value": e.select.value},
                    "cells": int(sel.sum()),
                    "footprint_cells": int(ext.footprint.sum()),
                    "components": comps,
                    "ref_luminance": {"field": _round(ref_field), "mesh": _round(ref_mesh)},
                    "fill": None if fill is None else [round(float(v), 4) for v in fill],
                }
            )
        views = _views(spec, cap, cfg)
        cast_v, cast_f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        refined = None
        if cfg.render == "surface" and cfg.refine_voxel > 0 and inputs.depth is not None:
            objects = [
                e.extent
                for e, r in zip(edits, records, strict=True)
                if all(c["class"] != cfg.floor_class for c in r["components"])
            ]
            cast_v, cast_f, refined = refine_mesh(
                cast_v, cast_f, boxes_of(objects, verts, cfg.refine_margin), inputs.depth,
                cfg.refine_voxel, cfg.refine_trunc,
            )  # fmt: skip
        draw = _drawer(cfg, model, cast_v, cast_f)
        scored = _render_views(cfg, draw, views, edits, outs, inputs.gt, records)
        t_gif = time.perf_counter()
        _gif(cfg, draw, spec, cap, edits, scored["orbit_frames"], outs.gif)
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
                "path": cfg.render,
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


def resolve_edit(
    cfg: EditConfig,
    e: Edit,
    sel: np.ndarray,
    bp: Blueprint,
    cmap: np.ndarray,
    verts: np.ndarray,
    colors: np.ndarray | None,
    model,
) -> FieldEdit:
    """One edit as `run` wraps the field with it (extent, reference luminance, ground fill),
    for callers that render edits one view at a time (`blunf render`, the studio)."""
    ext, comps = extent_of(sel, bp, cmap, verts, cfg)
    inside = verts[ext.contains(verts)]  # [M, 3]
    ref = field_luminance(model.fns(semantics=False), inside, REF_POINTS)
    return _field_edit(e, ext, ref, _fill(cfg, e, ext, comps, verts, colors, model))


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 4)


def _load_model(path: Path):
    try:
        return load_field(path)
    except pickle.UnpicklingError as e:  # load_field does not catch this one
        raise BlunfError(f"{path}: not a NeRF model ({e.__class__.__name__})") from None


def _load_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on a broken file
        raise BlunfError(f"{path}: not a readable mesh ({e.__class__.__name__})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise BlunfError(f"{path}: the mesh has no vertices")
    return mesh


def _fill(
    cfg: EditConfig,
    e: Edit,
    ext: Extent,
    comps: list[dict],
    verts: np.ndarray,
    colors: np.ndarray | None,
    model,
) -> torch.Tensor | None:
    """A removal's ground fill: the median colour of the fused floor (|z| <= floor_band) in a
    FILL_RING band round the footprint, from the mesh's vertex colours (what the photos showed
    there), or from the field when the mesh has none. None for other ops, for a removal of
    floor itself, and when no floor surrounds the footprint."""
    if e.op != "remove" or any(c["class"] == cfg.floor_class for c in comps):
        return None
    grow = max(1, round(FILL_RING / ext.grid.cell))
    ring = ndimage.binary_dilation(ext.footprint, iterations=grow) & ~ext.footprint  # [H, W]
    ring_ext = Extent(ext.grid, np.where(ring, -cfg.floor_band, np.inf).astype(np.float32),
                      np.where(ring, cfg.floor_band, -np.inf).astype(np.float32))  # fmt: skip
    on = ring_ext.contains(verts)  # [V] fused floor round the footprint
    if not on.any():
        return None
    if colors is not None:
        return torch.from_numpy(np.median(colors[on], axis=0).astype(np.float32))
    return field_color(model.fns(semantics=False), verts[on], REF_POINTS)


def _field_edit(
    e: Edit, ext: Extent, ref: float | None, fill: torch.Tensor | None = None
) -> FieldEdit:
    color = None if e.color is None else torch.tensor(e.color, dtype=torch.float32) / 255.0
    tex = None
    if e.texture is not None:
        tex = torch.from_numpy(read_image(e.texture).astype(np.float32) / 255.0)  # [Ht, Wt, 3]
    return FieldEdit(e.op, ext, color, e.strength, tex, ref, fill)


# ---- rendering ----------------------------------------------------------------------------
def _scaled(intr: Intrinsics, s: float) -> Intrinsics:
    if s == 1.0:
        return intr
    return intr.scaled(max(1, round(intr.width * s)), max(1, round(intr.height * s)))


def _views(spec: EditSpec, cap: Capture, cfg: EditConfig) -> list[View]:
    if spec.orbit is None:
        return [
            View(
                cap.frames[i].stem,
                np.asarray(cap.frames[i].pose),
                _scaled(cap.frames[i].intrinsics, cfg.render_scale),
                cap.frames[i].stem,
            )
            for i in spec.views
        ]
    o = spec.orbit
    intr = _scaled(cap.frames[0].intrinsics, cfg.render_scale)
    poses = orbit_poses(o.center, o.radius, o.height, o.frames)
    return [View(f"orbit_{k:03d}", p, intr, None) for k, p in enumerate(poses)]


def _overlay(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """rgb [H, W, 3] with the pixels of mask [H, W] blended half with MASK_TINT."""
    return np.where(mask[..., None], 0.5 * rgb + 0.5 * MASK_TINT, rgb)


def _drawer(cfg: EditConfig, model, vertices: np.ndarray, faces: np.ndarray) -> Draw:
    """The view renderer `cfg.render` names (the surface path casts the mesh `vertices`,
    `faces`), called as draw(pose, intr, edits, masks) -> render_view_edited's dict."""
    if cfg.render == "surface":
        fast = SurfaceRenderer(model, vertices, faces)
        return lambda pose, intr, ops, masks=(): fast.render_view(pose, intr, ops, masks, cfg.chunk)
    return lambda pose, intr, ops, masks=(): render_view_edited(
        model, pose, intr, ops, cfg.chunk, masks
    )


def _render_views(
    cfg: EditConfig,
    draw: Draw,
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
    extents = [e.extent for e in edits]
    field_ops = [e for e in edits if e.op != "mask"]
    scores = [EditScore(cfg.change_threshold) for _ in edits]
    renders = 0
    orbit_frames = []
    for k, v in enumerate(track(views, "edit render", unit="view")):
        before = draw(v.pose, v.intr, (), extents)
        renders += 1
        sel = before["masks"] >= cfg.mask_threshold  # [E, H, W]
        after = before["rgb"]
        if field_ops:
            after = draw(v.pose, v.intr, field_ops)["rgb"]
            renders += 1
        after_field = after  # the field edits' render, before any mask overlay
        for i, e in enumerate(edits):
            if e.op == "mask":
                after = _overlay(after, sel[i])
        if v.stem is None:
            orbit_frames.append(_u8(after))
        pair = [before["rgb"], np.ones((v.intr.height, SEPARATOR, 3)), after]
        write_image(outs.views / f"{v.name}.png", _u8(np.concatenate(pair, axis=1)))
        inst = gt_instances(gt, v.stem, v.intr.width, v.intr.height) if gt and v.stem else None
        for i, e in enumerate(edits):
            write_label_png(outs.masks / f"{v.name}_{i}.png", sel[i].astype(np.uint8) * 255)
            if e.op == "mask":
                single = _overlay(before["rgb"], sel[i])
            elif len(field_ops) == 1:  # rendered above already
                single = after_field
            else:  # this edit alone
                single = draw(v.pose, v.intr, [e])["rgb"]
                renders += 1
            scores[i].add(before["rgb"], single, sel[i], inst)
        log.info("edit/nerf: view %d/%d (%s) rendered", k + 1, len(views), v.name)
    names = gt_instance_names(gt)
    for rec, score in zip(records, scores, strict=True):
        rec["metrics"] = score.result(names)
    return {"renders": renders, "seconds": time.perf_counter() - t0, "orbit_frames": orbit_frames}


def _u8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _gif(
    cfg: EditConfig,
    draw: Draw,
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
        poses = orbit_poses((c[0], c[1], ORBIT_TARGET_Z), radius, float(c[2]), cfg.gif_frames)
        intr = _scaled(cap.frames[0].intrinsics, cfg.gif_scale)
        field_ops = [e for e in edits if e.op != "mask"]
        masks = [e.extent for e in edits if e.op == "mask"]
        for pose in track(poses, "edit orbit", unit="frame"):
            r = draw(pose, intr, field_ops, masks)
            rgb = r["rgb"]
            for m in r["masks"]:
                rgb = _overlay(rgb, m >= cfg.mask_threshold)
            frames.append(_u8(rgb))
    imgs = [Image.fromarray(f) for f in frames]
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=cfg.gif_ms, loop=0)

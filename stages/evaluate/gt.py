"""The evaluate stage: every metric the capture's ground truth allows, under the fixed names."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.capture import Capture
from stages.common.gt_frame import FRAME_ALIGNED, plan_frame, pose_pairs, pose_similarity
from stages.common.io import read_json, write_json
from stages.common.plan_metrics import evaluate_plan
from stages.evaluate.config import EvaluateConfig, EvaluateInputs, EvaluateOutputs
from stages.evaluate.heldout import heldout_pixels, score_pixels
from stages.evaluate.layout import layout_to_frame, score_layout
from stages.evaluate.observation import observation
from stages.evaluate.poses import pose_metrics


def run(cfg: EvaluateConfig, inputs: EvaluateInputs, out: Path) -> EvaluateOutputs:
    """Score each blueprint against gt/blueprint.npz and estimated poses against gt/poses.json.

    Plans built from estimated poses live in the reconstruction's frame: they are read at
    the GT cell centres mapped through the similarity from the frames' camera centres to the
    GT ones. Given poses are used so too when the align stage moved them (e.g. a Manhattan
    yaw) by more than a tenth of a GT cell. Each plan's metrics record the frame under "frame".
    With a heldout.json listing views, each plan is also scored on those views' labelled
    pixels (heldout.py), in its own frame: no ground truth needed for that, nor for
    metrics.observation (observation.py), which every run gets.
    """
    metrics: dict = {}
    gt_dir = inputs.gt
    gt_poses = gt_dir / "poses.json" if gt_dir is not None else None
    est: dict[str, np.ndarray] = {}
    gtp: dict[str, np.ndarray] = {}
    # ground truth is in the capture's world; the frames are that world less the offset
    # ingest took off far poses (Capture.origin): ground truth is moved by it too
    origin = np.asarray(Capture.load(inputs.frames).origin, np.float64)
    if gt_poses is not None and gt_poses.is_file() and (inputs.poses_estimated or cfg.plan):
        est, gtp = pose_pairs(inputs.frames, gt_poses)
        gtp = {k: _moved(T, -origin) for k, T in gtp.items()}
    gt_plan = gt_dir / "blueprint.npz" if gt_dir is not None else None
    if gt_plan is not None and gt_plan.is_file() and cfg.plan:
        gt = Blueprint.load(gt_plan)
        if origin[:2].any():
            g = gt.grid
            o = (g.origin[0] - origin[0], g.origin[1] - origin[1])
            gt = replace(gt, grid=replace(g, origin=o))
        pred_to_gt, frame = plan_frame(inputs.poses_estimated, est, gtp, gt.grid)
        if frame == FRAME_ALIGNED:  # how well the shared poses fix that frame
            common = [k for k in gtp if k in est]
            metrics["alignment"] = pose_similarity(
                [est[k] for k in common], [gtp[k] for k in common]
            )[1]
        metrics["blueprint"] = {
            m: {**evaluate_plan(Blueprint.load(p), gt, pred_to_gt), "frame": frame}
            for m, p in zip(inputs.methods, inputs.blueprints, strict=True)
        }
        gt_layout = gt_dir / "layout.json" if gt_dir is not None else None
        if inputs.layout is not None and gt_layout is not None and gt_layout.is_file():
            pred = layout_to_frame(read_json(inputs.layout), pred_to_gt)
            metrics["layout"] = score_layout(pred, read_json(gt_layout))
    if gtp and inputs.poses_estimated and cfg.poses:
        metrics["poses"] = pose_metrics(est, gtp)
    if inputs.heldout is not None and cfg.heldout:
        stems = [str(s) for s in read_json(inputs.heldout).get("stems", [])]
        if stems:
            cap = Capture.load(inputs.frames)
            xy, lab, inward = heldout_pixels(cap, stems, cfg.heldout_stride)  # lifted once
            for m, p in zip(inputs.methods, inputs.blueprints, strict=True):
                scores = score_pixels(Blueprint.load(p), cap, xy, lab, len(stems), inward)
                metrics.setdefault("blueprint", {}).setdefault(m, {}).update(scores)
    if (inputs.points is not None or inputs.observed is not None) and inputs.blueprints:
        metrics["observation"] = observation(
            inputs.blueprints[0], inputs.points, inputs.layout, inputs.observed
        )
    write_json(out / "metrics.json", metrics)
    return EvaluateOutputs.at(out)


def _moved(T: np.ndarray, by: np.ndarray) -> np.ndarray:
    """A camera-to-world pose with its centre moved by `by` (metres)."""
    T = np.array(T, np.float64)
    T[:3, 3] += by
    return T

"""The evaluate stage: every metric the capture's ground truth allows, under the fixed names."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import Capture
from stages.common.io import read_json, write_json
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.heldout import heldout_pixels, score_pixels
from stages.evaluate.plan import evaluate_plan, to_frame
from stages.evaluate.poses import pose_metrics, similarity

log = logging.getLogger(__name__)

FRAME_GT = "gt"  # the plan was built in the ground truth's frame (given poses, not moved)
FRAME_ALIGNED = "aligned to gt poses"  # read through the camera-centre similarity
FRAME_UNALIGNED = "estimated, not aligned"  # estimated poses that could not be aligned


@dataclass(frozen=True)
class EvaluateInputs:
    frames: Path  # frames.json the plans were projected from (poses; depth and labels for
    #               the held-out views)
    gt: Path | None  # the capture's gt/ folder (None: the capture has none)
    blueprints: tuple[Path, ...]  # blueprint.npz of each method
    methods: tuple[str, ...]  # the method name of each blueprint
    poses_estimated: bool  # score poses only when a stage estimated them
    heldout: Path | None = None  # the project stage's heldout.json (None: no held-out score)


@dataclass(frozen=True)
class EvaluateOutputs:
    STATS: ClassVar[str | None] = None  # metrics.json feeds report.metrics
    metrics: Path  # metrics.json: {"blueprint": {method: {...}}, "poses": {...}}; held-out
    #                scores under blueprint.<method>.heldout_pacc

    @classmethod
    def at(cls, out: Path) -> EvaluateOutputs:
        return cls(out / "metrics.json")


def run(cfg: EvaluateConfig, inputs: EvaluateInputs, out: Path) -> EvaluateOutputs:
    """Score each blueprint against gt/blueprint.npz and estimated poses against gt/poses.json.

    Plans built from estimated poses live in the reconstruction's frame: they are read at
    the GT cell centres mapped through the similarity from the frames' camera centres to the
    GT ones. Given poses are used so too when the align stage moved them (e.g. a Manhattan
    yaw) by more than a tenth of a GT cell. Each plan's metrics record the frame under "frame".
    With a heldout.json listing views, each plan is also scored on those views' labelled
    pixels (heldout.py), in its own frame: no ground truth needed for that.
    """
    metrics: dict = {}
    gt_dir = inputs.gt
    gt_poses = gt_dir / "poses.json" if gt_dir is not None else None
    est: dict[str, np.ndarray] = {}
    gtp: dict[str, np.ndarray] = {}
    if gt_poses is not None and gt_poses.is_file() and (inputs.poses_estimated or cfg.plan):
        est, gtp = pose_pairs(inputs.frames, gt_poses)
    gt_plan = gt_dir / "blueprint.npz" if gt_dir is not None else None
    if gt_plan is not None and gt_plan.is_file() and cfg.plan:
        gt = Blueprint.load(gt_plan)
        pred_to_gt, frame = plan_frame(inputs.poses_estimated, est, gtp, gt.grid)
        metrics["blueprint"] = {
            m: {**evaluate_plan(Blueprint.load(p), gt, pred_to_gt), "frame": frame}
            for m, p in zip(inputs.methods, inputs.blueprints, strict=True)
        }
    if gtp and inputs.poses_estimated and cfg.poses:
        metrics["poses"] = pose_metrics(est, gtp)
    if inputs.heldout is not None and cfg.heldout:
        stems = [str(s) for s in read_json(inputs.heldout).get("stems", [])]
        if stems:
            cap = Capture.load(inputs.frames)
            xy, lab = heldout_pixels(cap, stems, cfg.heldout_stride)  # lifted once
            for m, p in zip(inputs.methods, inputs.blueprints, strict=True):
                scores = score_pixels(Blueprint.load(p), cap, xy, lab, len(stems))
                metrics.setdefault("blueprint", {}).setdefault(m, {}).update(scores)
    write_json(out / "metrics.json", metrics)
    return EvaluateOutputs.at(out)


def pose_pairs(frames: Path, gt_poses: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(stem -> [4, 4] pose of frames.json, stem -> [4, 4] ground-truth pose of poses.json)."""
    cap = Capture.load(frames)
    est = {f.stem: np.asarray(f.pose, np.float64) for f in cap.frames if f.pose is not None}
    return est, {k: np.asarray(v, np.float64) for k, v in read_json(gt_poses).items()}


def gt_frame(
    frames: Path, gt_poses: Path | None, estimated: bool, grid: Grid
) -> tuple[np.ndarray | None, str]:
    """plan_frame for the plans projected from frames.json, given the capture's GT poses
    (None or missing: the plans are taken to be in the GT frame unless poses were estimated)."""
    if gt_poses is None or not gt_poses.is_file():
        return plan_frame(estimated, {}, {}, grid)
    return plan_frame(estimated, *pose_pairs(frames, gt_poses), grid)


def plan_frame(
    estimated: bool, est: dict[str, np.ndarray], gt: dict[str, np.ndarray], grid: Grid
) -> tuple[np.ndarray | None, str]:
    """(prediction-to-GT similarity or None, the frame's name) for the plan metrics.

    Args:
        estimated: whether a stage estimated the poses the plans were built from.
        est: stem -> [4, 4] camera-to-world pose the plans were built from.
        gt: stem -> [4, 4] ground-truth camera-to-world pose (empty when there is none).
        grid: the GT plan's grid; given poses that the alignment moves by less than a tenth
            of its cell anywhere on it count as the GT frame itself.
    """
    common = [s for s in gt if s in est]
    m = None
    if common:
        ce = np.stack([est[s][:3, 3] for s in common])  # [C, 3] camera centres of the plans
        cg = np.stack([gt[s][:3, 3] for s in common])  # [C, 3] ground-truth camera centres
        m = similarity(ce, cg)
    if m is None:
        if not estimated:
            return None, FRAME_GT
        log.warning(
            "evaluate: poses were estimated but cannot be aligned to ground-truth poses "
            "(%d shared frames); plans are compared cell by cell as they are",
            len(common),
        )
        return None, FRAME_UNALIGNED
    if not estimated and _moves(m, grid) < 0.1 * grid.cell:
        return None, FRAME_GT
    return m, FRAME_ALIGNED


def _moves(pred_to_gt: np.ndarray, grid: Grid) -> float:
    """How far (metres) the GT grid's corners land from where they are, read through it."""
    h, w = grid.shape
    corners = np.asarray(grid.origin) + np.array([[0, 0], [w, 0], [0, h], [w, h]]) * grid.cell
    return float(np.linalg.norm(to_frame(corners, pred_to_gt) - corners, axis=1).max())

"""The evaluate stage: every metric the capture's ground truth allows, under the fixed names."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.capture import Capture
from stages.common.io import read_json, write_json
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.plan import evaluate_plan
from stages.evaluate.poses import pose_metrics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvaluateInputs:
    frames: Path  # frames.json with the poses the blueprint was built from
    gt: Path  # the capture's gt/ folder
    blueprints: tuple[Path, ...]  # blueprint.npz of each method
    methods: tuple[str, ...]  # the method name of each blueprint
    poses_estimated: bool  # score poses only when a stage estimated them


@dataclass(frozen=True)
class EvaluateOutputs:
    metrics: Path  # metrics.json: {"blueprint": {method: {...}}, "poses": {...}}

    @classmethod
    def at(cls, out: Path) -> EvaluateOutputs:
        return cls(out / "metrics.json")


def run(cfg: EvaluateConfig, inputs: EvaluateInputs, out: Path) -> EvaluateOutputs:
    metrics: dict = {}
    gt_plan = inputs.gt / "blueprint.npz"
    if gt_plan.is_file() and cfg.plan:
        gt = Blueprint.load(gt_plan)
        metrics["blueprint"] = {
            m: evaluate_plan(Blueprint.load(p), gt)
            for m, p in zip(inputs.methods, inputs.blueprints, strict=True)
        }
    gt_poses = inputs.gt / "poses.json"
    if gt_poses.is_file() and inputs.poses_estimated and cfg.poses:
        cap = Capture.load(inputs.frames)
        est = {f.stem: np.asarray(f.pose) for f in cap.frames if f.pose is not None}
        gtp = {k: np.asarray(v, np.float64) for k, v in read_json(gt_poses).items()}
        metrics["poses"] = pose_metrics(est, gtp)
    write_json(out / "metrics.json", metrics)
    return EvaluateOutputs.at(out)

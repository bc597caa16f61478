"""Evaluate stage: every metric the capture's ground truth allows (plans, poses)."""

from stages.evaluate import gt
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.gt import EvaluateInputs, EvaluateOutputs
from stages.evaluate.metrics import plan_metrics
from stages.evaluate.plan import evaluate_plan

IMPLS = {"gt": gt.run}

__all__ = [
    "IMPLS",
    "EvaluateConfig",
    "EvaluateInputs",
    "EvaluateOutputs",
    "evaluate_plan",
    "plan_metrics",
]

"""Evaluate stage: every metric the capture's ground truth allows (plans, poses)."""

from stages.evaluate import gt
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.gt import EvaluateInputs, EvaluateOutputs

IMPLS = {"gt": gt.run}

__all__ = [
    "IMPLS",
    "EvaluateConfig",
    "EvaluateInputs",
    "EvaluateOutputs",
]

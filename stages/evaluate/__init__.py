"""Evaluate stage: every metric the capture's ground truth allows (plans, poses)."""

from stages.common.registry import LazyImpls
from stages.evaluate.config import EvaluateConfig, EvaluateInputs, EvaluateOutputs

IMPLS = LazyImpls({"gt": "stages.evaluate.gt:run"})

__all__ = [
    "IMPLS",
    "EvaluateConfig",
    "EvaluateInputs",
    "EvaluateOutputs",
]

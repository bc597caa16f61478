"""Configuration of the evaluate stage (its inputs and outputs are in stages/evaluate/gt.py)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EvaluateConfig:
    """Which metrics to compute when the capture has the ground truth for them."""

    impl: str = "gt"  # registry key in stages.evaluate.IMPLS
    plan: bool = True  # score each blueprint against gt/blueprint.npz (pacc, fwiou, ...)
    poses: bool = True  # score estimated poses against gt/poses.json

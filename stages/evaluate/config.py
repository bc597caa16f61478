"""Configuration of the evaluate stage (its inputs and outputs are in stages/evaluate/gt.py)."""

from __future__ import annotations

from dataclasses import dataclass

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class EvaluateConfig:
    """Which metrics to compute when the capture has the ground truth for them."""

    impl: str = "gt"  # registry key in stages.evaluate.IMPLS
    plan: bool = True  # score each blueprint against gt/blueprint.npz (pacc, fwiou, ...)
    poses: bool = True  # score estimated poses against gt/poses.json
    heldout: bool = True  # score each blueprint on the labelled pixels of the views the
    #                       project stage held out (heldout_pacc), with or without gt/
    heldout_stride: int = 2  # held-out views: score every n-th pixel in u and v

    def __post_init__(self) -> None:
        if self.heldout_stride < 1:
            raise BlunfError(f"evaluate.heldout_stride: must be >= 1, got {self.heldout_stride}")

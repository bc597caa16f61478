"""Configuration and the input / output contract of the evaluate stage."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

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


@dataclass(frozen=True)
class EvaluateInputs:
    frames: Path  # frames.json the plans were projected from (poses; depth and labels for
    #               the held-out views)
    gt: Path | None  # the capture's gt/ folder (None: the capture has none)
    blueprints: tuple[Path, ...]  # blueprint.npz of each method
    methods: tuple[str, ...]  # the method name of each blueprint
    poses_estimated: bool  # score poses only when a stage estimated them
    heldout: Path | None = None  # the project stage's heldout.json (None: no held-out score)
    layout: Path | None = None  # the layout stage's plan.json (scored against gt/layout.json)
    points: Path | None = None  # the project stage's points.npz: metrics.observation of the
    #                             first blueprint (observation.py); None: not scored
    observed: Path | None = None  # the project stage's observed.npz: the seen / inside
    #                               shares of a blueprint that does not carry them


@dataclass(frozen=True)
class EvaluateOutputs:
    STATS: ClassVar[str | None] = None  # metrics.json feeds report.metrics
    metrics: Path  # metrics.json: {"blueprint": {method: {...}}, "poses": {...}}; held-out
    #                scores under blueprint.<method>.heldout_pacc; "alignment": the scoring
    #                frame's conditioning when the plans were read through a similarity

    @classmethod
    def at(cls, out: Path) -> EvaluateOutputs:
        return cls(out / "metrics.json")

"""Which stages a scene needs, decided in one place from the capture and the request.

Given poses skip SfM; given depth skips NeRF depth; given labels skip semantics; no edits and
no NeRF baseline asked skip NeRF training. Every skip carries its reason into report.json.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.config import Config
from stages.common.capture import Capture
from stages.common.errors import BlunfError


@dataclass(frozen=True)
class Step:
    stage: str
    impl: str
    run: bool
    reason: str = ""


@dataclass(frozen=True)
class Plan:
    steps: tuple[Step, ...]

    def get(self, stage: str) -> Step:
        return next(s for s in self.steps if s.stage == stage)

    def runs(self, stage: str) -> bool:
        return any(s.stage == stage and s.run for s in self.steps)


def gt_files(cap: Capture) -> dict[str, Path]:
    """Ground-truth files the capture carries (evaluation uses what is there)."""
    if cap.gt is None:
        return {}
    names = {"blueprint": "blueprint.npz", "poses": "poses.json"}
    return {k: Path(cap.gt) / v for k, v in names.items() if (Path(cap.gt) / v).is_file()}


def make_plan(cap: Capture, cfg: Config, edits: Path | None = None) -> Plan:
    """Decide every stage's fate for this capture and config."""
    s: list[Step] = [Step("ingest", cfg["ingest"].impl, True)]

    pimpl = cfg["poses"].impl
    if pimpl == "auto":
        if cap.has_poses:
            s.append(Step("poses", "given", False, "capture gives poses"))
        else:
            s.append(Step("poses", "sfm", True, "capture has no poses"))
    elif pimpl == "given":
        if not cap.has_poses:
            raise BlunfError(f"{cap.root}: poses.impl=given but the capture has no poses")
        s.append(Step("poses", "given", False, "capture gives poses"))
    else:
        why = (
            "forced by config (capture poses hidden from the stage)"
            if cap.has_poses
            else ("capture has no poses")
        )
        s.append(Step("poses", pimpl, True, why))

    s.append(Step("align", cfg["align"].impl, True))

    if cap.has_depth:
        s.append(Step("depth", "nerf", False, "capture gives depth"))
    else:
        missing = next((f.stem for f in cap.frames if f.depth is None), "?")
        raise BlunfError(
            f"{cap.root}: no depth for frame {missing!r}; depth from photos alone needs the "
            "NeRF depth stage, which this version does not have yet (add depth/ to the capture)"
        )
    s.append(Step("fusion", cfg["fusion"].impl, True))

    if cap.has_labels:
        s.append(Step("semantics", "given", False, "capture gives labels"))
    else:
        s.append(
            Step(
                "semantics",
                "height",
                False,
                "no labels: the plan labels points by height (floor / occupied)",
            )
        )

    nerf_methods = [m for m in cfg.run.methods if m == "nerf_top"]
    if nerf_methods:
        raise BlunfError(
            "run.methods: nerf_top needs the NeRF stage, not available in this version"
        )
    if edits is not None:
        raise BlunfError(f"{edits}: editing needs the NeRF stage, not available in this version")
    s.append(Step("nerf", "grid", False, "no edits and no NeRF baseline asked"))

    s.append(Step("project", cfg["project"].impl, True))
    for m in cfg.run.methods:
        s.append(Step("blueprint", m, True))
    s.append(Step("edit", "blueprint", False, "no edit spec given"))
    gt = gt_files(cap)
    if gt:
        s.append(Step("evaluate", "gt", True, "ground truth: " + ", ".join(sorted(gt))))
    else:
        s.append(Step("evaluate", "gt", False, "capture has no ground truth"))
    s.append(Step("export", "files", True))
    return Plan(tuple(s))

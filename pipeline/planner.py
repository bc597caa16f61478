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
    # (stage, impl) that does the work when another stage's code does it; None = `stage`
    # with `impl`
    work: tuple[str, str] | None = None


@dataclass(frozen=True)
class Plan:
    steps: tuple[Step, ...]
    heldout: bool = False  # plans are also scored on views held out of them (see heldout())

    def get(self, stage: str) -> Step:
        return next(s for s in self.steps if s.stage == stage)

    def runs(self, stage: str) -> bool:
        return any(s.stage == stage and s.run for s in self.steps)

    def all(self, stage: str) -> tuple[Step, ...]:
        """Every step of a stage (blueprint: one per method, the product's first)."""
        return tuple(s for s in self.steps if s.stage == stage)


def gt_files(cap: Capture) -> dict[str, Path]:
    """Ground-truth files the capture carries (evaluation uses what is there)."""
    if cap.gt is None:
        return {}
    names = {"blueprint": "blueprint.npz", "poses": "poses.json"}
    return {k: Path(cap.gt) / v for k, v in names.items() if (Path(cap.gt) / v).is_file()}


def heldout(cap: Capture, cfg: Config) -> bool:
    """Whether plans are scored on held-out views: labels (given or from the semantics
    stage), no ground-truth plan to score them against instead, views held out by the
    project stage, and the score asked for."""
    labelled = cap.has_labels or _derive_labels(cfg)
    return (
        labelled
        and "blueprint" not in gt_files(cap)
        and cfg["project"].labelling != "height"
        and cfg["project"].holdout_every > 0
        and cfg["evaluate"].heldout
    )


def _derive_labels(cfg: Config) -> bool:
    """Whether a capture without labels gets them from the semantics stage."""
    return cfg["semantics"].impl != "height" and cfg["project"].labelling != "height"


def _depth_step(cfg: Config, missing: str, tracks: bool) -> Step:
    """The photos-only depth step, the depth stage: plane-sweep stereo (its `stereo`
    implementation), the plane fill, then a field trained to fill the holes only when the
    readings cover too little of the views (`depth.field.fill` auto; off: never; true:
    always); the field alone (its `field` implementation) when the config turns stereo off
    or there are no SfM tracks to bound the sweep (poses given: the field then learns depth
    from the photos alone). A field for edits or the NeRF top view is the nerf step's,
    trained later on the fused depth: it never needs this step's field."""
    st, fc = cfg["depth"].stereo, cfg["depth"].field
    head = f"no depth (e.g. frame {missing!r}): "
    if st.enabled and tracks and cfg["depth"].impl != "field":
        why = "plane-sweep stereo among the photos, " + (
            "no field trained (depth.field.fill off)"
            if fc.fill is False
            else "a field trained to fill its holes (depth.field.fill)"
            if fc.fill is True
            else "a field trained to fill its holes only if it covers under "
            f"{100 * fc.below:.0f} % of the pixels (depth.field.fill auto)"
        )
        return Step("depth", "stereo", True, head + why)
    why = "a field trained on the photos" + (
        " and the SfM tracks (depth.stereo off, or depth.impl field)"
        if tracks
        else " (poses given: no SfM tracks to supervise its depth)"
    )
    return Step("depth", "field", True, head + why + ", its render for fusion")


def make_plan(cap: Capture, cfg: Config, edits: Path | None = None) -> Plan:
    """Decide every stage's fate for this capture and config."""
    s: list[Step] = [Step("ingest", cfg["ingest"].impl, True)]

    pimpl = cfg["poses"].impl
    guess = next((f for f in cap.frames if f.calib not in ("given", "self-calibrated")), None)
    if guess is not None and cap.has_poses and pimpl in ("auto", "given"):
        raise BlunfError(
            f"{guess.image}: the capture gives poses but no intrinsics (only a {guess.calib} "
            "guess): give intrinsics, or --set poses.impl=sfm to estimate both"
        )
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
        s.append(Step("depth", cfg["depth"].impl, False, "capture gives depth"))
    else:
        missing = next((f.stem for f in cap.frames if f.depth is None), "?")
        some = next((f.stem for f in cap.frames if f.depth is not None), None)
        if some is not None:  # part of a depth capture is missing: a broken capture
            raise BlunfError(
                f"{cap.root}: no depth for frame {missing!r} while frame {some!r} has depth "
                "(give depth for every frame, or none to have the NeRF render it)"
            )
        s.append(
            _depth_step(cfg, missing, tracks=not cap.has_poses or pimpl not in ("auto", "given"))
        )
    s.append(Step("fusion", cfg["fusion"].impl, True))

    if cap.has_labels:
        s.append(Step("semantics", "given", False, "capture gives labels"))
    elif not _derive_labels(cfg):
        which = "project.labelling" if cfg["project"].labelling == "height" else "semantics.impl"
        reason = f"{which}=height: the plan labels points by height (floor / occupied)"
        s.append(Step("semantics", "height", False, reason))
    else:
        s.append(Step("semantics", cfg["semantics"].impl, True, "capture has no labels"))

    uses = (["NeRF top view baseline"] if "nerf_top" in cfg.run.methods else []) + (
        ["edit spec"] if edits is not None else []
    )
    if uses:
        s.append(Step("nerf", cfg["nerf"].impl, True, "asked for: " + ", ".join(uses)))
    else:
        s.append(Step("nerf", cfg["nerf"].impl, False, "no edits and no NeRF baseline asked"))
    s.append(Step("project", cfg["project"].impl, True))
    for m in cfg.run.methods:
        s.append(Step("blueprint", m, True))
    if edits is None:
        s.append(Step("edit", "nerf", False, "no edit spec given"))
    else:
        s.append(Step("edit", "nerf", True, f"edit spec {edits}"))
    s.append(Step("layout", cfg["layout"].impl, True))
    gt = gt_files(cap)
    scores = ["ground truth: " + ", ".join(sorted(gt))] if gt else []
    held = heldout(cap, cfg)
    if held:
        scores.append("held-out views")
    # metrics.observation needs no ground truth: the stage runs on every capture
    why = "; ".join(scores) or "observation only (no ground truth)"
    s.append(Step("evaluate", "gt", True, why))
    s.append(Step("export", "files", True))
    return Plan(tuple(s), held)

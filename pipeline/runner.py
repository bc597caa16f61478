"""Runs one stage through the cache: look up its key, else run it in a temp folder.

A caller that follows a run (the studio's trainer, `blunf batch`) gives the runner
`on_event`, as pycolmap's mapping takes callbacks: it gets a StageEvent when each stage is
taken up and when it ends (ran, cached, skipped or failed), and in between the stage's
progress (`stages.common.progress.StepProgress`), in order, on the run's thread.
"""

from __future__ import annotations

import importlib
import logging
import resource
import shutil
import time
import typing
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pipeline.cache import Cache, stage_key
from pipeline.config import Config, stage_view
from pipeline.planner import Step
from pipeline.publish import writing
from pipeline.report import Report, StageRecord, peak_rss_mb, peak_rss_reset
from pipeline.runtime import stage_threads, stop_if_requested
from stages.common.errors import BlunfError
from stages.common.heap import heap_returned
from stages.common.io import read_json
from stages.common.progress import StepProgress, listening
from stages.common.progress import close_all as close_progress
from stages.common.threads import torch_threads

log = logging.getLogger(__name__)


def registry(stage: str) -> dict[str, Any]:
    return importlib.import_module(f"stages.{stage}").IMPLS


def check_impl(stage: str, impl: str) -> None:
    reg = registry(stage)
    if impl not in reg:
        raise BlunfError(f"{stage}.impl: unknown implementation {impl!r} (known: {', '.join(reg)})")


@dataclass(frozen=True)
class StageEvent:
    """A stage taken up ("start") or finished ("end", with how: as the report records it)."""

    stage: str
    impl: str
    what: Literal["start", "end"]
    status: Literal["ran", "cached", "skipped", "failed"] | None = None  # None at "start"
    reason: str = ""  # why the plan runs or skips it
    seconds: float = 0.0  # "end" of a stage that ran
    error: str = ""  # "end" of a stage that failed: the exception, one line


RunEvent = StageEvent | StepProgress
OnEvent = Callable[[RunEvent], None]


class Runner:
    """Executes stages of one run directory, recording each in the report; `on_event` gets
    each stage's start and end and its progress (see the module's docstring)."""

    def __init__(self, out: Path, cfg: Config, report: Report, on_event: OnEvent | None = None):
        self.out = Path(out)
        self.cfg = cfg
        self.report = report
        self.on_event = on_event
        self.cache = Cache(self.out)
        self.cache.sweep()

    def _tell(self, stage: str, impl: str, what: Literal["start", "end"], **kw: Any) -> None:
        if self.on_event is not None:
            self.on_event(StageEvent(stage, impl, what, **kw))

    def step(self, step: Step, inputs: Any) -> Any:
        """A step of the plan: its stage's outputs, or None when the plan skips it (the skip
        and its reason go to the report). `inputs` may be a function giving them, called only
        when the step runs (inputs made of outputs that exist only then)."""
        if not step.run:
            log.info("%-10s skipped: %s", step.stage, step.reason)
            self.report.add(StageRecord(step.stage, step.impl, "skipped", step.reason))
            self._tell(step.stage, step.impl, "start", reason=step.reason)
            self._tell(step.stage, step.impl, "end", status="skipped", reason=step.reason)
            return None
        stage, impl = step.work or (step.stage, step.impl)
        return self.stage(stage, impl, inputs() if callable(inputs) else inputs, step.reason)

    def stage(self, stage: str, impl: str, inputs: Any, reason: str = "", cfg: Any = None) -> Any:
        """Run (or reuse) `stages.<stage>.IMPLS[impl](cfg, inputs, out)`; returns its outputs."""
        check_impl(stage, impl)
        stop_if_requested()  # a SIGTERM whose raise was lost in the stage before
        scfg = cfg if cfg is not None else self.cfg[stage]
        view = stage_view(scfg, impl)
        input_keys = self.cache.input_keys(inputs)  # hashes outside files (the capture) once
        key = stage_key(stage, impl, view, input_keys)
        changed = _changed(scfg, impl)
        self._tell(stage, impl, "start", reason=reason)
        with writing(self.out / stage), self.cache.lock(stage, key):
            folder = self.cache.folder(stage, key)
            if self.cache.is_done(stage, key):
                meta = read_json(folder / "meta.json")
                outputs_cls = _outputs_class(meta, stage, impl)
                log.info("%-10s %s: cached (%s)%s", stage, impl, key, changed)
                self.report.add(
                    StageRecord(
                        stage, impl, "cached", reason, 0.0, None, key, meta.get("facts", {})
                    )
                )
                self._tell(stage, impl, "end", status="cached", reason=reason)
                return outputs_cls.at(folder)
            log.info("%-10s %s: running (%s)%s", stage, impl, key, changed)
            fn = registry(stage)[impl]  # imports the implementation (torch, Open3D...) only now
            outputs_cls = typing.get_type_hints(fn)["return"]
            tmp = self.cache.temp(stage, key)
            try:  # a failing stage leaves nothing behind (a killed one is swept by the next run)
                heap_returned()  # what earlier stages freed is not this stage's peak
                peak_rss_reset()
                t0, c0, u0 = time.perf_counter(), time.process_time(), _user_cpu()
                listen = nullcontext() if self.on_event is None else listening(self.on_event)
                with torch_threads(stage_threads(self.cfg.run.threads)), listen:
                    fn(scfg, inputs, tmp)
                secs, cpu = time.perf_counter() - t0, time.process_time() - c0
                user = _user_cpu() - u0
                stats = stats_name(outputs_cls, impl)
                facts = _facts(tmp / stats) if stats else {}
                meta = {
                    "stage": stage,
                    "impl": impl,
                    "key": key,
                    "config": view,  # the full resolved config: here, not in the log
                    "inputs": input_keys,
                    "seconds": round(secs, 3),
                    "cpu_seconds": round(cpu, 3),
                    "cpu_user_seconds": round(user, 3),  # of cpu_seconds, outside the kernel
                    "peak_rss_mb": peak_rss_mb(),
                    "facts": facts,
                    "outputs_class": f"{outputs_cls.__module__}:{outputs_cls.__qualname__}",
                }
                folder = self.cache.commit(tmp, stage, key, meta)
            except BaseException as e:
                shutil.rmtree(tmp, ignore_errors=True)
                close_progress()  # a bar the stage left open (it raised mid-step)
                error = f"{type(e).__name__}: {e}".splitlines()[0] if str(e) else type(e).__name__
                self._tell(stage, impl, "end", status="failed", reason=reason, error=error)
                raise
            finally:
                close_progress()
        log.info("%-10s ran in %.1fs", stage, secs)
        self.report.add(
            StageRecord(stage, impl, "ran", reason, round(secs, 3), meta["peak_rss_mb"], key, facts)
        )
        self._tell(stage, impl, "end", status="ran", reason=reason, seconds=round(secs, 3))
        return outputs_cls.at(folder)


def stats_name(outputs_cls: Any, impl: str) -> str | None:
    """The stats file a stage's Outputs class names (per implementation when a mapping)."""
    name = getattr(outputs_cls, "STATS", None)
    return name.get(impl) if isinstance(name, dict) else name


def _changed(scfg: Any, impl: str) -> str:
    """` key=value ...` for the settings that differ from the stage's defaults ("" if none)."""
    try:
        default = stage_view(type(scfg)(), impl)
    except Exception:  # a config without defaults: nothing to compare with
        return ""
    now = _flat(stage_view(scfg, impl))
    base = _flat(default)
    diff = [f"{k}={v}" for k, v in now.items() if k != "impl" and base.get(k, object()) != v]
    return (" " + " ".join(diff)) if diff else ""


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _outputs_class(meta: dict, stage: str, impl: str) -> Any:
    """The Outputs class a cached entry was written with (no need to import the stage's code)."""
    name = meta.get("outputs_class")
    if name:
        module, _, qual = name.partition(":")
        return getattr(importlib.import_module(module), qual)
    return typing.get_type_hints(registry(stage)[impl])["return"]


def _facts(p: Path) -> dict:
    """The small JSON a stage writes about itself (its Outputs' STATS file), for the report."""
    if not p.is_file():
        return {}
    try:
        d = read_json(p)
    except BlunfError:
        return {}
    return d if isinstance(d, dict) and len(str(d)) < 20000 else {}


def _user_cpu() -> float:
    """User CPU seconds of every thread of this process so far (cpu_seconds less the
    kernel's share: page faults and zeroing of fresh memory, I/O)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_utime

"""Runs one stage through the cache: look up its key, else run it in a temp folder."""

from __future__ import annotations

import importlib
import logging
import os
import shutil
import time
import typing
from pathlib import Path
from typing import Any

from pipeline.cache import Cache, stage_key
from pipeline.config import Config, stage_view
from pipeline.report import Report, StageRecord, peak_rss_mb, peak_rss_reset
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.common.threads import torch_threads

log = logging.getLogger(__name__)


def registry(stage: str) -> dict[str, Any]:
    return importlib.import_module(f"stages.{stage}").IMPLS


def check_impl(stage: str, impl: str) -> None:
    reg = registry(stage)
    if impl not in reg:
        raise BlunfError(f"{stage}.impl: unknown implementation {impl!r} (known: {', '.join(reg)})")


class Runner:
    """Executes stages of one run directory, recording each in the report."""

    def __init__(self, out: Path, cfg: Config, report: Report):
        self.out = Path(out)
        self.cfg = cfg
        self.report = report
        self.cache = Cache(self.out)
        self.cache.sweep()

    def skip(self, stage: str, impl: str, reason: str) -> None:
        log.info("%-10s skipped: %s", stage, reason)
        self.report.add(StageRecord(stage, impl, "skipped", reason))

    def stage(self, stage: str, impl: str, inputs: Any, reason: str = "", cfg: Any = None) -> Any:
        """Run (or reuse) `stages.<stage>.IMPLS[impl](cfg, inputs, out)`; returns its outputs."""
        check_impl(stage, impl)
        scfg = cfg if cfg is not None else self.cfg[stage]
        key = stage_key(stage, impl, stage_view(scfg, impl), self.cache.input_keys(inputs))
        with self.cache.lock(stage, key):
            folder = self.cache.folder(stage, key)
            if self.cache.is_done(stage, key):
                meta = read_json(folder / "meta.json")
                outputs_cls = _outputs_class(meta, stage, impl)
                log.info("%-10s cached (%s)", stage, key)
                self.report.add(
                    StageRecord(
                        stage, impl, "cached", reason, 0.0, None, key, meta.get("facts", {})
                    )
                )
                return outputs_cls.at(folder)
            log.info("%-10s %s: running (%s) %s", stage, impl, key, stage_view(scfg, impl))
            fn = registry(stage)[impl]  # imports the implementation (torch, Open3D...) only now
            outputs_cls = typing.get_type_hints(fn)["return"]
            tmp = self.cache.temp(stage, key)
            try:  # a failing stage leaves nothing behind (a killed one is swept by the next run)
                peak_rss_reset()
                t0, c0 = time.perf_counter(), time.process_time()
                with torch_threads(_run_threads(self.cfg.run.threads)):
                    fn(scfg, inputs, tmp)
                secs, cpu = time.perf_counter() - t0, time.process_time() - c0
                facts = _facts(tmp, stage, impl)
                meta = {
                    "stage": stage,
                    "impl": impl,
                    "key": key,
                    "config": stage_view(scfg, impl),
                    "inputs": self.cache.input_keys(inputs),
                    "seconds": round(secs, 3),
                    "cpu_seconds": round(cpu, 3),
                    "peak_rss_mb": peak_rss_mb(),
                    "facts": facts,
                    "outputs_class": f"{outputs_cls.__module__}:{outputs_cls.__qualname__}",
                }
                folder = self.cache.commit(tmp, stage, key, meta)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        log.info("%-10s ran in %.1fs", stage, secs)
        self.report.add(
            StageRecord(stage, impl, "ran", reason, round(secs, 3), meta["peak_rss_mb"], key, facts)
        )
        return outputs_cls.at(folder)


def _outputs_class(meta: dict, stage: str, impl: str) -> Any:
    """The Outputs class a cached entry was written with (no need to import the stage's code)."""
    name = meta.get("outputs_class")
    if name:
        module, _, qual = name.partition(":")
        return getattr(importlib.import_module(module), qual)
    return typing.get_type_hints(registry(stage)[impl])["return"]


def _run_threads(threads: int) -> int:
    """The torch threads a stage runs with: run.threads, else OMP_NUM_THREADS, else 1 (set only
    once torch is actually needed: see torch_threads)."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    return threads or (int(env) if env.isdigit() and int(env) > 0 else 1)


def _facts(folder: Path, stage: str, impl: str) -> dict:
    """The small JSON a stage writes about itself, if any, for the report."""
    for name in (f"{stage}.json", f"{impl}.json", "train.json", "stats.json"):
        p = folder / name
        if not p.is_file():
            continue
        try:
            d = read_json(p)
        except BlunfError:
            continue
        return d if isinstance(d, dict) and len(str(d)) < 20000 else {}
    return {}

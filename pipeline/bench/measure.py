"""Running the variants: warm caches, fresh run folders, one child process per run.

Every run is a child process (`python -m pipeline.bench.child`) that imports the heavy
libraries before its clock starts, so no variant pays (or escapes) an import, each peak
resident size is the run's own, and a crash costs one row. The stages before the variant's
`fresh_from` are hard-linked from the capture's warm cache (`<out>/warm/<capture>/`), so a
repeat reruns only the stage under study and what follows it. The warm cache is filled by a
warm-up run per upstream configuration (frame budget, upstream settings), its later stages
on cheap settings, kept under `<out>/warm/<capture>/runs/` (later stages' frames.json name
its files). Repeats are interleaved over the variants (repeat 1 of every variant, then
repeat 2...), so a burst of load from elsewhere on the machine spreads over all of them
rather than skewing one.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.bench.grid import STAGE_ORDER, Variant
from stages.common.errors import BlunfError
from stages.common.io import read_json, write_json

log = logging.getLogger(__name__)

TIMEOUT_S = 3600  # one run; a hung child is killed and its row notes it
# A warm-up keeps only the stages before the variant's fresh_from: the later ones run on
# these cheap settings (their cache keys do not enter the upstream stages' keys)
CHEAP = {
    "fusion": ("fusion.voxel=0.1", "fusion.raycast=false"),
    "project": ("project.stride=8", "project.cell=0.1"),
    "blueprint": ("run.methods=mvr",),
}


@dataclass
class Sample:
    """One run of a variant."""

    wall_s: float  # the pipeline call (cached lookups of the upstream stages included)
    cpu_s: float  # CPU of the child process (all threads) and of any process it waited for
    peak_rss_mb: float | None  # max over the stages that ran (report.json peak_rss_mb)
    seconds: dict[str, float]  # stage -> seconds, summed over the records that ran
    cpu: dict[str, float]  # stage -> CPU seconds (meta.json of the stage folders that ran)
    metrics: dict[str, Any]  # flattened report.json metrics


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1}: metrics.blueprint.blunf.fwiou -> blueprint.blunf.fwiou."""
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def stage_rank(stage: str) -> int:
    """Position of a stage in the pipeline (unknown stages last)."""
    return STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER)


def upstream(v: Variant) -> tuple[str, ...]:
    """The stages reused from the warm cache: those before v.fresh_from."""
    return STAGE_ORDER[: STAGE_ORDER.index(v.fresh_from)]


def link_tree(src: Path, dst: Path) -> None:
    """Copy a folder as hard links (a cached stage entry is never written again)."""
    shutil.copytree(src, dst, copy_function=os.link, dirs_exist_ok=True)


def seed(run_dir: Path, warm: Path, stages: tuple[str, ...]) -> None:
    """Hard-link the warm cache's finished entries of `stages` into a fresh run folder."""
    for stage in stages:
        for entry in sorted((warm / stage).glob("*/meta.json")):
            link_tree(entry.parent, run_dir / stage / entry.parent.name)


def harvest(run_dir: Path, warm: Path, stages: tuple[str, ...]) -> None:
    """Add a run's finished entries of `stages` to the warm cache."""
    for stage in stages:
        for entry in sorted((run_dir / stage).glob("*/meta.json")):
            if not (warm / stage / entry.parent.name).exists():
                link_tree(entry.parent, warm / stage / entry.parent.name)


def child_run(
    capture: Path,
    run_dir: Path,
    sets: list[str],
    threads: int,
    log_file: Path,
    config: Path | None = None,
) -> dict:
    """Run the pipeline in a child process; returns its result (see child.py)."""
    spec = {"capture": str(capture), "out": str(run_dir), "sets": sets, "threads": threads}
    if config is not None:
        spec["config"] = str(config)
    spec_file = run_dir / ".bench-spec.json"
    write_json(spec_file, spec)
    env = dict(os.environ, BLUNF_THREADS=str(threads), OMP_NUM_THREADS=str(threads))
    cmd = [sys.executable, "-m", "pipeline.bench.child", str(spec_file)]
    with open(log_file, "a") as lf:
        try:
            proc = subprocess.run(
                cmd, stdout=lf, stderr=subprocess.STDOUT, env=env, timeout=TIMEOUT_S, check=False
            )
        except subprocess.TimeoutExpired:
            return {"ok": False, "error": f"timed out after {TIMEOUT_S} s"}
    res_file = run_dir / ".bench-result.json"
    if proc.returncode != 0 or not res_file.is_file():
        tail = log_file.read_text().strip().splitlines()[-1:] or ["(no output)"]
        return {"ok": False, "error": f"exit {proc.returncode}: {tail[0][:200]}"}
    return read_json(res_file)


def sample_of(v: Variant, run_dir: Path, res: dict) -> Sample:
    """Read one finished run: timings from report.json and the stages' meta.json."""
    rep = read_json(run_dir / "report.json")
    seconds: dict[str, float] = {}
    cpu: dict[str, float] = {}
    peaks = []
    for s in rep["stages"]:
        if s["status"] != "ran":
            continue
        seconds[s["name"]] = seconds.get(s["name"], 0.0) + float(s["seconds"])
        meta = run_dir / s["name"] / str(s["key"]) / "meta.json"
        if meta.is_file():
            c = read_json(meta).get("cpu_seconds")
            if c is not None:
                cpu[s["name"]] = cpu.get(s["name"], 0.0) + float(c)
        if s.get("peak_rss_mb") is not None:  # what ran here ran afresh (upstream: cached)
            peaks.append(float(s["peak_rss_mb"]))
    return Sample(
        wall_s=float(res["wall_s"]),
        cpu_s=float(res["cpu_s"]),
        peak_rss_mb=max(peaks) if peaks else None,
        seconds=seconds,
        cpu=cpu,
        metrics=flatten(rep.get("metrics", {})),
    )


def cold(v: Variant, run_dir: Path) -> list[str]:
    """Upstream stages (before fresh_from) that this run had to build."""
    rep = read_json(run_dir / "report.json")
    up = set(upstream(v))
    return [s["name"] for s in rep["stages"] if s["status"] == "ran" and s["name"] in up]


class Bench:
    """Runs variants on resolved captures, keeping warm caches and per-run reports."""

    def __init__(self, out: Path, threads: int, keep_runs: bool = False):
        self.out = Path(out)
        self.threads = threads
        self.keep_runs = keep_runs
        # (capture, stages, sets) of every warm-up: its stages are in the warm cache
        self.warmed: list[tuple[str, tuple[str, ...], tuple[str, ...]]] = []
        for sub in ("warm", "runs", "reports", "logs"):
            (self.out / sub).mkdir(parents=True, exist_ok=True)

    def sets(self, v: Variant) -> list[str]:
        """The variant's overrides, plus the frame budget and the bench's thread count."""
        return [
            f"ingest.frames={v.frames}",
            f"run.threads={self.threads}",
            f"poses.threads={self.threads}",
            *v.sets,
        ]

    def warm_up(self, v: Variant, capture: Path) -> str | None:
        """Build v's upstream stages into the warm cache, once per upstream configuration, in
        a run whose later stages are made cheap (CHEAP). Returns an error line, or None."""
        up = upstream(v)
        if not up or any(
            c == v.capture and set(up) <= set(u) and _only(sets, up) == _only(self.sets(v), up)
            for c, u, sets in self.warmed
        ):
            return None
        warm = self.out / "warm" / v.capture
        # kept: the frames.json of later stages name files in this folder
        run_dir = warm / "runs" / f"w{len(self.warmed)}"
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        seed(run_dir, warm, up)
        log_file = self.out / "logs" / f"{v.name}.log"
        cheap = [x for st, sets in CHEAP.items() if st not in up for x in sets]
        res = child_run(capture, run_dir, [*self.sets(v), *cheap], self.threads, log_file)
        if not res.get("ok"):
            return str(res.get("error", "failed"))
        harvest(run_dir, warm, up)
        self.warmed.append((v.capture, up, tuple(self.sets(v))))
        return None

    def once(self, v: Variant, capture: Path, rep: int) -> Sample | str:
        """One timed run of v, its upstream taken from the warm cache (built first if need
        be). Returns the sample, or the error line of a failed run."""
        err = self.warm_up(v, capture)
        if err is not None:
            return err
        warm = self.out / "warm" / v.capture
        log_file = self.out / "logs" / f"{v.name}.log"
        for attempt in range(2):
            run_dir = self.out / "runs" / f"{v.name}-r{rep}-{attempt}"
            shutil.rmtree(run_dir, ignore_errors=True)
            run_dir.mkdir(parents=True)
            seed(run_dir, warm, upstream(v))
            res = child_run(capture, run_dir, self.sets(v), self.threads, log_file)
            if not res.get("ok"):
                return str(res.get("error", "failed"))
            built = cold(v, run_dir)
            if not built or attempt == 1:
                break
            # the warm-up missed a stage (its key depends on something the signature lacks):
            # this run becomes a warm-up too (kept, linked from the warm cache), then again
            harvest(run_dir, warm, upstream(v))
            log.warning(
                "bench %s: built %s after its warm-up; running again", v.name, ", ".join(built)
            )
        shutil.copyfile(run_dir / "report.json", self.out / "reports" / f"{v.name}-r{rep}.json")
        s = sample_of(v, run_dir, res)
        if not self.keep_runs:
            shutil.rmtree(run_dir, ignore_errors=True)
        return s


def _only(sets: Sequence[str], stages: Sequence[str]) -> list[str]:
    """The overrides of `stages` among sets, sorted (what their cache keys depend on)."""
    return sorted(s for s in sets if s.split(".")[0] in stages)


def summarise(v: Variant, samples: list[Sample], errors: list[str], meta: dict) -> dict:
    """One CSV row: medians over the samples, the error, the flattened metrics."""
    row: dict[str, Any] = {
        "variant": v.name,
        "group": v.group,
        "capture": v.capture,
        "frames": meta.get("frames", v.frames),
        "width": meta.get("width", ""),
        "height": meta.get("height", ""),
        "pixels": meta.get("pixels", ""),
        "reference": int(v.reference),
        "cost": v.cost,
        "sets": " ".join(v.sets),
        "repeats": len(samples),
        "failed": len(errors),
        "note": errors[0] if errors else "",
    }
    if not samples:
        return row
    med = statistics.median
    row["wall_s"] = round(med(s.wall_s for s in samples), 3)
    row["wall_s_min"] = round(min(s.wall_s for s in samples), 3)
    row["wall_s_max"] = round(max(s.wall_s for s in samples), 3)
    row["cpu_s"] = round(med(s.cpu_s for s in samples), 3)
    peaks = [s.peak_rss_mb for s in samples if s.peak_rss_mb is not None]
    row["peak_rss_mb"] = round(med(peaks), 1) if peaks else ""
    stages = sorted({k for s in samples for k in s.seconds}, key=stage_rank)
    for st in stages:
        row[f"seconds.{st}"] = round(med(s.seconds.get(st, 0.0) for s in samples), 3)
        cpus = [s.cpu[st] for s in samples if st in s.cpu]
        if cpus:
            row[f"cpu.{st}"] = round(med(cpus), 3)
    row["stage_s"] = round(med(sum(s.seconds.get(t, 0.0) for t in v.timed) for s in samples), 3)
    for k in sorted({k for s in samples for k in s.metrics}):
        vals = [s.metrics[k] for s in samples if k in s.metrics]
        nums = [x for x in vals if isinstance(x, int | float) and not isinstance(x, bool)]
        row[k] = med(nums) if len(nums) == len(vals) else vals[-1]
    row["error"] = error_of(v.error, row)
    return row


def error_of(spec: str, row: dict) -> float | str:
    """The y value named by a variant's `error` ("<c>-<metric>", e.g. "100-<metric>", or
    "<metric>"); "" if absent."""
    if not spec:
        return ""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)-(.+)", spec)
    v = row.get(m.group(2) if m else spec)
    if v is None or v == "" or not isinstance(v, int | float):
        return ""
    return round(float(m.group(1)) - v if m else float(v), 4)


def capture_facts(capture: Path, frames: int) -> dict:
    """frames used, and the image size and pixels of the capture (read from one image)."""
    from stages.ingest import load

    with tempfile.TemporaryDirectory(prefix="blunf-bench-probe-") as work:
        try:
            cap = load(capture, Path(work))
        except BlunfError as e:
            log.warning("bench: %s", e)
            return {}
    f = cap.frames[0]
    n = len(cap.frames) if frames <= 0 else min(frames, len(cap.frames))
    return {
        "frames": n,
        "width": f.intrinsics.width,
        "height": f.intrinsics.height,
        "pixels": f.intrinsics.width * f.intrinsics.height,
    }


def timestamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S")

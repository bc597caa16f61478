"""The runs behind `blunf bench --targets` (targets.py): timed `blunf run` commands in child
processes, each repeat from an empty run folder, read back through the bench's report reader
(measure.sample_of) with every stage's peak memory, and the medians the targets' rows take.
"""

from __future__ import annotations

import logging
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.bench.grid import Variant, synthetic
from pipeline.bench.measure import Sample, sample_of, stage_rank
from pipeline.bench.target_table import Row
from pipeline.runtime import free_cores
from stages.common.io import read_json

log = logging.getLogger(__name__)

TIMEOUT_S = 3600  # one run; past it the run is killed and its rows say so
KITCHEN_QUICK_TIMEOUT_S = 600  # --quick stays bounded: twice target 2's budget
_RUN = Variant("targets", "targets", "targets")  # sample_of's variant argument (unused there)


@dataclass
class Measured:
    """One timed run: the bench's sample, plus per-stage and process peaks."""

    sample: Sample
    stage_peaks: dict[str, float]  # stage -> peak resident MB (report.json)
    process_peak_mb: float | None = None  # the whole process, imports included (wait4)


@dataclass
class Session:
    """The runs of one `blunf bench --targets`: made once, shared by the targets that read
    them (the demo's runs serve targets 1, 3, 4, 5 and 8)."""

    out: Path
    quick: bool
    repeats: int
    threads: int = 0  # 0: each run sizes its threads to the free cores, as `blunf run` does
    runs: dict[str, list[Measured] | str] = field(default_factory=dict)  # name -> runs | error
    dirs: dict[str, Path] = field(default_factory=dict)  # name -> the last repeat's folder
    commands: dict[str, str] = field(default_factory=dict)
    killed: dict[str, tuple[float, float, str]] = field(default_factory=dict)  # at the limit:
    # name -> (wall, CPU, the last stage line of its log)

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        for sub in ("runs", "logs", "reports", "captures"):
            (self.out / sub).mkdir(parents=True, exist_ok=True)

    @property
    def cores(self) -> int:
        return self.threads or free_cores()

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        if self.threads:
            env["BLUNF_THREADS"] = env["OMP_NUM_THREADS"] = str(self.threads)
        else:  # as a user's command: the run picks its own
            env.pop("BLUNF_THREADS", None)
            env.pop("OMP_NUM_THREADS", None)
        return env

    def run(
        self, name: str, capture: Path, opts: Sequence[str], repeats: int = 0, timeout: float = 0
    ) -> list[Measured] | str:
        """`blunf run CAPTURE --out DIR OPTS`, `repeats` times (default the session's), each
        from an empty folder; the last repeat's folder is kept. Returns the runs, or the
        error line of the first that failed."""
        if name in self.runs:
            return self.runs[name]
        got: list[Measured] = []
        for rep in range(repeats or self.repeats):
            run_dir = self.out / "runs" / f"{name}-r{rep}"
            shutil.rmtree(run_dir, ignore_errors=True)
            args = ["run", str(capture), "--out", str(run_dir), *opts, "--quiet"]
            self.commands[name] = "blunf " + shown(args[:-1])
            log.info("targets: %s, repeat %d: %s", name, rep + 1, self.commands[name])
            res = timed_command(
                [sys.executable, "-m", "pipeline", *args],
                self.out / "logs" / f"{name}.log",
                self.env(),
                timeout or TIMEOUT_S,
            )
            if res["error"]:
                if res["error"].startswith("timed out"):
                    log_text = (self.out / "logs" / f"{name}.log").read_text()
                    stages = [ln for ln in log_text.splitlines() if "pipeline.runner:" in ln]
                    last = stages[-1].split("pipeline.runner:")[-1].strip() if stages else ""
                    self.killed[name] = (res["wall_s"], res["cpu_s"], " ".join(last.split()))
                self.runs[name] = f"{name}: {res['error']}"
                return self.runs[name]
            shutil.copyfile(run_dir / "report.json", self.out / "reports" / f"{name}-r{rep}.json")
            got.append(
                Measured(sample_of(_RUN, run_dir, res), stage_peaks(run_dir), res["peak_mb"])
            )
            if rep > 0:  # only the last folder is read again (previews, scores)
                shutil.rmtree(self.out / "runs" / f"{name}-r{rep - 1}", ignore_errors=True)
            self.dirs[name] = run_dir
        self.runs[name] = got
        return got

    def capture(self, views: int, size: tuple[int, int], photos: bool = False) -> Path:
        """The procedural room `blunf synth CAP --views V --seed 0 --size WxH [--photos-only]`
        makes (under DIR/captures, made once)."""
        return synthetic(views, size, seed=0, photos=photos)(self.out)


def timed_command(argv: list[str], log_file: Path, env: dict, timeout: float) -> dict:
    """Run argv (output to log_file): {"error": "" or a line, "wall_s", "cpu_s", "peak_mb"},
    CPU from the kernel's account of the process (wait4), peak resident memory from its
    /proc/<pid>/status VmHWM read every POLL_S while it runs. (wait4's ru_maxrss is not
    used for memory: Linux folds the forking parent's resident size into it at exec, so a
    child of a 1 GB test process "peaked" at 1.1 GB while holding 200 MB.)"""
    with open(log_file, "a") as lf:
        lf.write(f"$ {shlex.join(argv)}\n")
        lf.flush()
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=lf, stderr=subprocess.STDOUT, env=env)
        timer = threading.Timer(timeout, proc.kill)
        timer.start()
        done = threading.Event()
        hwm = [0.0]  # MB, the highest VmHWM read
        watch = threading.Thread(target=_watch_hwm, args=(proc.pid, done, hwm), daemon=True)
        watch.start()
        try:
            _, status, ru = os.wait4(proc.pid, 0)
        except BaseException:  # interrupted: the run does not outlive the bench
            proc.kill()
            proc.wait()
            raise
        finally:
            timer.cancel()
            done.set()
            watch.join()
        wall = time.perf_counter() - t0
    proc.returncode = rc = os.waitstatus_to_exitcode(status)
    err = ""
    if rc != 0:
        tail = log_file.read_text().strip().splitlines()[-1:] or ["(no output)"]
        err = f"timed out after {timeout:.0f} s" if wall >= timeout else f"exit {rc}: {tail[0]}"
    return {
        "error": err[:200],
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "peak_mb": hwm[0] or None,  # None: the run ended before a first reading
    }


POLL_S = 0.05  # seconds between readings of a timed command's peak memory


def _watch_hwm(pid: int, done: threading.Event, hwm: list[float]) -> None:
    """Keep hwm[0] at the highest VmHWM (MB) of process `pid` until `done` or its end. The
    first reading may still be the forking parent's (before exec): VmHWM only rises, so a
    reading is kept once the process runs its own program (its exe differs from ours)."""
    ours = os.readlink("/proc/self/exe")
    while not done.is_set():
        try:
            if os.readlink(f"/proc/{pid}/exe") != ours or _cmdline(pid) != _cmdline(os.getpid()):
                with open(f"/proc/{pid}/status") as f:
                    for line in f:
                        if line.startswith("VmHWM:"):
                            hwm[0] = max(hwm[0], int(line.split()[1]) / 1024.0)
        except OSError:  # ended (or a zombie without its status lines)
            pass
        done.wait(POLL_S)


def _cmdline(pid: int) -> bytes:
    with open(f"/proc/{pid}/cmdline", "rb") as f:
        return f.read()


def stage_peaks(run_dir: Path) -> dict[str, float]:
    """stage -> peak resident MB of the stages that ran (the run's report.json)."""
    return stage_peaks_of(read_json(run_dir / "report.json"))


def shown(args: Sequence[object]) -> str:
    """A command line with paths under the working folder made relative to it."""
    cwd = Path.cwd()

    def one(a: object) -> str:
        p = Path(str(a))
        if p.is_absolute() and p.is_relative_to(cwd):
            return str(p.relative_to(cwd))
        return str(a)

    return shlex.join(one(a) for a in args)


def med(vals: Sequence[float | None]) -> float | None:
    got = [float(v) for v in vals if v is not None]
    return statistics.median(got) if got else None


def wall_cpu(ms: list[Measured], stage: str = "") -> tuple[float | None, float | None]:
    """Median wall and CPU seconds of the runs (of one stage when given)."""
    if stage:
        return med([m.sample.seconds.get(stage) for m in ms]), med(
            [m.sample.cpu.get(stage) for m in ms]
        )
    return med([m.sample.wall_s for m in ms]), med([m.sample.cpu_s for m in ms])


def metric(ms: list[Measured], key: str) -> float | None:
    """Median of a flattened report.json metric over the runs."""
    vals = [m.sample.metrics.get(key) for m in ms]
    return med([v for v in vals if isinstance(v, int | float) and not isinstance(v, bool)])


def skip(rows: list[Row], why: str) -> list[Row]:
    for r in rows:
        r.skipped = why
    return rows


def top_stages(ms: list[Measured], n: int = 3) -> str:
    """The n slowest stages (median seconds): where the run's time went."""
    names = {k for m in ms for k in m.sample.seconds}
    secs = {k: med([m.sample.seconds.get(k, 0.0) for m in ms]) or 0.0 for k in names}
    top = sorted(secs.items(), key=lambda kv: -kv[1])[:n]
    return ", ".join(f"{k} {v:.1f} s" for k, v in top)


def stage_peaks_of(report: dict) -> dict[str, float]:
    """stage -> peak resident MB of the stages that ran, from a report.json's content."""
    return {
        st["name"]: float(st["peak_rss_mb"])
        for st in report["stages"]
        if st["status"] == "ran" and st.get("peak_rss_mb") is not None
    }


def where_time_went(s: Session) -> list[str]:
    """One line per run: median wall, CPU and peak, then every stage's seconds, CPU, peak."""
    lines = []
    for name, ms in s.runs.items():
        if isinstance(ms, str):
            lines.append(f"- {name}: failed: {ms}")
            continue
        wall, cpu = wall_cpu(ms)
        peak = max((p for m in ms for p in m.stage_peaks.values()), default=0.0)
        stages = sorted({k for m in ms for k in m.sample.seconds}, key=stage_rank)
        parts = []
        for st in stages:
            w, c = wall_cpu(ms, st)
            p = max((m.stage_peaks.get(st, 0.0) for m in ms), default=0.0)
            parts.append(f"{st} {w or 0:.2f} s / {c or 0:.2f} CPU-s / {p:.0f} MB")
        head = f"- {name} ({len(ms)} run(s), median wall {wall or 0:.1f} s, CPU {cpu or 0:.1f} s"
        lines.append(f"{head}, peak {peak:.0f} MB): " + "; ".join(parts))
    return lines

"""`blunf batch`: many captures, one Dask task each, on this machine or on a cluster.

Each task is a normal `blunf run` (pipeline.run.run, in the worker process) into
`OUT/<scene>/` with its own cache, logging to `OUT/<scene>.log`. Without a scheduler address a
`dask.distributed.LocalCluster` starts here (one worker process per core, one task at a time
each); with one, the tasks go to a running cluster whose workers see the same file system.

Faults: a worker that dies mid-capture has its task rescheduled by Dask on another worker
(up to `distributed.scheduler.allowed-failures` times); the stage it was running wrote only
into a temp folder, which the next run of that capture sweeps (pipeline/cache.py), so the
retry gives the same result. A capture that fails (bad input) is recorded with its one-line
error and the others go on. Ctrl-C cancels the batch: stages already committed stay valid,
the ones cut short never reach their key.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pipeline.config import Config, load_config
from pipeline.runner import OnEvent, RunEvent, StageEvent
from pipeline.summary import summarise
from stages.common.errors import BlunfError
from stages.common.io import check_exists, finite_json
from stages.common.progress import configure as configure_progress

log = logging.getLogger(__name__)

KEY_PREFIX = "blunf-run-"
TOPIC = "blunf-batch"  # Dask event topic: {"scene", "worker"} when a task starts a capture,
#                        {"scene", "stage"} when its run takes up a stage


@dataclass(frozen=True)
class BatchOptions:
    """How a batch runs (the run options are those of `blunf run`)."""

    out: Path
    scheduler: str | None = None  # tcp://host:8786 of a running cluster; None = a local one
    workers: int = 0  # local workers; 0 = the cores divided by threads_per_worker
    threads_per_worker: int = 1  # CPU threads (torch, Open3D) each capture uses
    config: Path | None = None
    sets: tuple[str, ...] = ()
    edits: Path | None = None
    dashboard: str | None = "127.0.0.1:8787"  # local dashboard address; None = no dashboard
    progress_every: float = 2.0  # seconds between progress lines (when something changed)
    quiet: bool = False  # no progress lines, here nor in the captures' logs


@dataclass(frozen=True)
class Job:
    """One capture's task, as sent to a worker (absolute paths: a worker's cwd is its own)."""

    capture: str
    out: str
    log: str
    cfg: Config
    edits: str | None
    threads: int
    progress: str = "log"  # how the stages' progress shows (stages/common/progress.py)


@dataclass
class Outcome:
    """What a task returns (and what batch.json lists for each capture)."""

    scene: str
    ok: bool = False
    error: str = ""
    seconds: float = 0.0
    worker: str = ""
    stages: dict[str, str] = field(default_factory=dict)


def run_capture(job: Job) -> Outcome:
    """The task: `blunf run` of one capture in this worker process (never raises)."""
    from pipeline.run import run
    from pipeline.runtime import setup_runtime

    n = str(job.threads)  # torch reads these on import, the runner when it sizes its threads
    os.environ.update(OMP_NUM_THREADS=n, MKL_NUM_THREADS=n, BLUNF_THREADS=n)
    setup_runtime(job.threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(job.threads)
    configure_progress(job.progress)  # lines in the capture's log, never bars
    res = Outcome(scene=Path(job.out).name, worker=f"{_hostname()}:{os.getpid()}")
    handler = _log_to(Path(job.log))
    _event({"scene": res.scene, "worker": res.worker})
    t0 = time.perf_counter()
    try:
        logging.getLogger("blunf").info("batch: %s on worker %s", job.capture, res.worker)
        edits = Path(job.edits) if job.edits else None
        rep = run(Path(job.capture), Path(job.out), job.cfg, edits, _stage_events(res.scene))
        res.ok = True
        res.stages = {f"{s.name}:{s.impl}": s.status for s in rep.stages}
    except BlunfError as e:
        res.error = str(e)
    except Exception as e:  # a bug, not bad input: the traceback goes to the capture's log
        logging.getLogger("blunf").exception("batch: %s failed", job.capture)
        res.error = f"{type(e).__name__}: {e}".splitlines()[0]
    finally:
        res.seconds = round(time.perf_counter() - t0, 3)
        if res.error:
            logging.getLogger("blunf").error("blunf: error: %s", res.error)
        _unlog(handler)
    return res


def batch(captures: list[Path], opts: BatchOptions) -> dict:
    """Run every capture; writes OUT/summary.csv, index.html and batch.json; returns the
    batch facts (wall time, speedup over the sum of the captures' times, each outcome)."""
    jobs = _jobs(captures, opts)
    from distributed import Client, LocalCluster

    opts.out.mkdir(parents=True, exist_ok=True)
    quiet = logging.getLogger().getEffectiveLevel() > logging.DEBUG  # Dask's chatter: with -v
    if quiet:
        logging.getLogger("distributed").setLevel(logging.WARNING)
    cluster = None
    t0 = time.perf_counter()
    try:
        if opts.scheduler is None:
            cluster = LocalCluster(**_local_kwargs(opts, len(jobs)))
            client = Client(cluster)
        else:
            client = _connect(opts.scheduler)
    except OSError as e:
        raise BlunfError(f"{opts.scheduler or 'local cluster'}: cannot start ({e})") from None
    try:
        nw = len(client.scheduler_info(n_workers=-1)["workers"])
        where = opts.scheduler or f"a local cluster of {nw} workers"
        log.info("batch: %d captures on %s", len(jobs), where)
        if client.dashboard_link and (opts.scheduler or opts.dashboard):
            log.info("batch: Dask dashboard %s", client.dashboard_link)
        outcomes = _drive(client, jobs, opts)
    finally:
        client.close()
        if cluster is not None:
            if quiet:  # a worker that imported torch outlives the nanny's 4 s wait and is killed:
                # harmless once its tasks are over (every stage committed or cut short in a temp)
                logging.getLogger("distributed.nanny").setLevel(logging.ERROR)
            cluster.close()
    wall = time.perf_counter() - t0
    return _finish(opts, outcomes, wall)


BATCH_FILES = ("index.html", "summary.csv", "batch.json")  # what a batch writes in OUT


def _jobs(captures: list[Path], opts: BatchOptions) -> list[Job]:
    """Check everything a user can get wrong before any cluster starts."""
    if not captures:
        raise BlunfError("batch: no capture given")
    if opts.threads_per_worker < 1:
        raise BlunfError(f"--threads-per-worker {opts.threads_per_worker}: must be >= 1")
    cfg = load_config(opts.config, list(opts.sets))
    if opts.edits is not None:
        from stages.edit.spec import load_spec

        load_spec(opts.edits)  # a bad spec fails here, before any cluster starts
    out = opts.out.resolve()
    if out.exists() and not out.is_dir():
        raise BlunfError(f"{opts.out}: the batch folder exists and is not a folder")
    # the names each capture takes in OUT (its folder and its log), and the batch's own
    taken: dict[str, str] = {n: "the batch's own file" for n in BATCH_FILES}
    jobs = []
    for c in captures:
        check_exists(c, "capture folder")
        name = c.resolve().name
        for n in (name, f"{name}.log"):
            if n in taken:
                raise BlunfError(
                    f"{c}: its output {opts.out / n} would collide with {taken[n]}; "
                    "rename the capture folder"
                )
        taken[name] = taken[f"{name}.log"] = f"capture {c}'s output"
        jobs.append(
            Job(
                capture=str(c.resolve()),
                out=str(out / name),
                log=str(out / f"{name}.log"),
                cfg=cfg,
                edits=str(opts.edits.resolve()) if opts.edits is not None else None,
                threads=opts.threads_per_worker,
                progress="off" if opts.quiet else "log",
            )
        )
    return jobs


def _local_kwargs(opts: BatchOptions, n_jobs: int) -> dict:
    cores = len(os.sched_getaffinity(0))
    n = opts.workers or max(1, cores // opts.threads_per_worker)
    t = str(opts.threads_per_worker)
    dash = opts.dashboard if opts.dashboard and _has_bokeh() else None
    return {
        "n_workers": max(1, min(n, n_jobs)),
        "threads_per_worker": 1,  # one capture at a time: torch's thread count is per process
        "processes": True,
        "host": "127.0.0.1",
        "dashboard_address": dash,
        # Dask's default caps each worker at RAM / workers and pauses or kills it near the cap;
        # a capture is one task holding its own memory, so the machine's limit is the one
        "memory_limit": 0,
        "env": {"OMP_NUM_THREADS": t, "MKL_NUM_THREADS": t, "BLUNF_THREADS": t},
        "silence_logs": logging.ERROR,
    }


def _connect(address: str):  # -> distributed.Client
    from distributed import Client

    try:
        client = Client(address, timeout=30)
    except (OSError, TimeoutError) as e:
        raise BlunfError(f"{address}: cannot reach the Dask scheduler ({e})") from None
    try:
        client.wait_for_workers(1, timeout=60)
    except TimeoutError:
        client.close()
        raise BlunfError(f"{address}: the scheduler has no workers (waited 60 s)") from None
    return client


def _drive(client, jobs: list[Job], opts: BatchOptions) -> list[Outcome]:
    """Submit every job, report progress until all are done; Ctrl-C cancels the rest."""
    from distributed import KilledWorker

    token = f"{os.getpid()}-{int(time.time())}"
    for j in jobs:  # each batch starts each capture's log afresh; a retry appends to it
        Path(j.log).write_text("")
    futs = {
        client.submit(run_capture, j, key=f"{KEY_PREFIX}{Path(j.out).name}-{token}", pure=False): j
        for j in jobs
    }
    results: dict[str, Outcome] = {}
    last, shown = 0.0, ""
    seen: dict[str, str] = {}
    try:
        while len(results) < len(futs):
            for f, j in futs.items():
                scene = Path(j.out).name
                if scene in results or not f.done():
                    continue
                try:
                    results[scene] = f.result()
                except KilledWorker as e:
                    results[scene] = Outcome(scene, error=f"its worker died every try ({e})")
                except Exception as e:  # the task itself never raises: Dask or transport
                    results[scene] = Outcome(scene, error=f"{type(e).__name__}: {e}")
                r = results[scene]
                if r.ok:
                    log.info("batch: %s done in %.1f s on %s", scene, r.seconds, r.worker)
                else:
                    log.warning("batch: %s failed: %s", scene, r.error)
            if not opts.quiet and time.monotonic() - last >= opts.progress_every:
                line = _progress(client, jobs, results, seen)
                if line != shown:
                    log.info("batch: %s", line)
                shown, last = line, time.monotonic()
            time.sleep(0.2)
    except KeyboardInterrupt:
        log.warning("batch: interrupted; cancelling %d captures", len(futs) - len(results))
        client.cancel(list(futs), force=True)
        for j in jobs:
            results.setdefault(Path(j.out).name, Outcome(Path(j.out).name, error="interrupted"))
        _finish(opts, [results[Path(j.out).name] for j in jobs], None)
        raise
    return [results[Path(j.out).name] for j in jobs]


def _progress(client, jobs: list[Job], results: dict[str, Outcome], seen: dict[str, str]) -> str:
    """'2 done, 1 failed, 2 running (a: fusion, b: blueprint), 3 waiting'; `seen` keeps the
    last stage each capture's run took up (its runner's events, `_stage_events`)."""
    try:
        events = [e for _, e in client.get_events(TOPIC) if isinstance(e, dict)]
    except Exception:  # a scheduler going away mid-batch: progress is best effort
        events = []
    for e in events:
        seen[e["scene"]] = e.get("stage", seen.get(e["scene"], "starting"))
    running = []
    for j in jobs:
        scene = Path(j.out).name
        if scene in seen and scene not in results:
            running.append(f"{scene}: {seen[scene]}")
    done = sum(r.ok for r in results.values())
    failed = len(results) - done
    waiting = len(jobs) - len(results) - len(running)
    inner = f" ({', '.join(running)})" if running else ""
    return f"{done} done, {failed} failed, {len(running)} running{inner}, {waiting} waiting"


def _finish(opts: BatchOptions, outcomes: list[Outcome], wall: float | None) -> dict:
    """summary.csv and index.html (pipeline/summary.py), then batch.json with the timing."""
    errors = {r.scene: r.error for r in outcomes if not r.ok}
    csv_path, html_path = summarise(opts.out, errors, scenes=[r.scene for r in outcomes])
    total = sum(r.seconds for r in outcomes)
    facts = {
        "captures": len(outcomes),
        "ok": sum(r.ok for r in outcomes),
        "failed": sum(not r.ok for r in outcomes),
        "wall_seconds": None if wall is None else round(wall, 3),
        "sum_capture_seconds": round(total, 3),
        "speedup": None if not wall else round(total / wall, 3),
        "scheduler": opts.scheduler or "local",
        "outcomes": [asdict(r) for r in outcomes],
    }
    (opts.out / "batch.json").write_text(json.dumps(finite_json(facts), indent=1) + "\n")
    if wall is not None:
        timing = (
            f"<p>{facts['ok']} of {facts['captures']} captures in {wall:.1f} s wall time; "
            f"the captures' times add up to {total:.1f} s (speedup {facts['speedup']:.2f}x)</p>"
        )
        page = html_path.read_text()
        html_path.write_text(page.replace("<h1>blunf batch</h1>", f"<h1>blunf batch</h1>{timing}"))
        log.info(
            "batch: %d ok, %d failed; wall %.1f s, captures %.1f s summed, speedup %.2fx",
            facts["ok"],
            facts["failed"],
            wall,
            total,
            facts["speedup"],
        )
    log.info("batch: %s  %s", csv_path, html_path)
    return facts


class _ThisThread(logging.Filter):
    """Only records of the thread that made it (a worker may run tasks in several threads)."""

    def __init__(self) -> None:
        super().__init__()
        self.ident = threading.get_ident()

    def filter(self, record: logging.LogRecord) -> bool:
        return record.thread == self.ident


_LOGGERS = ("blunf", "pipeline", "stages")


def _log_to(path: Path) -> logging.Handler:
    """The capture's log file (appended: a retried capture shows each attempt)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    h = logging.FileHandler(path, mode="a")
    h.setFormatter(logging.Formatter("%(asctime)s %(name)s: %(message)s", "%H:%M:%S"))
    h.addFilter(_ThisThread())
    for name in _LOGGERS:
        lg = logging.getLogger(name)
        if lg.getEffectiveLevel() > logging.INFO:
            lg.setLevel(logging.INFO)
        lg.addHandler(h)
    return h


def _unlog(h: logging.Handler) -> None:
    for name in _LOGGERS:
        logging.getLogger(name).removeHandler(h)
    h.close()


def _stage_events(scene: str) -> OnEvent:
    """The runner's listener in a worker: each stage it takes up, told to the client."""

    def on_event(e: RunEvent) -> None:
        if isinstance(e, StageEvent) and e.what == "start":
            _event({"scene": scene, "stage": e.stage})

    return on_event


def _event(msg: dict) -> None:
    """Tell the client a capture started (outside a worker, e.g. called directly: nothing)."""
    try:
        from distributed import get_worker

        get_worker().log_event(TOPIC, msg)
    except ValueError:  # not in a worker
        pass


def _hostname() -> str:
    return re.sub(r"[^\w.-]", "_", os.uname().nodename)


def _has_bokeh() -> bool:
    try:
        import bokeh  # noqa: F401  (the dashboard needs it; Dask runs fine without)
    except ImportError:
        return False
    return True

"""The process's runtime: torch/Open3D threads sized to the free cores, glibc's malloc
thresholds raised (set once, by the command line or a batch worker, before the stages run).

The one place that decides how many threads a run computes with: `setup_runtime` decides
them for the process (run.threads, else the free cores), `stage_threads` hands that count
to each stage the runner runs. A stage's own `threads` setting (e.g. nerf.threads) only
overrides it for that stage."""

from __future__ import annotations

import ctypes
import os
import time

_decided: int | None = None  # the process's thread count, once setup_runtime decided it
_stop_requested = False  # a SIGTERM arrived (pipeline/cli.py's handler)


class Terminated(KeyboardInterrupt):
    """SIGTERM, ending blunf as Ctrl-C does (temp folders removed, one line)."""


def request_stop() -> None:
    """Record a SIGTERM and raise Terminated. The raise can be lost: a signal handler runs
    wherever the main thread is, and an exception raised inside a finaliser (`__del__`, a
    weakref or GC callback of torch's or Open3D's objects) is printed and dropped; the
    record stays, and `stop_if_requested` raises it again at the next stage."""
    global _stop_requested
    _stop_requested = True
    raise Terminated


def stop_if_requested() -> None:
    """Raise Terminated if a SIGTERM arrived whose own raise was lost."""
    if _stop_requested:
        raise Terminated


def setup_runtime(threads: int = 0) -> int:
    """Size torch/Open3D threads to the free cores (or `threads`, run.threads) and raise
    glibc's malloc thresholds; returns the thread count decided."""
    global _decided
    n = _decided = threads or free_cores()
    # OpenMP (torch, Open3D) reads this when first loaded; torch's own setting is applied by the
    # runner once a stage that needs torch runs (a fully cached run never imports it).
    os.environ.setdefault("OMP_NUM_THREADS", str(n))
    try:  # M_TRIM_THRESHOLD = -1, M_MMAP_THRESHOLD = -3: keep big tensors in the heap
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 32 * 1024 * 1024)
        libc.mallopt(-1, 4 * 1024 * 1024 * 1024 - 1)
    except OSError:
        pass
    return n


def stage_threads(threads: int = 0) -> int:
    """The torch threads a stage runs with: `threads` (run.threads) when given, else the
    count setup_runtime decided for this process, else OMP_NUM_THREADS, else 1 (a process
    that never set its runtime up: a test, a library call)."""
    if threads:
        return threads
    if _decided is not None:
        return _decided
    env = os.environ.get("OMP_NUM_THREADS", "")
    return int(env) if env.isdigit() and int(env) > 0 else 1


def free_cores() -> int:
    """Cores this process may use minus those busy with other work right now.

    "Right now" is the share of CPU time the whole machine spent busy over BUSY_WINDOW
    seconds (/proc/stat), not the 1-minute load average: that lags by a minute, so a run
    started just after another (make demo's second run, a batch's next capture) saw the
    finished one as busy and took one thread on an idle machine (measured: the demo's edit
    run 203 s on one thread, 157 s on two). The load average is the fallback without
    /proc/stat."""
    env = os.environ.get("BLUNF_THREADS") or os.environ.get("OMP_NUM_THREADS")
    if env and env.isdigit() and int(env) > 0:
        return int(env)
    ncpu = len(os.sched_getaffinity(0))
    try:
        a = _cpu_times()
        time.sleep(BUSY_WINDOW)
        busy = busy_cores(a, _cpu_times(), os.cpu_count() or ncpu)
    except (OSError, ValueError, IndexError):
        busy = os.getloadavg()[0]
    return max(1, ncpu - int(busy + 0.5))


BUSY_WINDOW = 0.25  # seconds over which the machine's busy share is measured


def _cpu_times() -> tuple[int, int]:
    """(total, idle) jiffies of all CPUs since boot: /proc/stat's first line (idle + iowait)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v[:8]), v[3] + v[4]  # user .. steal (guest time is counted in user already)


def busy_cores(before: tuple[int, int], after: tuple[int, int], ncpu: int) -> float:
    """Cores busy between two (total, idle) readings of all `ncpu` CPUs (0 when no time
    passed)."""
    total, idle = after[0] - before[0], after[1] - before[1]
    if total <= 0:
        return 0.0
    return ncpu * max(0.0, min(1.0, 1.0 - idle / total))

"""The process's runtime: torch/Open3D threads sized to the free cores, glibc's malloc
thresholds raised (set once, by the command line or a batch worker, before the stages run)."""

from __future__ import annotations

import ctypes
import os


def setup_runtime(threads: int = 0) -> int:
    """Size torch/Open3D threads to the free cores and raise glibc's malloc thresholds."""
    n = threads or free_cores()
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


def free_cores() -> int:
    """Cores this process may use minus those busy with other work (1 min load average)."""
    env = os.environ.get("BLUNF_THREADS") or os.environ.get("OMP_NUM_THREADS")
    if env and env.isdigit() and int(env) > 0:
        return int(env)
    ncpu = len(os.sched_getaffinity(0))
    busy = int(os.getloadavg()[0] + 0.5)
    return max(1, ncpu - busy)

"""One bench run in its own process: `python -m pipeline.bench.child SPEC.json`.

SPEC = {"capture", "out", "sets", "threads"} and optionally "config" (a YAML file). The
heavy libraries the run uses are imported before the clock starts (numpy before pycolmap:
the other order corrupts the heap; torch when a BluNF plan is asked for), then the pipeline
runs once; `<out>/.bench-result.json` gets {"ok", "wall_s", "cpu_s"} (CPU of every thread
of this process and of any process it waited for) and "rss_start_mb": [stage, MB] for each
stage taken up, the resident size when it started (its peak, in report.json, is the
process's high-water mark from there: the difference is what the stage itself added).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path


def main(spec_path: str) -> int:
    import numpy  # noqa: F401  (first: see the docstring)
    import open3d  # noqa: F401
    import pycolmap  # noqa: F401

    from pipeline.config import load_config
    from pipeline.run import run
    from pipeline.runtime import setup_runtime
    from stages.common.heap import heap_returned
    from stages.common.io import read_json, write_json

    spec = read_json(Path(spec_path))
    out = Path(spec["out"])
    threads = int(spec["threads"])
    setup_runtime(threads)
    cfg = load_config(spec.get("config"), list(spec["sets"]))
    if "blunf" in cfg.run.methods:  # the one stage here that trains with torch
        import torch

        torch.set_num_threads(threads)
    starts: list[tuple[str, float | None]] = []

    def on_event(e: object) -> None:
        if getattr(e, "what", None) == "start":
            heap_returned()  # as the runner does before the stage runs: its start, not before
            starts.append((e.stage, rss_mb()))  # type: ignore[attr-defined]

    t0, c0, k0 = time.perf_counter(), time.process_time(), os.times()
    run(Path(spec["capture"]), out, cfg, on_event=on_event)
    k1 = os.times()
    children = (k1.children_user - k0.children_user) + (k1.children_system - k0.children_system)
    write_json(
        out / ".bench-result.json",
        {
            "ok": True,
            "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0 + children,
            "user_s": (k1.user - k0.user) + (k1.children_user - k0.children_user),
            "rss_start_mb": starts,
        },
    )
    return 0


def rss_mb() -> float | None:
    """Resident size of this process now, in MB (Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        return None
    return None


if __name__ == "__main__":
    import logging

    from stages.common.errors import BlunfError

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    try:
        sys.exit(main(sys.argv[1]))
    except BlunfError as e:
        print(f"blunf: error: {e}", file=sys.stderr)
        sys.exit(2)

"""Threads sized to the cores that are free now (pipeline/runtime.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from pipeline.runtime import _cpu_times, busy_cores, free_cores


def test_busy_cores_from_two_readings():
    # 100 jiffies passed on all CPUs, 50 of them idle: half of 2 cores is 1 core busy
    assert busy_cores((1000, 800), (1100, 850), 2) == 1.0
    assert busy_cores((1000, 800), (1100, 900), 4) == 0.0  # all idle
    assert busy_cores((1000, 800), (1000, 800), 2) == 0.0  # no time passed


def test_a_spinning_process_is_seen_busy_at_once():
    # a process that has just started spinning is busy now; the 1-minute load average
    # would not show it for a while (and would show it for a minute after it ends)
    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        a = _cpu_times()
        time.sleep(0.5)
        busy = busy_cores(a, _cpu_times(), os.cpu_count() or 1)  # at least the spinner's core
    finally:
        spin.kill()
        spin.wait()
    assert busy >= 0.6, busy
    total, idle = _cpu_times()
    assert total > idle >= 0


def test_an_explicit_thread_count_wins(monkeypatch):
    monkeypatch.setenv("BLUNF_THREADS", "3")
    assert free_cores() == 3
    monkeypatch.delenv("BLUNF_THREADS")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert 1 <= free_cores() <= len(os.sched_getaffinity(0))


def test_threads_are_decided_once_and_handed_to_every_stage(monkeypatch):
    import pipeline.runtime as rt

    monkeypatch.setattr(rt, "_decided", None)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert rt.stage_threads() == 3  # no runtime set up: the environment's count
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert rt.stage_threads() == 1
    monkeypatch.setenv("BLUNF_THREADS", "2")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # an older setting the decision overrides
    assert rt.setup_runtime() == 2
    assert rt.stage_threads() == 2  # what the runtime decided, not OMP_NUM_THREADS again
    assert rt.stage_threads(4) == 4  # run.threads, when given, wins

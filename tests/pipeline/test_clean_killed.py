"""`blunf clean` and runs that died: their `.runs/<id>` folders go, also when their pid now
belongs to another, later process (which must not make clean refuse forever); a live run's
folder makes it refuse."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from pipeline.clean import clean
from stages.common.errors import BlunfError


def _run_folder(tmp_path):
    out = tmp_path / "run"
    (out / ".runs" / "100-1").mkdir(parents=True)  # the published run (.current)
    (out / ".current").symlink_to(".runs/100-1")
    (out / "report.json").symlink_to(".current/report.json")
    (out / ".runs" / "100-1" / "report.json").write_text(json.dumps({"stages": []}))
    return out


def test_clean_removes_killed_runs(tmp_path) -> None:
    out = _run_folder(tmp_path)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    killed = out / ".runs" / f"{time.time_ns()}-{int(dead.stdout)}"
    killed.mkdir()
    (killed / "blueprint.png").write_bytes(b"x" * 1000)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        time.sleep(0.2)
        # a run of an hour ago whose pid the live process (started now) took since
        reused = out / ".runs" / f"{time.time_ns() - 3600 * 10**9}-{live.pid}"
        reused.mkdir()
        freed, n = clean(out)
        assert not killed.exists() and not reused.exists()
        assert n == 2 and freed >= 1000
        assert (out / ".runs" / "100-1" / "report.json").is_file()  # the published run stays
        # a folder the live process made after it started: a run at work, clean refuses
        (out / ".runs" / f"{time.time_ns()}-{live.pid}").mkdir()
        with pytest.raises(BlunfError, match=f"pid {live.pid}"):
            clean(out)
    finally:
        live.kill()
        live.wait()

"""Faults: a run interrupted or killed mid-stage, two runs sharing one run folder, and checks
that must come before expensive work (mid-publish kills, read-only and full run folders and
`blunf clean` are in test_faults_publish.py).

Each test starts real `python -m pipeline run` processes. The cache contract (pipeline/cache.py):
a stage writes into `<stage>/.tmp-<key>-<pid>/`, renamed to `<stage>/<key>/` once meta.json
is in it, under an flock on `<stage>/.<key>.lock`; a failed or interrupted stage removes its
temp folder, a killed one leaves it for the next run to sweep (its pid is dead).
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.cache import code_version
from pipeline.cli import main
from stages.common.blueprint import Blueprint
from tests.faults import (
    FAST,
    ROOT,
    assert_entries_complete,
    entries,
    make_fault_room,
    statuses,
)

UPSTREAM = ("ingest", "align", "fusion", "project")
# BluNF training long enough (~3-5 s here) to be caught mid-stage, short enough to rerun.
SLOW_BLUNF = ["--set", "blueprint.blunf.steps=400", "--set", "blueprint.blunf.batch=4096"]


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return make_fault_room(tmp_path_factory)


def start(capture: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "pipeline", "run", str(capture), "--out", str(out), *FAST, *extra],
        cwd=ROOT,
        env={**os.environ, "BLUNF_THREADS": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a test session started in the background (`make test &`) inherits SIGINT ignored,
        # and Python then installs no KeyboardInterrupt handler: give the run the default
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def wait_for_temp(proc: subprocess.Popen, folder: Path, timeout: float = 120.0) -> Path:
    """The first `.tmp-*` folder to appear under `folder` while proc runs."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        found = sorted(folder.glob(".tmp-*"))
        if found:
            return found[0]
        if proc.poll() is not None:
            raise AssertionError(f"the run ended first ({proc.returncode}): {proc.stderr.read()}")
        time.sleep(0.02)
    proc.kill()
    raise AssertionError(f"no temp folder under {folder} after {timeout} s")


def test_interrupt_then_kill_then_rerun(room, tmp_path):
    """Ctrl-C mid-stage: exit 130, temp folder removed. kill -9 mid-stage: temp folder left,
    no entry. The rerun sweeps it, reuses the finished stages and completes the killed one."""
    out = tmp_path / "run"

    # 1. SIGINT (Ctrl-C) while BluNF trains: KeyboardInterrupt unwinds through the runner.
    p = start(room, out, *SLOW_BLUNF)
    tmp = wait_for_temp(p, out / "blueprint")
    time.sleep(0.2)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert err.strip().splitlines()[-1] == "blunf: interrupted" and "Traceback" not in err
    assert not tmp.exists() and not list(out.rglob(".tmp-*"))
    assert_entries_complete(out)
    key = tmp.name.split("-")[1]
    assert key not in entries(out)["blueprint"]
    for stage in UPSTREAM:  # what finished before the interrupt stays
        assert len(entries(out)[stage]) == 1, stage

    # 2. SIGKILL at the same point: nothing can run, the temp folder stays, no entry appears.
    p = start(room, out, *SLOW_BLUNF)
    tmp = wait_for_temp(p, out / "blueprint")
    time.sleep(0.2)
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL
    assert tmp.is_dir() and tmp.name.split("-")[1] == key
    assert key not in entries(out)["blueprint"]
    assert_entries_complete(out)
    with open(out / "blueprint" / f".{key}.lock", "w") as fh:  # the kernel freed its flock
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)

    # 3. Rerun, same config: the dead run's temp folder is swept, upstream is cached, the
    # killed stage runs to completion under the same key. (This process hashes the stage
    # sources afresh, like the subprocesses did: the session's memo may predate an edit.)
    code_version.cache_clear()
    assert main(["run", str(room), "--out", str(out), *FAST, *SLOW_BLUNF]) == 0
    report = json.loads((out / "report.json").read_text())
    st = statuses(report)
    assert {s: st[s] for s in ("ingest:auto", "align:auto", "fusion:tsdf", "project:pinhole")} == {
        s: "cached" for s in ("ingest:auto", "align:auto", "fusion:tsdf", "project:pinhole")
    }
    assert st["blueprint:blunf"] == "ran" and st["export:files"] == "ran"
    assert not list(out.rglob(".tmp-*")) and not tmp.exists()
    assert_entries_complete(out)
    assert key in entries(out)["blueprint"]

    # 4. An entry that lost its meta.json (deleted by hand, a half-copied run folder) is not
    # trusted: it is rebuilt in place, and only what depends on its content reruns.
    mvr = next(k for k in entries(out)["blueprint"] if k != key)
    (out / "blueprint" / mvr / "meta.json").unlink()
    (out / "blueprint" / mvr / "blueprint.npz").write_bytes(b"truncated")
    assert main(["run", str(room), "--out", str(out), *FAST, *SLOW_BLUNF]) == 0
    st = statuses(json.loads((out / "report.json").read_text()))
    assert st["blueprint:mvr"] == "ran" and st["blueprint:blunf"] == "cached"
    assert_entries_complete(out)
    assert Blueprint.load(out / "blueprint" / mvr / "blueprint.npz").labels.size > 0


def test_two_runs_share_one_folder(room, tmp_path):
    """Two processes on one scene and one --out at once: both succeed, every stage is built
    by exactly one of them (the other waits on the entry's lock, then reuses it), and both
    end with the same blueprint."""
    out = tmp_path / "run"
    extra = ["--set", "blueprint.blunf.steps=60", "--set", "blueprint.blunf.batch=4096"]
    procs = [start(room, out, *extra) for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, results, strict=True):
        assert p.returncode == 0, err
        assert "Traceback" not in err
    summaries = [json.loads(stdout) for stdout, _ in results]
    a, b = (s["stages"] for s in summaries)
    assert a.keys() == b.keys()
    for stage in a:
        if a[stage] == "skipped":
            assert b[stage] == "skipped", stage
        else:  # one built it, the other found it done
            assert sorted((a[stage], b[stage])) == ["cached", "ran"], (stage, a[stage], b[stage])
    assert summaries[0]["metrics"] == summaries[1]["metrics"]  # scored the same plans
    assert not list(out.rglob(".tmp-*")) and not list(out.glob(".*.tmp-*"))
    assert_entries_complete(out)
    assert all(len(v) == 1 for k, v in entries(out).items() if k != "blueprint"), entries(out)
    assert len(entries(out)["blueprint"]) == 2  # blunf and mvr, one entry each
    # The published plan is the blunf entry's, byte for byte.
    blunf = next(
        out / "blueprint" / k
        for k in entries(out)["blueprint"]
        if json.loads((out / "blueprint" / k / "meta.json").read_text())["impl"] == "blunf"
    )
    assert (out / "blueprint.npz").read_bytes() == (blunf / "blueprint.npz").read_bytes()


def test_edit_spec_views_fail_right_after_ingest(room, tmp_path, capsys):
    """views: [0, 99] on an 8-view capture fails once the frames are known, before any
    other stage (the NeRF would train minutes before the edit stage looked at them)."""
    spec = tmp_path / "spec.yaml"
    spec.write_text("edits:\n  - select: {class: table}\n    op: remove\nviews: [0, 99]\n")
    out = tmp_path / "run"
    assert main(["run", str(room), "--out", str(out), *FAST, "--edits", str(spec)]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert str(spec) in line and "views[1]" in line and "99" in line, line
    assert sorted(entries(out)) == ["ingest"], entries(out)
    assert not (out / "report.json").exists() and not list((out / ".runs").iterdir())


def test_label_id_missing_from_labels_json_fails_at_ingest(room, tmp_path, capsys):
    """A label map holding an id labels.json does not name fails after ingest, naming the
    label file and the class table (it failed at evaluate, naming no file)."""
    from PIL import Image

    cap = tmp_path / "cap"
    shutil.copytree(room, cap)
    label = sorted((cap / "labels").glob("*.png"))[3]
    a = np.array(Image.open(label))
    a[:2, :2] = 77
    Image.fromarray(a).save(label)
    out = tmp_path / "run"
    assert main(["run", str(cap), "--out", str(out), *FAST]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert str(label) in line and "label id 77" in line and "labels.json" in line, line
    assert sorted(entries(out)) == ["ingest"], entries(out)

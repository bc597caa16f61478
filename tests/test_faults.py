"""Faults: a run interrupted or killed mid-stage or mid-publish, two runs sharing one run
folder, a read-only or full run folder, checks that must come before expensive work, and
`blunf clean`.

Each test starts real `python -m pipeline run` processes. The cache contract (pipeline/cache.py):
a stage writes into `<stage>/.tmp-<key>-<pid>/`, renamed to `<stage>/<key>/` once meta.json
is in it, under an flock on `<stage>/.<key>.lock`; a failed or interrupted stage removes its
temp folder, a killed one leaves it for the next run to sweep (its pid is dead).
"""

from __future__ import annotations

import fcntl
import json
import os
import resource
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

ROOT = Path(__file__).resolve().parents[1]
UPSTREAM = ("ingest", "align", "fusion", "project")
# BluNF training long enough (~3-5 s here) to be caught mid-stage, short enough to rerun.
SLOW_BLUNF = ["--set", "blueprint.blunf.steps=400", "--set", "blueprint.blunf.batch=4096"]
FAST = ["--set", "fusion.voxel=0.05", "--set", "run.methods=blunf,mvr"]


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    from stages.synth import make_room

    return make_room(tmp_path_factory.mktemp("faults") / "room", views=8, seed=4, size=(64, 48))


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


def entries(out: Path) -> dict[str, list[str]]:
    """stage -> names of its cache entries (folders not starting with '.')."""
    return {
        s.name: sorted(e.name for e in s.iterdir() if not e.name.startswith("."))
        for s in out.iterdir()
        if s.is_dir() and not s.is_symlink() and not s.name.startswith(".")  # not .runs/
    }


def assert_entries_complete(out: Path) -> None:
    for stage, names in entries(out).items():
        for n in names:
            assert (out / stage / n / "meta.json").is_file(), f"{stage}/{n} has no meta.json"


def statuses(report: dict) -> dict[str, str]:
    return {f"{s['name']}:{s['impl']}": s["status"] for s in report["stages"]}


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


# ---- outputs switched in at once; read-only and full run folders; early checks; clean ----
QUICK = ["--set", "blueprint.blunf.steps=60", "--set", "blueprint.blunf.batch=4096"]
OUTPUTS = ("report.json", "blueprint.npz", "blueprint.png", "mesh.ply", "components.json")


@pytest.fixture(scope="module")
def done(room, tmp_path_factory) -> Path:
    """A finished run of `room` (FAST + QUICK), copied by the tests that need one."""
    out = tmp_path_factory.mktemp("done") / "run"
    code_version.cache_clear()
    assert main(["run", str(room), "--out", str(out), *FAST, *QUICK]) == 0
    return out


def copy_run(done: Path, dst: Path) -> Path:
    shutil.copytree(done, dst, symlinks=True)
    return dst


def published(out: Path) -> Path:
    """The one .runs/<id> folder every top-level output name resolves into."""
    folders = {(out / n).resolve().parent for n in OUTPUTS}
    assert len(folders) == 1, f"outputs of several runs: {folders}"
    (folder,) = folders
    assert folder.parent == (out / ".runs").resolve() and folder == (out / ".current").resolve()
    return folder


def entry_of(out: Path, report: dict, stage: str, impl: str) -> Path:
    key = next(s["key"] for s in report["stages"] if (s["name"], s["impl"]) == (stage, impl))
    return out / stage / key


def tree(folder: Path) -> dict[str, tuple[int, int]]:
    """Relative path -> (size, mtime) of every file, folder and link (links not followed)."""
    return {
        str(p.relative_to(folder)): (p.lstat().st_size, p.lstat().st_mtime_ns)
        for p in folder.rglob("*")
    }


def one_error_line(err: str) -> str:
    assert "Traceback" not in err, err
    errors = [ln for ln in err.strip().splitlines() if ln.startswith("blunf: error:")]
    assert len(errors) == 1 and err.strip().splitlines()[-1] == errors[0], err
    return errors[0]


def test_kill_while_publishing_then_rerun(room, done, tmp_path):
    """SIGKILL while a run copies its outputs: the run folder still shows the previous run,
    whole (no name points into the killed run's files); the rerun sweeps what the killed run
    left and switches every name to its own outputs at once."""
    out = copy_run(done, tmp_path / "run")
    before = published(out)
    old = json.loads((out / "report.json").read_text())
    # an older version's leftover beside the outputs: a temp file of a dead process
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], text=True, capture_output=True
    ).stdout.strip()
    stale = out / f".mesh.ply.tmp-{dead}"
    stale.write_bytes(b"half a mesh")

    steps = ["--set", "blueprint.blunf.steps=90"]  # another plan than the finished run's
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pipeline",
            "run",
            str(room),
            "--out",
            str(out),
            *FAST,
            *QUICK,
            *steps,
        ],
        cwd=ROOT,
        env={**os.environ, "BLUNF_THREADS": "1", "BLUNF_PUBLISH_PAUSE": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    t0 = time.monotonic()
    while True:  # kill once the new run has copied some of its outputs (blueprint.npz first)
        new = [
            d
            for d in (out / ".runs").iterdir()
            if d.resolve() != before and (d / "blueprint.npz").exists()
        ]
        if new:
            break
        assert p.poll() is None, p.communicate()
        assert time.monotonic() - t0 < 300, "the run never started publishing"
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    (killed,) = new
    assert not (killed / "report.json").exists()  # killed mid-publish, not after
    # Readers see the finished run only: every name, the same folder, its report and plan.
    assert published(out) == before
    assert json.loads((out / "report.json").read_text()) == old
    blunf_entry = entry_of(out, old, "blueprint", "blunf")
    assert (out / "blueprint.npz").read_bytes() == (blunf_entry / "blueprint.npz").read_bytes()
    assert (killed / "blueprint.npz").read_bytes() != (out / "blueprint.npz").read_bytes()

    # The rerun: sweeps the killed run's folder and the old temp file, publishes its own.
    code_version.cache_clear()
    assert main(["run", str(room), "--out", str(out), *FAST, *QUICK, *steps]) == 0
    assert not killed.exists() and not stale.exists() and not before.exists()
    assert [d.resolve() for d in (out / ".runs").iterdir()] == [published(out)]
    new_report = json.loads((out / "report.json").read_text())
    assert new_report["config"]["blueprint"]["blunf"]["steps"] == 90
    blunf_entry = entry_of(out, new_report, "blueprint", "blunf")
    assert (out / "blueprint.npz").read_bytes() == (blunf_entry / "blueprint.npz").read_bytes()
    assert not list(out.glob(".*.tmp-*")) and not list(out.rglob(".tmp-*"))


def _ro_mount_works(folder: Path) -> bool:
    r = subprocess.run(
        [
            "unshare",
            "-m",
            "sh",
            "-c",
            'mount --bind "$0" "$0" && mount -o remount,ro,bind '
            '"$0" "$0" && ! touch "$0/probe" 2>/dev/null',
            str(folder),
        ],
        capture_output=True,
    )
    return r.returncode == 0


def test_read_only_run_folder_one_line(room, done, tmp_path):
    """A fully cached run in a run folder on read-only media (a read-only bind mount in a
    private mount namespace): one line naming the folder, exit 2, nothing written."""
    out = copy_run(done, tmp_path / "run")
    if shutil.which("unshare") is None or not _ro_mount_works(out):
        pytest.skip("no read-only bind mount here (needs unshare -m and mount)")
    before = tree(out)
    r = subprocess.run(
        [
            "unshare",
            "-m",
            "sh",
            "-c",
            'mount --bind "$0" "$0" && mount -o remount,ro,bind "$0" "$0" && exec "$@"',
            str(out),
            sys.executable,
            "-m",
            "pipeline",
            "run",
            str(room),
            "--out",
            str(out),
            *FAST,
            *QUICK,
        ],
        cwd=ROOT,
        env={**os.environ, "BLUNF_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2, r.stderr
    line = one_error_line(r.stderr)
    assert str(out) in line and "Read-only file system" in line, line
    assert tree(out) == before


def test_full_disk_one_line_nothing_half_written(room, done, tmp_path):
    """The disk fills while a stage writes (RLIMIT_FSIZE: writes past 64 kB fail with EFBIG,
    as on a full disk): one line naming the folder, exit 2, no temp folder, no entry without
    meta.json, and the previous run's outputs still whole."""
    out = copy_run(done, tmp_path / "run")
    before = published(out)
    old = (out / "report.json").read_bytes()

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a killing signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (64_000, 64_000))

    r = subprocess.run(  # a new export title: export reruns and writes the (large) plan files
        [
            sys.executable,
            "-m",
            "pipeline",
            "run",
            str(room),
            "--out",
            str(out),
            *FAST,
            *QUICK,
            "--set",
            "export.title=full",
        ],
        cwd=ROOT,
        env={**os.environ, "BLUNF_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
    )
    assert r.returncode == 2, r.stderr
    line = one_error_line(r.stderr)
    assert str(out / "export") in line and "File too large" in line, line
    assert not list(out.rglob(".tmp-*")) and not list(out.glob(".*.tmp-*"))
    assert_entries_complete(out)
    assert published(out) == before
    assert [d.resolve() for d in (out / ".runs").iterdir()] == [before]
    assert (out / "report.json").read_bytes() == old


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


def test_clean_drops_entries_the_latest_run_did_not_use(room, done, tmp_path, capsys):
    """`blunf clean RUN`: the entries the latest report names stay (a rerun of it is all
    cached), every other one goes, and it says how much it freed."""
    out = copy_run(done, tmp_path / "run")
    seed5 = ["--set", "blueprint.blunf.seed=5"]  # a new plan: blunf, evaluate and export rerun
    code_version.cache_clear()
    assert main(["run", str(room), "--out", str(out), *FAST, *QUICK, *seed5]) == 0
    report = json.loads((out / "report.json").read_text())
    used = {(s["name"], s["key"]) for s in report["stages"] if s["key"]}
    every = {(stage, k) for stage, keys in entries(out).items() for k in keys}
    unused = every - used
    assert {s for s, _ in unused} == {"blueprint", "export", "evaluate"}, unused
    size = sum(p.stat().st_size for s, k in unused for p in (out / s / k).rglob("*") if p.is_file())
    capsys.readouterr()
    assert main(["clean", str(out)]) == 0
    assert capsys.readouterr().out.strip() == f"freed {size / 1e6:.1f} MB ({len(unused)} entries)"
    assert {(stage, k) for stage, keys in entries(out).items() for k in keys} == used
    assert_entries_complete(out)
    # what the run folder shows still opens, and a rerun of the latest config is all cached
    blunf_entry = entry_of(out, report, "blueprint", "blunf")
    assert (out / "blueprint.npz").read_bytes() == (blunf_entry / "blueprint.npz").read_bytes()
    assert main(["run", str(room), "--out", str(out), *FAST, *QUICK, *seed5]) == 0
    st = statuses(json.loads((out / "report.json").read_text()))
    assert set(st.values()) <= {"cached", "skipped"}, st
    capsys.readouterr()
    assert main(["clean", str(out)]) == 0
    assert capsys.readouterr().out.strip() == "freed 0.0 MB (0 entries)"
    # not a run folder: one line
    assert main(["clean", str(room)]) == 2
    assert "report.json" in capsys.readouterr().err

"""Faults while a run publishes its outputs: a kill mid-publish, a read-only or full run
folder, and `blunf clean`. Outputs are switched in at once: every top-level name points into
one `.runs/<id>/` folder, so readers see one whole run or the previous one.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.cache import code_version
from pipeline.cli import main
from tests.faults import (
    FAST,
    ROOT,
    assert_entries_complete,
    entries,
    make_fault_room,
    statuses,
)

QUICK = ["--set", "blueprint.blunf.steps=60", "--set", "blueprint.blunf.batch=4096"]
OUTPUTS = ("report.json", "blueprint.npz", "blueprint.png", "mesh.ply", "components.json")


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return make_fault_room(tmp_path_factory)


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


def run_with_64kb_files(room: Path, out: Path, setting: str) -> subprocess.CompletedProcess:
    """`blunf run` of room into out with --set setting, in a process whose writes past
    64 kB fail with EFBIG (RLIMIT_FSIZE), as on a full disk."""

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a killing signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (64_000, 64_000))

    args = ["run", str(room), "--out", str(out), *FAST, *QUICK, "--set", setting]
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *args],
        cwd=ROOT,
        env={**os.environ, "BLUNF_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
    )


def test_full_disk_one_line_nothing_half_written(room, done, tmp_path):
    """The disk fills while a stage writes (RLIMIT_FSIZE: writes past 64 kB fail with EFBIG,
    as on a full disk): one line naming the folder, exit 2, no temp folder, no entry without
    meta.json, and the previous run's outputs still whole."""
    out = copy_run(done, tmp_path / "run")
    before = published(out)
    old = (out / "report.json").read_bytes()

    # a new export title: export reruns and writes the (large) plan files
    r = run_with_64kb_files(room, out, "export.title=full")
    assert r.returncode == 2, r.stderr
    line = one_error_line(r.stderr)
    # the first write past the limit fails: the export stage's files, or the layout stage's
    # plan.dxf being published into the new run folder (it reaches 64 kB first on this room)
    assert str(out) in line and "File too large" in line, line
    assert not list(out.rglob(".tmp-*")) and not list(out.glob(".*.tmp-*"))
    assert_entries_complete(out)
    assert published(out) == before
    assert [d.resolve() for d in (out / ".runs").iterdir()] == [before]
    assert (out / "report.json").read_bytes() == old


def test_full_disk_while_fusion_writes_its_mesh_keeps_no_entry(room, done, tmp_path):
    """Open3D's mesh writer cuts a file short without an error (it prints and returns True):
    the disk fills as fusion writes mesh.ply (RLIMIT_FSIZE 64 kB, the mesh is larger). One
    line naming the file, exit 2, and no fusion entry for the new key, so the next run does
    not read a truncated mesh from the cache."""
    out = copy_run(done, tmp_path / "run")
    keys = set(entries(out)["fusion"])

    r = run_with_64kb_files(room, out, "fusion.voxel=0.04")  # fusion reruns
    assert r.returncode == 2, r.stderr
    line = one_error_line(r.stderr)
    assert "mesh.ply: cannot write" in line and str(out) in line, line
    assert set(entries(out)["fusion"]) == keys
    assert_entries_complete(out)
    assert not list(out.rglob(".tmp-*")) and not list(out.glob(".*.tmp-*"))


def test_clean_drops_entries_the_latest_run_did_not_use(room, done, tmp_path, capsys):
    """`blunf clean RUN`: the entries the latest report names stay (a rerun of it is all
    cached), every other one goes, and it says how much it freed."""
    out = copy_run(done, tmp_path / "run")
    seed5 = ["--set", "blueprint.blunf.seed=5"]  # a new plan: blunf, layout, evaluate, export rerun
    code_version.cache_clear()
    assert main(["run", str(room), "--out", str(out), *FAST, *QUICK, *seed5]) == 0
    report = json.loads((out / "report.json").read_text())
    used = {(s["name"], s["key"]) for s in report["stages"] if s["key"]}
    every = {(stage, k) for stage, keys in entries(out).items() for k in keys}
    unused = every - used
    assert {s for s, _ in unused} == {"blueprint", "layout", "export", "evaluate"}, unused
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

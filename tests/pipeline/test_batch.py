"""`blunf batch` on Dask: the same plans as runs one by one, whatever happens to a worker.

Every batch here is a real `python -m pipeline batch` process (a LocalCluster of single-thread
workers, or a scheduler and workers started as their own processes on 127.0.0.1); each test
stops every process it starts. The reference is each capture run alone in this process, as
`blunf run` does it, with one thread.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.config import stage_configs

ROOT = Path(__file__).resolve().parents[2]
RUN = [
    "--config",
    str(ROOT / "configs" / "fast.yaml"),
    "--set",
    "blueprint.blunf.steps=60",
    "--set",
    "blueprint.blunf.batch=4096",
    "--set",
    "fusion.voxel=0.05",
]
SCENES = ("room1", "room2", "room3")
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "BLUNF_THREADS": "1", "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def rooms(tmp_path_factory) -> dict[str, Path]:
    """Three 6-view 64x48 rooms and a copy of the first with a corrupt image."""
    from stages.synth import make_room

    base = tmp_path_factory.mktemp("batch")
    caps = {
        s: make_room(base / s, views=6, seed=i + 1, size=(64, 48)) for i, s in enumerate(SCENES)
    }
    bad = base / "corrupt"
    shutil.copytree(caps["room1"], bad)
    (bad / "images" / "0002.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    caps["corrupt"] = bad
    return caps


@pytest.fixture(scope="module")
def alone(rooms, tmp_path_factory) -> dict[str, bytes]:
    """blueprint.npz of each good room run alone (`blunf run`, one thread)."""
    out = tmp_path_factory.mktemp("alone")
    res = {}
    for s in SCENES:
        assert main(["run", str(rooms[s]), "--out", str(out / s), *RUN]) == 0
        res[s] = (out / s / "blueprint.npz").read_bytes()
    return res


def start(args: list[str]) -> subprocess.Popen:
    """A process in its own group (so that teardown reaches its children too)."""
    return subprocess.Popen(
        args,
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        # a session started in the background inherits SIGINT ignored: give the default back
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def wait_for_stage(p: subprocess.Popen, out: Path, scenes, timeout: float = 600) -> tuple:
    """(scene, pid) of the first worker seen running a stage that lasts > 1 s here."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout and p.poll() is None:
        for s in scenes:
            for stage in ("fusion", "blueprint", "export"):
                tmp = sorted((out / s / stage).glob(".tmp-*"))
                if tmp:
                    return s, int(tmp[0].name.rsplit("-", 1)[-1])
        time.sleep(0.02)
    raise AssertionError(f"no capture was seen running a stage ({p.poll()})")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture
def procs():
    """Processes a test starts: terminated (then killed) with their groups at the end."""
    started: list[subprocess.Popen] = []
    yield started
    for p in reversed(started):
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=15)


def batch_cmd(caps: list[Path], out: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "pipeline",
        "batch",
        *map(str, caps),
        "--out",
        str(out),
        "--dashboard",
        "none",
        *extra,
        *RUN,
    ]


# The timeouts are guards against a hung batch, not timings: the suites run two tests at once
# (pytest-xdist), so a batch may get one core for its two workers.
def finish(p: subprocess.Popen, timeout: float = 900) -> tuple[int, str]:
    try:
        _, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        _, err = p.communicate()
        raise AssertionError(f"the batch did not finish in {timeout} s:\n{err[-3000:]}") from None
    return p.returncode, err


def assert_same(out: Path, alone: dict[str, bytes], scenes=SCENES) -> None:
    for s in scenes:
        got = (out / s / "blueprint.npz").read_bytes()
        assert got == alone[s], f"{s}: the batch's blueprint.npz differs from the run alone"
        leftovers = list((out / s).glob("*/.tmp-*"))
        assert not leftovers, f"{s}: temp folders left: {leftovers}"
        assert_entries_complete(out / s)


def assert_entries_complete(run: Path) -> None:
    """Every cache entry `<stage>/<key>/` of a run folder holds its meta.json (the published
    outputs, `.runs/` and the links to them, are not cache entries)."""
    stages = [p for p in run.iterdir() if p.is_dir() and not p.is_symlink()]
    for stage in stages:
        if stage.name.startswith(".") or stage.name == "edits":
            continue
        for entry in stage.iterdir():
            if entry.is_dir() and not entry.name.startswith("."):
                assert (entry / "meta.json").is_file(), f"{entry}: a cache entry without meta"


def summary(out: Path) -> dict[str, dict]:
    with open(out / "summary.csv") as f:
        return {r["scene"]: r for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def local_batch(rooms, tmp_path_factory) -> tuple[Path, int, str]:
    """The three rooms and the corrupt one on a LocalCluster of 2 single-thread workers."""
    out = tmp_path_factory.mktemp("local") / "batch"
    caps = [rooms[s] for s in (*SCENES, "corrupt")]
    p = start(batch_cmd(caps, out, "--workers", "2", "--dashboard", "127.0.0.1:0"))
    try:
        rc, err = finish(p)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    return out, rc, err


def test_local_cluster_gives_the_plans_of_runs_alone(local_batch, alone):
    out, rc, err = local_batch
    assert rc == 1, err[-3000:]  # one capture failed
    assert "local cluster of 2 workers" in err
    assert "Dask dashboard http://127.0.0.1:" in err
    assert "running (room" in err, "no progress line named a running capture"
    # ... and the stage its run took up (the runner's events, told by the worker), not just
    # "starting": which stage a 2 s heartbeat catches depends on the machine's load
    stages = "|".join(stage_configs())
    assert re.search(rf"running \([^)]*\broom\w*: ({stages})\b", err), err
    assert_same(out, alone)
    facts = json.loads((out / "batch.json").read_text())
    assert facts["ok"] == 3 and facts["failed"] == 1
    assert facts["wall_seconds"] > 0 and facts["speedup"] > 0
    workers = {o["worker"] for o in facts["outcomes"] if o["ok"]}
    assert len(workers) == 2, f"both workers should have run captures: {workers}"
    assert "speedup" in (out / "index.html").read_text()


def test_corrupt_capture_is_reported_and_the_others_finish(local_batch):
    out, _, _ = local_batch
    rows = summary(out)
    assert [rows[s]["ok"] for s in SCENES] == ["True"] * 3
    bad = rows["corrupt"]
    assert bad["ok"] == "False"
    assert "0002.png" in bad["error"] and "\n" not in bad["error"], bad["error"]
    assert "blunf: error:" in (out / "corrupt.log").read_text()


@pytest.mark.slow
def test_worker_killed_mid_capture(rooms, alone, tmp_path, procs):
    out = tmp_path / "batch"
    scenes = ("room1", "room2")
    p = start(batch_cmd([rooms[s] for s in scenes], out, "--workers", "2"))
    procs.append(p)
    scene, pid = wait_for_stage(p, out, scenes)
    os.kill(pid, signal.SIGKILL)  # the worker process, mid-stage
    rc, err = finish(p)
    assert rc == 0, err[-3000:]
    assert_same(out, alone, scenes)
    attempts = (out / f"{scene}.log").read_text().count(" on worker ")
    assert attempts >= 2, f"{scene}: the killed capture was not run again"
    outcome = {o["scene"]: o for o in json.loads((out / "batch.json").read_text())["outcomes"]}
    assert not outcome[scene]["worker"].endswith(f":{pid}")


@pytest.mark.slow
def test_scheduler_and_workers_as_processes(rooms, alone, tmp_path, procs):
    dask = str(Path(sys.executable).parent / "dask")
    sched_file = tmp_path / "scheduler.json"
    common = ["--no-dashboard", "--host", "127.0.0.1"]
    procs.append(start([dask, "scheduler", "--scheduler-file", str(sched_file), *common]))
    t0 = time.monotonic()
    while not sched_file.is_file() and time.monotonic() - t0 < 60:
        assert procs[0].poll() is None, procs[0].stderr.read()
        time.sleep(0.1)
    address = json.loads(sched_file.read_text())["address"]
    assert address.startswith("tcp://127.0.0.1:")
    for _ in range(2):
        w = [dask, "worker", "--scheduler-file", str(sched_file), "--nthreads", "1", *common]
        procs.append(start(w))
    out = tmp_path / "batch"
    scenes = ("room2", "room3")
    p = start(batch_cmd([rooms[s] for s in scenes], out, "--scheduler", address))
    procs.append(p)
    rc, err = finish(p)
    assert rc == 0, err[-3000:]
    assert address in err
    assert_same(out, alone, scenes)
    assert all(summary(out)[s]["ok"] == "True" for s in scenes)


@pytest.mark.slow
def test_ctrl_c_stops_the_batch_and_leaves_the_cache_consistent(rooms, alone, tmp_path, procs):
    out = tmp_path / "batch"
    p = start(batch_cmd([rooms["room3"]], out))
    procs.append(p)
    _, pid = wait_for_stage(p, out, ["room3"])
    p.send_signal(signal.SIGINT)
    rc, err = finish(p, timeout=60)
    assert rc == 130, err[-3000:]
    assert summary(out)["room3"]["error"] == "interrupted"
    t0 = time.monotonic()
    while alive(pid) and time.monotonic() - t0 < 10:
        time.sleep(0.1)
    assert not alive(pid), "the worker outlived its batch"
    assert_entries_complete(out / "room3")  # what is under a key is complete
    p = start(batch_cmd([rooms["room3"]], out))  # and the next batch picks up from there
    procs.append(p)
    rc, err = finish(p)
    assert rc == 0, err[-3000:]
    assert_same(out, alone, ["room3"])


def test_bad_arguments_fail_before_any_cluster(rooms, tmp_path, capsys):
    out = tmp_path / "batch"
    twin = tmp_path / "twin" / "room1"
    shutil.copytree(rooms["room1"], twin)
    bad_spec = tmp_path / "edits.yaml"
    bad_spec.write_text("edits:\n  - select: {class: chair}\n    op: explode\n")
    cases = {
        "missing": ([str(tmp_path / "nowhere")], "nowhere: capture folder not found"),
        "twins": ([str(rooms["room1"]), str(twin)], "would collide with capture"),
        "bad set": ([str(rooms["room1"]), "--set", "fusion.nope=1"], "fusion.nope"),
        "bad edits": ([str(rooms["room1"]), "--edits", str(bad_spec)], "edits[0].op"),
    }
    # capture folders whose names collide with the batch's own files, or one's folder with
    # another's log (`a` beside `a.log`)
    for n in ("index.html", "summary.csv", "batch.json"):
        (tmp_path / n).mkdir()
        cases[n] = ([str(rooms["room1"]), str(tmp_path / n)], "the batch's own file")
    (tmp_path / "a").mkdir()
    (tmp_path / "a.log").mkdir()
    cases["a.log"] = ([str(tmp_path / "a"), str(tmp_path / "a.log")], "a.log would collide")
    for name, (args, msg) in cases.items():
        assert main(["batch", *args, "--out", str(out)]) == 2, name
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, f"{name}: {err}"
    assert not out.exists(), "nothing is made before the batch starts"

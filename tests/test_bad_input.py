"""The bad-input table (its cases: tests/bad_inputs.py): every broken capture, argument or
config ends in one line.

Each case breaks a private copy of the tiny room (or an argument), runs `blunf run` through
`pipeline.cli.main` (a few also through `python -m pipeline`), and checks the contract of
DESIGN.md: exit status 2, exactly one stderr line `blunf: error: ...` naming the file or value
at fault, no traceback, the capture unchanged byte for byte, and nothing half-written in the
run folder (no `.tmp-*` folder, no stage entry without meta.json).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.cli import main
from tests.bad_inputs import CASES, SUBPROCESS, Case

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--set", "blueprint.blunf.steps=20", "--set", "fusion.voxel=0.05"]


# ---- the checks ---------------------------------------------------------------------------
def snapshot(folder: Path, exclude: Path | None = None) -> dict[str, str]:
    """Relative path -> sha1 of the bytes (or "-> target" of a symlink) of a whole tree,
    leaving out what lies under `exclude`."""
    out = {}
    if not folder.exists():
        return out
    for p in sorted(folder.rglob("*")):
        if exclude is not None and p.is_relative_to(exclude):
            continue
        rel = str(p.relative_to(folder))
        if p.is_symlink():
            out[rel] = f"-> {os.readlink(p)}"
        elif p.is_file():
            out[rel] = hashlib.sha1(p.read_bytes()).hexdigest()
        else:
            out[rel] = "dir"
    return out


def assert_cache_clean(run: Path) -> None:
    """No temp folder anywhere; every stage entry (run/<stage>/<key>/) is finished."""
    if not run.is_dir():
        return
    tmp = [str(p) for p in run.rglob(".tmp-*")]
    assert not tmp, f"temp folders left behind: {tmp}"
    stages = (p for p in run.iterdir() if p.is_dir() and not p.is_symlink())
    for stage in (p for p in stages if not p.name.startswith(".")):  # not .runs/ (outputs)
        for entry in stage.iterdir():
            if entry.name.startswith("."):
                assert entry.suffix == ".lock" and entry.is_file(), entry
                continue
            assert (entry / "meta.json").is_file(), f"{entry}: entry without meta.json"


def check_error(rc: int, err: str, names: str, subprocess_run: bool) -> None:
    """Exit 2 and one `blunf: error:` line naming the fault; nothing else from blunf."""
    assert rc == 2, f"exit status {rc}, stderr:\n{err}"
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("blunf: error:")]
    assert len(errors) == 1, f"expected one error line, got:\n{err}"
    # In-process, pytest captures the log records, so stderr holds the error line only; a
    # subprocess also prints its INFO log (and pycolmap's glog) above it: the error comes last.
    assert lines[-1] == errors[0] if subprocess_run else lines == errors, err
    assert names in errors[0], f"{names!r} not named in: {errors[0]}"


@pytest.fixture
def broken(tiny_room, tmp_path, request):
    """(case, capture copy, tmp) with the case's edit applied to the copy."""
    case: Case = request.param
    cap = tmp_path / "cap"
    shutil.copytree(tiny_room, cap, symlinks=True)
    (tmp_path / "empty").mkdir()
    (tmp_path / "file.txt").write_text("not a capture\n")
    if case.edit is not None:
        case.edit(cap, tmp_path)
    return case, cap, tmp_path


def _argv(case: Case, cap: Path, tmp: Path) -> tuple[list[str], str, Path]:
    def sub(s: str) -> str:
        return s.replace("{cap}", str(cap)).replace("{tmp}", str(tmp))

    out = Path(sub(case.out))
    argv = ["run", sub(case.capture), "--out", str(out), *FAST, *(sub(a) for a in case.args)]
    return argv, sub(case.names), out


@pytest.mark.parametrize("broken", CASES, ids=[c.name for c in CASES], indirect=True)
def test_bad_input(broken, capsys):
    case, cap, tmp = broken
    argv, names, out = _argv(case, cap, tmp)
    # The capture, the files its symlinks point to and the config files: all but the run.
    before = snapshot(tmp, exclude=tmp / "run")
    rc = main(argv)  # argparse's own exit included: main() returns a status, never raises
    err = capsys.readouterr().err
    check_error(rc, err, names, subprocess_run=False)
    assert snapshot(tmp, exclude=tmp / "run") == before, "the capture (or a file it links) changed"
    if out != cap:  # (out_is_capture: refused before anything is written)
        assert_cache_clean(out)


@pytest.mark.parametrize(
    "broken",
    [c for c in CASES if c.name in SUBPROCESS],
    ids=[c.name for c in CASES if c.name in SUBPROCESS],
    indirect=True,
)
def test_bad_input_subprocess(broken):
    case, cap, tmp = broken
    argv, names, out = _argv(case, cap, tmp)
    before = snapshot(tmp, exclude=tmp / "run")
    r = subprocess.run(
        [sys.executable, "-m", "pipeline", *argv],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "BLUNF_THREADS": "1"},
        timeout=120,
    )
    check_error(r.returncode, r.stderr, names, subprocess_run=True)
    assert "blunf: error" not in r.stdout
    assert snapshot(tmp, exclude=tmp / "run") == before
    assert_cache_clean(out)


def test_failed_stage_then_good_config_reuses_finished_stages(tiny_room, tmp_path, capsys):
    """A failure inside a stage keeps what finished before it; the fixed rerun reuses that."""
    out = tmp_path / "run"
    bad = ["--set", "blueprint.blunf.lr=1e30"]  # diverges in the blueprint stage, after project
    assert main(["run", str(tiny_room), "--out", str(out), *FAST, *bad]) == 2
    check_error(2, capsys.readouterr().err, "blueprint.blunf", subprocess_run=False)
    assert_cache_clean(out)
    assert main(["run", str(tiny_room), "--out", str(out), *FAST]) == 0
    assert_cache_clean(out)
    st = {s["name"]: s["status"] for s in json.loads((out / "report.json").read_text())["stages"]}
    assert st["ingest"] == st["align"] == st["fusion"] == st["project"] == "cached"
    assert st["blueprint"] == "ran"


def test_set_order_does_not_matter():
    """Cross-field checks see the final values: raising depth_min above the default
    depth_max (5 m) is fine when depth_max is raised too, in either order."""
    from pipeline.config import load_config
    from stages.common.errors import BlunfError

    sets = ["fusion.depth_min=6", "fusion.depth_max=10"]
    a, b = load_config(None, sets), load_config(None, sets[::-1])
    assert a["fusion"] == b["fusion"] and (a["fusion"].depth_min, a["fusion"].depth_max) == (6, 10)
    with pytest.raises(BlunfError, match="depth_min < depth_max"):
        load_config(None, ["fusion.depth_min=6"])

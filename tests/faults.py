"""Helpers shared by the fault tests: the capture they run and the cache entries of a run
folder (folders `<stage>/<key>/`, each whole once it holds meta.json)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--set", "fusion.voxel=0.05", "--set", "run.methods=blunf,mvr"]


def make_fault_room(tmp_path_factory) -> Path:
    """The capture of the fault tests: 8 views of 64x48."""
    from stages.synth import make_room

    return make_room(tmp_path_factory.mktemp("faults") / "room", views=8, seed=4, size=(64, 48))


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

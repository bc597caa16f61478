"""The run the studio's default tests share: a tiny room's run without a NeRF, made once."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.runs import VOXEL, run_ok, small_room


@pytest.fixture(scope="session")
def studio_run(tmp_path_factory) -> tuple[Path, Path]:
    """(capture, run) of the small room, no NeRF trained. Tests read it; a test that writes
    into it keeps to RUN/studio (the studio's own folder)."""
    base = tmp_path_factory.mktemp("studio")
    cap = small_room(base / "room")
    run_ok(cap, base / "run", "--set", f"fusion.voxel={VOXEL}")
    return cap, base / "run"

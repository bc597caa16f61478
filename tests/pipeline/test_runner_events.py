"""Runner events (pipeline/runner.py `on_event`): each stage's start and end (ran, cached,
skipped, failed) and between them the progress of the stage at work, in order."""

from __future__ import annotations

import pytest

from pipeline.config import load_config
from pipeline.planner import Step
from pipeline.report import Report
from pipeline.runner import Runner, StageEvent
from stages.common.errors import BlunfError
from stages.common.progress import StepProgress
from stages.fusion import FusionInputs
from stages.ingest.config import IngestInputs
from tests.runs import VOXEL, small_room


def _stages(events: list) -> list[tuple[str, str | None, list[StepProgress]]]:
    """(stage, how it ended, its progress) per stage; fails unless each stage's events are
    start, its progress only, end."""
    out, at, steps = [], None, []
    for e in events:
        if isinstance(e, StageEvent) and e.what == "start":
            assert at is None, f"{e.stage} starts inside {at}"
            at, steps = e.stage, []
        elif isinstance(e, StageEvent):
            assert e.stage == at, f"{e.stage} ends, {at} under way"
            out.append((at, e.status, steps))
            at = None
        else:
            assert isinstance(e, StepProgress) and at is not None, e  # inside a stage only
            steps.append(e)
    assert at is None
    return out


def _runner(tmp_path, events: list) -> Runner:
    cfg = load_config(None, [f"fusion.voxel={VOXEL}"])
    return Runner(tmp_path / "run", cfg, Report("run", "room", {}), events.append)


def test_a_listener_follows_each_stage_and_its_progress(tmp_path) -> None:
    cap = small_room(tmp_path / "room")
    events: list = []
    r = _runner(tmp_path, events)
    frames = r.stage("ingest", "auto", IngestInputs(capture=cap)).frames
    r.step(Step("fusion", "tsdf", True, "asked for"), FusionInputs(frames=frames))
    r.step(Step("nerf", "grid", False, "no edit spec"), None)
    got = _stages(events)
    assert [(s, how) for s, how, _ in got] == [(s.name, s.status) for s in r.report.stages]
    assert [(s, how) for s, how, _ in got] == [
        ("ingest", "ran"),
        ("fusion", "ran"),
        ("nerf", "skipped"),
    ]
    # the fusion's integration, view by view: opened at 0, counting up, closed at its total
    steps = [e for e in got[1][2] if e.name == got[1][2][0].name]
    assert steps[0].n == 0 and not steps[0].done and steps[0].total == 8  # the room's views
    assert [e.n for e in steps] == sorted(e.n for e in steps)
    assert steps[-1].done and steps[-1].n == 8
    ends = [e for e in events if isinstance(e, StageEvent) and e.what == "end"]
    assert ends[0].seconds > 0 and ends[1].reason == "asked for"

    again: list = []  # the same stages in a second runner: found in the cache
    r = _runner(tmp_path, again)
    r.stage("ingest", "auto", IngestInputs(capture=cap))
    r.step(Step("fusion", "tsdf", True), FusionInputs(frames=frames))
    assert [(s, how, p) for s, how, p in _stages(again)] == [
        ("ingest", "cached", []),
        ("fusion", "cached", []),
    ]

    failed: list = []  # a stage that raises: its end says so, then the error goes on
    r = _runner(tmp_path, failed)
    with pytest.raises(BlunfError):
        r.stage("fusion", "tsdf", FusionInputs(frames=tmp_path / "none.json"))
    ((stage, how, _),) = _stages(failed)
    assert (stage, how) == ("fusion", "failed") and "none.json" in failed[-1].error


def test_the_heap_goes_back_before_each_stage_that_runs_and_before_its_peak(
    tmp_path, monkeypatch
) -> None:
    # a stage's peak_rss_mb counts from a heap without what earlier stages freed; a cached
    # or skipped stage costs no hand-back
    import pipeline.runner as runner

    calls: list[str] = []
    monkeypatch.setattr(runner, "heap_returned", lambda: calls.append("heap"))
    reset = runner.peak_rss_reset
    monkeypatch.setattr(runner, "peak_rss_reset", lambda: calls.append("reset") or reset())
    cap = small_room(tmp_path / "room")
    r = _runner(tmp_path, [])
    frames = r.stage("ingest", "auto", IngestInputs(capture=cap)).frames
    r.step(Step("fusion", "tsdf", True, "asked for"), FusionInputs(frames=frames))
    r.step(Step("nerf", "grid", False, "no edit spec"), None)
    r.stage("ingest", "auto", IngestInputs(capture=cap))  # cached now
    assert calls == ["heap", "reset"] * 2

"""Progress display (stages/common/progress.py): log lines every ~10 % off a terminal, nothing
when off, nothing for steps shorter than MIN_SECONDS."""

from __future__ import annotations

import logging
import re
import time

import pytest

from stages.common import progress as P


@pytest.fixture
def log_mode(monkeypatch, caplog):
    """Log mode with no minimum duration; restores the mode after."""
    monkeypatch.setattr(P, "MIN_SECONDS", 0.0)
    P.configure("log")
    caplog.set_level(logging.INFO, logger=P.log.name)
    yield caplog
    P.configure("auto")


def _lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == P.log.name]


def test_log_mode_gives_a_line_every_tenth_with_eta(log_mode):
    for _ in P.track(range(50), "stereo", unit="view"):
        pass
    lines = _lines(log_mode)
    assert len(lines) == 10, lines  # 10 %, 20 % ... 100 %: one line each, not one a view
    pcts = [int(re.search(r"(\d+)%", s).group(1)) for s in lines]  # type: ignore[union-attr]
    assert pcts == list(range(10, 101, 10))
    assert all(s.startswith("stereo:") for s in lines)
    assert "ETA" in lines[0] and "(5/50 view)" in lines[0]
    assert lines[-1].endswith("done")


def test_info_shown_unless_it_repeats_the_count(log_mode):
    bar = P.progress("nerf", total=4, unit="step")
    for k in range(1, 5):
        bar.moveto(k, step=k, psnr=20.0 + k)
    bar.close()
    lines = _lines(log_mode)
    assert len(lines) == 4
    assert lines[-1].endswith("done, psnr 24.00"), lines[-1]  # "step" is the unit: not again


def test_stopped_early_says_where(log_mode):
    bar = P.progress("nerf", total=100, unit="step")
    bar.update(30)
    bar.close()  # a plateau stop at 30 %
    lines = _lines(log_mode)
    assert lines[-1].startswith("nerf: stopped at 30/100 step")


def test_phase_without_total_logs_its_time(log_mode):
    with P.progress("sfm extract"):
        pass
    lines = _lines(log_mode)
    assert len(lines) == 1 and re.fullmatch(r"sfm extract: done in [\d.]+ s", lines[0]), lines


def test_off_and_short_steps_say_nothing(monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger=P.log.name)
    P.configure("off")
    try:
        monkeypatch.setattr(P, "MIN_SECONDS", 0.0)
        for _ in P.track(range(20), "blunf", unit="step"):
            pass
        with P.progress("sfm match"):
            pass
        assert _lines(caplog) == []
        P.configure("log")  # on, but every step is shorter than MIN_SECONDS
        monkeypatch.setattr(P, "MIN_SECONDS", 60.0)
        for _ in P.track(range(20), "blunf", unit="step"):
            time.sleep(0.001)
        assert _lines(caplog) == []
    finally:
        P.configure("auto")


def test_close_all_closes_what_a_failing_stage_left_open(log_mode):
    def failing():
        for i in P.track(range(10), "fusion", unit="view"):
            if i == 3:
                raise RuntimeError("boom")
            yield i

    with pytest.raises(RuntimeError):
        list(failing())
    bar = P.progress("edit render", total=5, unit="view")
    bar.update(2)
    assert bar in P._open
    P.close_all()
    assert bar.closed and not P._open
    bar.update(1)  # after close: ignored, no error


def test_bad_mode_is_refused():
    with pytest.raises(ValueError, match="progress mode"):
        P.configure("loud")


def test_a_listener_gets_every_change_of_its_threads_steps():
    # opened (n 0), each update with its facts, closed (done) - whatever the display mode;
    # a step of another thread is not told to this thread's listener
    import threading

    got: list[P.StepProgress] = []
    P.configure("off")
    try:
        with P.listening(got.append):
            bar = P.progress("nerf", total=3, unit="step")
            bar.update(1, psnr=20.5)
            bar.update(2)
            bar.close()
            other = threading.Thread(target=lambda: list(P.track(range(4), "elsewhere")))
            other.start()
            other.join()
        list(P.track(range(2), "after the block"))
    finally:
        P.configure("auto")
    assert [(e.name, e.n, e.total, e.done) for e in got] == [
        ("nerf", 0, 3, False),
        ("nerf", 1, 3, False),
        ("nerf", 3, 3, False),
        ("nerf", 3, 3, True),
    ]
    assert got[1].info == {"psnr": 20.5} and got[0].info == {} and got[0].unit == "step"

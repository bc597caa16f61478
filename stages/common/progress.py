"""Progress of the long steps of a stage: a bar with an ETA on a terminal, log lines elsewhere.

One switch for the whole process, set once by the command line (`configure`):
- "bar": a tqdm bar on stderr (shown once a step has run MIN_SECONDS, erased when done);
- "log": a line every ~10 % (logger `stages.progress`), only for steps past MIN_SECONDS, so a
  log file (batch workers) stays short;
- "off": nothing (`--quiet`);
- "auto" (the default): "bar" when stderr is a terminal, else "log".

A stage marks its steps in a line or two, without re-indenting its loops:

    for i in track(range(n), "stereo", unit="view"): ...      # a loop
    bar = progress("nerf", total=steps, unit="step")           # a loop with facts to show
    bar.update(1, psnr=24.1); ...; bar.close()
    with progress("sfm extract"): one_long_call()              # a phase: elapsed time only

A bar a stage leaves open (an exception) is closed by `close_all`, which the runner calls
after every stage.

A caller that shows progress its own way (a web page, a batch's summary line) listens
instead of reading the bars: `with listening(fn): ...` calls fn(StepProgress) for every step
opened, advanced and closed in that block's thread (as pycolmap's mapping callbacks), the
bars and log lines going on as before.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TypeVar

log = logging.getLogger(__name__)

MODES = ("auto", "bar", "log", "off")
MIN_SECONDS = 2.0  # steps shorter than this show nothing
LOG_STEPS = 10  # log mode: a line every 1 / LOG_STEPS of the total
LOG_EVERY_S = 60.0  # log mode, no total known: a line this often
_mode = "auto"
_open: list[Progress] = []
_lock = threading.Lock()
_bars_on = 0  # bars on screen now
_redirection: Any = None  # the logging redirection while any bar is on screen
T = TypeVar("T")
_local = threading.local()  # .listeners: the listeners of this thread's `listening` blocks


@dataclass(frozen=True)
class StepProgress:
    """How far one step is: sent to listeners when it opens, advances and closes."""

    name: str  # the step, e.g. "nerf" or "edit render"
    n: float  # how far, in `unit`
    total: float | None  # None: a phase of unknown length
    unit: str
    done: bool = False  # the step closed (finished, or stopped by an exception)
    info: dict[str, Any] = field(default_factory=dict)  # facts shown beside the count


Listener = Callable[[StepProgress], None]


@contextmanager
def listening(fn: Listener) -> Iterator[None]:
    """Within the block, fn gets a StepProgress for each change of a step this thread opens."""
    mine = getattr(_local, "listeners", ())
    _local.listeners = (*mine, fn)
    try:
        yield
    finally:
        _local.listeners = mine


def configure(mode: str) -> None:
    """Set how progress shows in this process: auto, bar, log or off."""
    global _mode
    if mode not in MODES:
        raise ValueError(f"progress mode {mode!r}: expected one of {MODES}")
    _mode = mode


def mode() -> str:
    """The mode in force ("auto" resolved against stderr now)."""
    if _mode != "auto":
        return _mode
    isatty = getattr(sys.stderr, "isatty", None)
    return "bar" if isatty is not None and isatty() else "log"


class Progress:
    """One step's progress. `total` None: a phase of unknown length (elapsed time only)."""

    def __init__(self, name: str, total: float | None = None, unit: str = "it"):
        self.name, self.unit = name, unit
        self.total = total if total is None or total > 0 else None
        self.n: float = 0
        self.info: dict[str, Any] = {}
        self.t0 = time.perf_counter()
        self.mode = mode()
        self.closed = False
        self._logged = -1  # log mode: the last tenth logged (-1: none yet)
        self._last_log = self.t0
        self._bar: Any = None
        self._ticker: threading.Thread | None = None
        self._listeners: tuple[Listener, ...] = getattr(_local, "listeners", ())
        self._tell()
        if self.mode == "bar":
            self._start_bar()
        with _lock:
            _open.append(self)

    # -- what stages call -------------------------------------------------------------------
    def update(self, n: float = 1, **info: Any) -> None:
        """Advance by `n` (in `unit`); `info` (e.g. psnr=24.1) is shown beside the count."""
        self.moveto(self.n + n, **info)

    def moveto(self, n: float, **info: Any) -> None:
        """Set how far the step is (in `unit`), e.g. seconds of a time budget."""
        if self.closed:
            return
        step = n - self.n
        self.n = n
        if info:
            self.info.update(info)
        self._tell()
        if self._bar is not None:
            if info:
                self._bar.set_postfix(_fmt_info(self.info, self.unit), refresh=False)
            self._bar.update(step)
        elif self.mode == "log":
            self._maybe_log()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        with _lock:
            if self in _open:
                _open.remove(self)
        self._tell()
        if self._bar is not None:
            self._bar.close()
            _redirect(-1)
        elif self.mode == "log":
            secs = time.perf_counter() - self.t0
            if self.total is None and secs >= MIN_SECONDS:
                log.info("%s: done in %s%s", self.name, _secs(secs), self._info())
            elif self._logged >= 0 and self._logged < LOG_STEPS:  # stopped before the total
                log.info("%s: stopped at %s, %s%s", self.name, self._count(), _secs(secs),
                         self._info())  # fmt: skip

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- inside -----------------------------------------------------------------------------
    def _tell(self) -> None:
        if self._listeners:
            n, total, info = self.n, self.total, dict(self.info)
            ev = StepProgress(self.name, n, total, self.unit, self.closed, info)
            for fn in self._listeners:
                fn(ev)

    def _start_bar(self) -> None:
        from tqdm import tqdm

        fmt = None
        if self.total is None:
            fmt = "{desc}: {elapsed}{postfix}"
        elif self.unit == "s":
            fmt = "{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}{postfix}"
        _redirect(+1)
        self._bar = tqdm(
            total=self.total,
            desc=self.name,
            unit=self.unit,
            file=sys.stderr,
            delay=MIN_SECONDS,
            leave=False,
            dynamic_ncols=True,
            mininterval=0.5,
            bar_format=fmt,
        )
        if self.total is None:  # a single long call: tick the elapsed time from a thread
            self._ticker = threading.Thread(target=self._tick, daemon=True)
            self._ticker.start()

    def _tick(self) -> None:
        while not self.closed:
            time.sleep(1.0)
            bar = self._bar
            if not self.closed and bar is not None and time.perf_counter() - self.t0 >= 2:
                try:
                    bar.refresh()
                except Exception:  # closed meanwhile
                    return

    def _maybe_log(self) -> None:
        now = time.perf_counter()
        secs = now - self.t0
        if self.total is None:
            if now - self._last_log >= LOG_EVERY_S:
                self._last_log = now
                log.info("%s: %s, %s%s", self.name, self._count(), _secs(secs), self._info())
            return
        frac = min(1.0, self.n / self.total)
        tenth = int(frac * LOG_STEPS + 1e-9)
        if tenth <= self._logged or tenth == 0 or secs < MIN_SECONDS:
            return
        self._logged = tenth
        eta = secs * (1 - frac) / frac
        when = f"ETA {_secs(eta)}" if frac < 1 else "done"
        log.info("%s: %3.0f%% (%s), %s, %s%s", self.name, 100 * frac, self._count(),
                 _secs(secs), when, self._info())  # fmt: skip

    def _count(self) -> str:
        n = f"{self.n:.0f}"
        return f"{n}/{self.total:.0f} {self.unit}" if self.total else f"{n} {self.unit}"

    def _info(self) -> str:
        return "".join(f", {k} {v}" for k, v in _fmt_info(self.info, self.unit).items())


def progress(name: str, total: float | None = None, unit: str = "it") -> Progress:
    """A progress display for one step; close it (or use it in a `with`) when done."""
    return Progress(name, total, unit)


def track(items: Iterable[T], name: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """`items` one by one, counting them (total: len(items) when it has one)."""
    if total is None:
        total = len(items) if hasattr(items, "__len__") else None  # type: ignore[arg-type]
    with Progress(name, total, unit) as bar:
        for x in items:
            yield x
            bar.update(1)


def close_all() -> None:
    """Close every bar still open (a stage that raised in the middle of a step)."""
    with _lock:
        left = list(_open)
    for p in left:
        p.close()


def _fmt_info(info: dict[str, Any], unit: str) -> dict[str, str]:
    """The facts shown beside the count, but not one the count gives already (unit = key)."""
    return {k: f"{v:.2f}" if isinstance(v, float) else str(v) for k, v in info.items() if k != unit}


def _secs(s: float) -> str:
    s = max(0.0, s)
    if s < 60:
        return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"
    m, s = divmod(int(s + 0.5), 60)
    return f"{m} min {s:02d} s" if m < 60 else f"{m // 60} h {m % 60:02d} min"


def _redirect(delta: int) -> None:
    """While a bar is on screen, log lines go through tqdm.write (above the bar, not across
    it): tqdm's own logging redirection, entered with the first open bar, left with the last."""
    global _bars_on, _redirection
    from tqdm.contrib.logging import logging_redirect_tqdm

    with _lock:
        _bars_on += delta
        if delta > 0 and _bars_on == 1:
            _redirection = logging_redirect_tqdm()
            _redirection.__enter__()
        elif delta < 0 and _bars_on == 0 and _redirection is not None:
            ctx, _redirection = _redirection, None
            ctx.__exit__(None, None, None)

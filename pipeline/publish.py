"""A run's user-facing outputs, switched in all at once, so no reader sees two runs mixed.

Each run writes its outputs (report.json, blueprint.*, mesh.ply, edits/...) into its own
hidden folder `RUN/.runs/<time>-<pid>/`. The names DESIGN.md gives (`RUN/report.json`,
`RUN/blueprint.png`, `RUN/edits/`...) are symbolic links `NAME -> .current/NAME`, and
`.current -> .runs/<id>` is replaced by one atomic rename once the run's folder is complete:
every top-level name then points into the new run at the same instant. A run killed while
copying leaves only its own `.runs/<id>` (its pid dead), which the next run sweeps, with the
previous run's outputs untouched; so does a run that fails. Older runs' folders are removed
once replaced.

A run removes only what runs wrote: `.runs/<id>` folders and the links to them. What a
person keeps in the run folder stays: the studio saves into `RUN/studio/` (a name no run
publishes), and a real folder where a run publishes a link (an older layout's `edits/`,
where the studio once saved) is moved aside into `RUN/studio/`, never deleted.

The environment variable BLUNF_PUBLISH_PAUSE (seconds) makes a run wait after each file it
publishes: tests use it to kill a run in the middle of publishing.
"""

from __future__ import annotations

import errno
import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pipeline.cache import alive
from pipeline.report_html import report_html
from stages.common.errors import BlunfError
from stages.common.io import write_json

RUNS = ".runs"
CURRENT = ".current"
STUDIO = "studio"  # the studio's saves: never published, never removed by a run
# errors that mean "this folder cannot be written" (read-only media, full disk, quota,
# RLIMIT_FSIZE), never a fault of the capture or of the config
WRITE_ERRNOS = frozenset({errno.EROFS, errno.ENOSPC, errno.EFBIG, errno.EDQUOT})


def write_error(e: OSError, where: Path | str) -> BlunfError | None:
    """A one-line error naming the path when `e` is a write failure, else None."""
    if e.errno not in WRITE_ERRNOS:
        return None
    # filename2 is the destination of a copy or rename (shutil names the source filename)
    return BlunfError(f"{e.filename2 or e.filename or where}: cannot write ({e.strerror})")


@contextmanager
def writing(where: Path | str) -> Iterator[None]:
    """Turn a write failure (read-only, disk full) into a one-line error naming the file."""
    try:
        yield
    except OSError as e:
        err = write_error(e, where)
        if err is None:
            raise
        raise err from None


class Publication:
    """The outputs of one run, gathered in `.runs/<id>/` and switched in by `switch()`."""

    def __init__(self, out: Path):
        self.out = Path(out)
        sweep(self.out)
        self.dir = self.out / RUNS / f"{time.time_ns()}-{os.getpid()}"
        try:
            self.dir.mkdir(parents=True)
        except OSError as e:
            why = e.strerror
            raise BlunfError(f"{self.out}: cannot write into the run folder ({why})") from None
        self.switched = False
        self._pause = float(os.environ.get("BLUNF_PUBLISH_PAUSE", "0") or 0)

    def add(self, src: Path, name: str) -> None:
        """Copy `src` to `name` (relative, e.g. "edits/orbit.gif") in this run's outputs."""
        if Path(name).parts[0] == STUDIO:
            raise ValueError(f"{name}: {STUDIO}/ is the studio's, never a run's output")
        dst = self.dir / name
        with writing(dst):
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
        if self._pause > 0:
            time.sleep(self._pause)

    def add_json(self, name: str, data: Any) -> None:
        with writing(self.dir / name):
            write_json(self.dir / name, data)

    def add_report(self, report: dict) -> None:
        """report.json, and report.html drawn from it and the outputs published so far."""
        self.add_json("report.json", report)
        page = report_html(self.dir, report)
        with writing(self.dir / "report.html"):
            (self.dir / "report.html").write_text(page, encoding="utf-8")

    def switch(self) -> None:
        """Make this run's outputs the run folder's, at once; remove the replaced run's."""
        names = sorted(p.name for p in self.dir.iterdir() if not p.name.startswith("."))
        for name in names:  # NAME -> .current/NAME (made once; dangling until the switch)
            _link(self.out / name, f"{CURRENT}/{name}")
        old = _current(self.out)
        _link(self.out / CURRENT, f"{RUNS}/{self.dir.name}")
        self.switched = True
        for p in self.out.iterdir():  # names the previous run had and this one has not
            if p.is_symlink() and os.readlink(p) == f"{CURRENT}/{p.name}" and p.name not in names:
                p.unlink(missing_ok=True)
        legacy = self.out / "edits"  # an older layout's real edits/ folder (studio saves)
        if legacy.is_dir() and not legacy.is_symlink():
            set_aside(legacy)
        if old is not None and old != self.dir.name:
            shutil.rmtree(self.out / RUNS / old, ignore_errors=True)
        sweep(self.out)

    def discard(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def _link(path: Path, target: str) -> None:
    """Point `path` at `target` atomically (a symlink renamed over it)."""
    if path.is_symlink() and os.readlink(path) == target:
        return
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.unlink(missing_ok=True)
    os.symlink(target, tmp)
    if path.is_dir() and not path.is_symlink():  # a real folder of an older run folder layout
        set_aside(path)
    os.replace(tmp, path)


def set_aside(folder: Path) -> Path:
    """Move a real folder out of a published name's way into RUN/studio/ (never delete it:
    an older layout's `edits/` holds the studio's saves). The first becomes RUN/studio itself
    when there is none yet (where the studio looks for its save), later ones go inside it."""
    studio = folder.parent / STUDIO
    if not studio.exists():
        dst = studio
    else:
        dst = studio / f"older-{folder.name}-{time.time_ns()}"
    os.replace(folder, dst)
    return dst


def _current(out: Path) -> str | None:
    """The name under .runs/ the run folder's outputs point at, if any."""
    try:
        return Path(os.readlink(out / CURRENT)).name
    except OSError:
        return None


def _pid(name: str) -> int | None:
    tail = name.rsplit("-", 1)[-1]
    return int(tail) if tail.isdigit() else None


def run_alive(name: str) -> bool:
    """Whether the run that made `.runs/<name>` (`<time_ns>-<pid>`) still lives: its pid is
    alive and that process started before the folder was made (a dead run's pid taken by a
    later process does not keep its folder forever)."""
    pid = _pid(name)
    if pid is None or not alive(pid):
        return False
    made = name.split("-", 1)[0]
    started = _process_start(pid)
    return started is None or not made.isdigit() or started <= int(made) / 1e9 + 1.0


def _process_start(pid: int) -> float | None:
    """When process `pid` started (seconds since the epoch; Linux /proc), else None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22: starttime
        btime = next(
            int(ln.split()[1]) for ln in Path("/proc/stat").read_text().splitlines()
            if ln.startswith("btime ")
        )  # fmt: skip
        return btime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def killed_runs(out: Path) -> list[Path]:
    """The `.runs/<id>` folders of runs that died before switching theirs in."""
    runs, cur = Path(out) / RUNS, _current(Path(out))
    if not runs.is_dir():
        return []
    return [d for d in runs.iterdir() if d.name != cur and not run_alive(d.name)]


def in_progress(out: Path) -> list[int]:
    """Pids of other live runs writing into this run folder now."""
    runs, cur = Path(out) / RUNS, _current(Path(out))
    names = [p.name for p in runs.iterdir() if p.name != cur] if runs.is_dir() else []
    live = [n for n in names if _pid(n) != os.getpid() and run_alive(n)]
    return sorted({p for p in map(_pid, live) if p is not None})


def sweep(out: Path) -> None:
    """Remove what killed runs left: their `.runs/<id>` folders, and temp files beside the
    outputs (`.NAME.tmp-<pid>`, also inside an older layout's real `edits/` folder)."""
    out = Path(out)
    cur = _current(out)
    if (out / RUNS).is_dir():
        for d in (out / RUNS).iterdir():
            pid = _pid(d.name)
            if d.name != cur and pid is not None and (pid == os.getpid() or not run_alive(d.name)):
                shutil.rmtree(d, ignore_errors=True)
    folders = [out] + [out / n for n in ("edits", STUDIO) if (out / n).is_dir()]
    for folder in folders:
        for t in folder.glob(".*.tmp-*"):
            pid = _pid(t.name)
            if pid is not None and not alive(pid) and (t.is_symlink() or t.is_file()):
                try:
                    t.unlink()
                except OSError:
                    pass

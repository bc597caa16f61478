"""Training a run's NeRF from the studio: the run `blunf run` would make, in the background.

A run made without edits has no NeRF (the planner trains one only for an edit spec or the
NeRF top-view baseline). The studio trains it the way the command it names would
(`pipeline.render.TRAIN_HINT`): the session's edits saved as RUN/studio/studio.yaml, then
`pipeline.run.run` on the run's capture into the same run folder, with the run's own
config (report.json) and configs/edit-fast.yaml on top. Every stage but the NeRF, the edit and
what follows is found in the run's cache, and the same command typed later finds the NeRF
there too. The page shows the run's events while it works (`pipeline.runner.Runner`'s
`on_event`): the stage at work and its step's progress.
"""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import yaml

from pipeline.config import Config, load_config, merge, recorded_sections
from pipeline.runner import RunEvent, StageEvent
from pipeline.studio.state import Session
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.common.progress import StepProgress

log = logging.getLogger(__name__)

EDIT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "edit-fast.yaml"


def training_config(run: Path, sets: Sequence[str] = ()) -> Config:
    """The run's own config (report.json), configs/edit-fast.yaml on top, then `sets`."""
    rep = Path(run) / "report.json"
    d = read_json(rep).get("config")
    if not isinstance(d, dict):
        raise BlunfError(f"{rep}: no config recorded (made by an older blunf? run it again)")
    d = recorded_sections(d)  # a run of an earlier version: its flat keys moved
    edit = yaml.safe_load(EDIT_CONFIG.read_text()) or {}
    with tempfile.TemporaryDirectory(prefix="blunf-studio-") as tmp:
        path = Path(tmp) / "config.yaml"
        merge(d, edit)  # the config files' own layering
        path.write_text(yaml.safe_dump(d))
        try:
            return load_config(path, list(sets))
        except BlunfError as e:
            raise BlunfError(f"{rep}: its config does not load ({e})") from None


class Trainer:
    """One background training of the session's run; `status()` says how far it is."""

    def __init__(self, session: Session, sets: Sequence[str] = ()):
        self.session, self.sets = session, tuple(sets)
        self.state = "idle"  # idle | running | done | failed
        self.error = ""
        self.stages: list[str] = []  # the stage lines seen, in order
        self.t0 = 0.0
        self.thread: threading.Thread | None = None
        self._stage = ""  # the stage at work, e.g. "nerf grid: running"
        self._step: StepProgress | None = None  # its step under way (None: none open)

    @property
    def running(self) -> bool:
        return self.state == "running"

    def start(self, views: Sequence[int] = (0,)) -> Path:
        """Save the edits and start training; returns the spec the run is given. Raises (and
        starts nothing) when the run has a NeRF, a training is under way or there is no edit."""
        sess = self.session
        if self.running:
            raise BlunfError("train: a training is under way already")
        if sess.scene.has_field:
            raise BlunfError(f"{sess.files.run}: the run has a NeRF already")
        if not sess.edits:
            raise BlunfError(
                "train: apply an edit first (the run trains its NeRF for an edit spec)"
            )
        cfg = training_config(sess.files.run, self.sets)  # a config that fails: here, at once
        spec = sess.save(list(views))
        self.state, self.error, self.stages, self.t0 = "running", "", [], time.perf_counter()
        self._stage, self._step = "", None
        self.thread = threading.Thread(target=self._work, args=(cfg, spec), daemon=True)
        self.thread.start()
        return spec

    def _on_event(self, e: RunEvent) -> None:
        """The run's events (its thread): the stage lines seen, the step under way."""
        if isinstance(e, StageEvent):
            how = "running" if e.what == "start" else e.status
            self._stage = f"{e.stage} {e.impl}: {how}"
            self.stages.append(self._stage)
            self._step = None
        else:
            self._step = None if e.done else e

    def _work(self, cfg: Config, spec: Path) -> None:
        from pipeline.run import run

        try:
            run(self.session.files.capture, self.session.files.run, cfg, spec, self._on_event)
            self.session.reload()
            if not self.session.scene.has_field:
                raise BlunfError(f"{self.session.files.run}: the run trained no NeRF")
            self.state = "done"
        except BlunfError as e:
            self.error, self.state = str(e), "failed"
        except Exception as e:  # the server goes on; the page says what failed
            log.exception("studio: training failed")
            self.error, self.state = f"{e.__class__.__name__}: {e}", "failed"

    def wait(self, timeout: float | None = None) -> str:
        if self.thread is not None:
            self.thread.join(timeout)
        return self.state

    def progress(self) -> tuple[str, float | None]:
        """What the page shows: a line (the stage at work, its step) and the fraction of
        the step done (None when unknown)."""
        secs = time.perf_counter() - self.t0
        if self.state == "done":
            return f"NeRF trained in {secs:.0f} s.", 1.0
        if self.state == "failed":
            return f"Training failed: {self.error}", None
        if self.state == "idle":
            return "", None
        step = self._step
        frac = None
        line = f"Training ({secs:.0f} s): {self._stage or 'starting'}"
        if step is not None:
            n, total = step.n, step.total
            line += (
                f"  \n{step.name}: {n:.0f}" + (f"/{total:.0f}" if total else "") + f" {step.unit}"
            )
            frac = min(1.0, n / total) if total else None
        return line, frac

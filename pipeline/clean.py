"""`blunf clean RUN_DIR`: drop the cache entries the run folder's latest run did not use.

Stage caches are never pruned by a run (an entry of an earlier config may be wanted again);
each entry costs from kilobytes to a few hundred MB (a NeRF model, fused depth). The entries
the latest report.json names (ran or cached) are kept, with everything the outputs need.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from pipeline.cache import alive
from pipeline.config import stage_configs
from pipeline.publish import in_progress, killed_runs, sweep
from stages.common.errors import BlunfError
from stages.common.io import read_json


def clean(run_dir: Path) -> tuple[int, int]:
    """Remove unused entries (and temp folders of killed runs); returns (bytes, entries)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise BlunfError(f"{run_dir}: run folder not found")
    report = run_dir / "report.json"
    if not report.is_file():
        raise BlunfError(f"{report}: not found (not a run folder, or no run finished in it)")
    busy = in_progress(run_dir)
    if busy:
        raise BlunfError(f"{run_dir}: a run (pid {busy[0]}) is writing into it; clean after it")
    stages_ = read_json(report).get("stages")
    if not isinstance(stages_, list):
        raise BlunfError(f"{report}: no 'stages' list: not a run report")
    keep = {(s.get("name"), s.get("key")) for s in stages_ if isinstance(s, dict)}
    killed = killed_runs(run_dir)
    freed, count = sum(map(_size, killed)), len(killed)
    sweep(run_dir)  # killed runs' .runs/<id> folders (their pid dead or taken by another)
    for stage in stage_configs():
        folder = run_dir / stage
        if not folder.is_dir() or folder.is_symlink():
            continue
        for entry in sorted(folder.iterdir()):
            if not entry.is_dir() or entry.is_symlink():
                continue
            if entry.name.startswith(".tmp-"):  # a killed run's temp folder (its pid is dead)
                pid = entry.name.rsplit("-", 1)[-1]
                if not pid.isdigit() or alive(int(pid)):
                    continue
            elif entry.name.startswith(".") or (stage, entry.name) in keep:
                continue
            freed += _size(entry)
            count += 1
            shutil.rmtree(entry)
            (folder / f".{entry.name}.lock").unlink(missing_ok=True)
    return freed, count


def _size(folder: Path) -> int:
    total = 0
    for root, _, files in os.walk(folder):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total

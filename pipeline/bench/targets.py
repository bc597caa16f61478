"""`blunf bench --targets`: each speed target's figure, from real runs of the pipeline.

    blunf bench --targets [--quick] [--only 1,5,7] [--repeats N] [--threads N] --out DIR

The targets, each a row or two of DIR/targets.md (and .csv, .json):
  1  the photos-only demo room (60 views 320x240, configs/phone.yaml): run <= 120 s, fwIoU >= 84
  2  the 7-Scenes kitchen from its photos (100 views 640x480): run <= 300 s; its sensor-depth
     run of the same views is the measured reference, and the photos-only plan is scored
     against that run's plan (pipeline/bench/real.py)
  3  `make demo`'s two runs (1, and the edit run of 4) <= 300 s together
  4  the demo's edit run (configs/edit-fast.yaml): NeRF training <= 120 s, changed_iou >= 0.9
     in every view of every edit
  5  an edited 320x240 view <= 1 s, an 80x60 preview <= 0.2 s (pipeline/bench/preview.py on
     the edit run; the volume render is the measured reference)
  6  SfM <= 0.5x plain pycolmap's time at <= 1.1x its ATE (pipeline.bench.sfm.compare)
  7  the project stage <= 5 s for 100 frames of 640x480 (measure.Bench: the stages before it
     from a warm cache, so that a repeat reruns the project stage and what follows)
  8  peak memory <= 4 GB over every run above (report.json's per-stage peaks and the peak of
     the run's process)
Whole runs are the `blunf run` command itself in a child process, timed from its start
(interpreter and imports included: what a user waits for), with its CPU (all threads, and the
processes it waited for) from the kernel (wait4) and its peak memory from its own VmHWM
(target_runs.timed_command says why not wait4's); each repeat starts from an
empty run folder. Runs use the threads the command picks for itself (the free cores) unless
--threads is given. Figures are medians over the repeats.
--quick: one repeat, and 30 of the kitchen's 100 views for targets 2 and 6 (the rows say so).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from pipeline.bench.grid import SHARED_DATA, Variant
from pipeline.bench.measure import Bench, timestamp
from pipeline.bench.target_runs import (
    KITCHEN_QUICK_TIMEOUT_S,
    TIMEOUT_S,
    Measured,
    Session,
    med,
    metric,
    shown,
    skip,
    stage_peaks_of,
    top_stages,
    wall_cpu,
    where_time_went,
)
from pipeline.bench.target_table import BUDGET, Bar, Row, write
from stages.common.errors import BlunfError
from stages.common.io import read_json

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
KITCHEN = SHARED_DATA / "7scenes-redkitchen"
PHONE = ROOT / "configs" / "phone.yaml"
EDIT_FAST = ROOT / "configs" / "edit-fast.yaml"
DEMO_EDITS = ROOT / "configs" / "edits" / "demo.yaml"
TARGETS = tuple(range(1, 9))


# ---- the targets ---------------------------------------------------------------------------
def demo_phone(s: Session) -> tuple[list[Measured] | str, str]:
    cap = s.capture(60, (320, 240), photos=True)
    ms = s.run("demo-phone", cap, ["--config", str(PHONE)])
    synth = shown(["blunf", "synth", cap, "--views", "60", "--seed", "0", "--photos-only"])
    return ms, f"{synth}; {s.commands.get('demo-phone', '')}"


def demo_edit(s: Session) -> tuple[list[Measured] | str, str]:
    cap = s.capture(60, (320, 240))
    ms = s.run("demo-edit", cap, ["--config", str(EDIT_FAST), "--edits", str(DEMO_EDITS)])
    synth = shown(["blunf", "synth", cap, "--views", "60", "--seed", "0"])
    return ms, f"{synth}; {s.commands.get('demo-edit', '')}"


def target_1(s: Session) -> list[Row]:
    ms, cmd = demo_phone(s)
    rows = [
        Row("1a", "photos-only demo room, whole run", "s", Bar("figure", "<=", 120), cmd),
        Row("1b", "photos-only demo room, BluNF fwIoU", "", Bar("figure", ">=", 84), cmd),
    ]
    if isinstance(ms, str):
        return skip(rows, ms)
    wall, cpu = wall_cpu(ms)
    rows[0].figure, rows[0].wall_s, rows[0].cpu_s = wall, wall, cpu
    rows[0].note = f"slowest: {top_stages(ms)}"
    rows[1].figure, rows[1].wall_s, rows[1].cpu_s = metric(ms, "blueprint.blunf.fwiou"), wall, cpu
    return rows


def target_2(s: Session) -> list[Row]:
    from pipeline.bench.real import score, stripped_copy

    frames = 30 if s.quick else 100
    text = f"7-Scenes kitchen from photos, {frames} views 640x480, whole run"
    row = Row("2", text, "s", Bar("figure", "<=", 300), "", ref_name="sensor-depth run")
    if not KITCHEN.is_dir():
        return skip([row], f"{KITCHEN} absent")
    photos = stripped_copy(KITCHEN, s.out / "captures" / "kitchen-photos", sensor=False)
    sensor = stripped_copy(KITCHEN, s.out / "captures" / "kitchen-sensor", sensor=True)
    pick = ["--frames", str(frames)]
    limit = KITCHEN_QUICK_TIMEOUT_S if s.quick else TIMEOUT_S
    ms = s.run("kitchen-photos", photos, ["--config", str(PHONE), *pick], timeout=limit)
    row.command = s.commands.get("kitchen-photos", "")
    if isinstance(ms, str):
        if "kitchen-photos" not in s.killed:
            return skip([row], ms)
        row.figure, row.cpu_s, last = s.killed["kitchen-photos"]
        row.wall_s, row.ref_name = row.figure, BUDGET  # no reference measured
        row.note = f"killed at the {limit} s limit (a lower bound), after: {last}; no reference run"
        return [row]
    ref = s.run("kitchen-sensor", sensor, pick, repeats=1)
    row.command += f" (ref: {s.commands['kitchen-sensor']})"
    row.figure, row.cpu_s = wall_cpu(ms)
    row.wall_s = row.figure
    row.note = ("quick: 30 of the 100 views; " if s.quick else "") + f"slowest: {top_stages(ms)}"
    if isinstance(ref, str):
        row.note += f"; reference failed: {ref}"
        return [row]
    row.reference = wall_cpu(ref)[0]
    sc = score(s.dirs["kitchen-sensor"], s.dirs["kitchen-photos"])
    row.note += f"; plan fwIoU {sc['plan']['fwiou']:.1f} against the sensor run's plan"
    if sc["poses"].get("ate_rmse_m") is not None:
        row.note += f", ATE {100 * sc['poses']['ate_rmse_m']:.1f} cm"
    return [row]


def target_3(s: Session) -> list[Row]:
    (phone, c1), (edit, c2) = demo_phone(s), demo_edit(s)
    row = Row("3", "`make demo`'s two runs", "s", Bar("figure", "<=", 300), f"{c1}; {c2}")
    if isinstance(phone, str) or isinstance(edit, str):
        return skip([row], phone if isinstance(phone, str) else str(edit))
    (w1, c1s), (w2, c2s) = wall_cpu(phone), wall_cpu(edit)
    if None in (w1, w2, c1s, c2s):
        return skip([row], "a run gave no timing")
    row.figure = row.wall_s = float(w1 or 0) + float(w2 or 0)
    row.cpu_s = float(c1s or 0) + float(c2s or 0)
    row.note = f"photos-only {w1:.0f} s + edit run {w2:.0f} s; captures made beforehand"
    return [row]


def worst_view(ms: list[Measured], views: Sequence[int]) -> tuple[float | None, str]:
    """Median over the runs of the lowest changed_iou of any edit in any of the spec's
    `views` (input view indices, in changed_iou_views' order), and where it was."""

    def name(e: dict, i: int) -> str:
        return f"edit {e.get('index')} ({e.get('op')}) in view {views[i] if i < len(views) else i}"

    lows, where = [], ""
    for m in ms:
        per = [
            (v, name(e, i))
            for e in m.sample.metrics.get("edit") or []
            for i, v in enumerate(e.get("changed_iou_views") or [])
            if v is not None
        ]
        if per:
            lo = min(per)
            lows.append(lo[0])
            where = lo[1]
    return med(lows), where


def target_4(s: Session) -> list[Row]:
    ms, cmd = demo_edit(s)
    rows = [
        Row("4a", "NeRF for the demo's edits, training", "s", Bar("figure", "<=", 120), cmd),
        Row("4b", "edit changed_iou, lowest view", "", Bar("figure", ">=", 0.9), cmd),
    ]
    if isinstance(ms, str):
        return skip(rows, ms)
    rows[0].figure = rows[0].wall_s = metric(ms, "nerf.seconds")
    rows[0].cpu_s = wall_cpu(ms, "nerf")[1]
    rows[0].note = f"{metric(ms, 'nerf.steps') or 0:.0f} steps; CPU s: the nerf stage's"
    from stages.edit.spec import load_spec

    rows[1].figure, where = worst_view(ms, load_spec(DEMO_EDITS).views)
    rows[1].wall_s, rows[1].cpu_s = wall_cpu(ms, "edit")
    rows[1].note = f"lowest: {where}; seconds: the edit stage's" if where else "no changed_iou"
    return rows


def target_5(s: Session) -> list[Row]:
    import torch

    from pipeline.bench.preview import bench as preview

    ms, _ = demo_edit(s)
    cmd = "python -m pipeline.bench.preview {run} --edits configs/edits/demo.yaml --repeats {n}"
    rows = [
        Row("5a", "one edited 320x240 view, fast path", "s", Bar("figure", "<=", 1.0), cmd),
        Row("5b", "edited 80x60 preview, fast path", "s", Bar("figure", "<=", 0.2), cmd),
    ]
    if isinstance(ms, str):
        return skip(rows, ms)
    run, n, cores = s.dirs["demo-edit"], s.repeats, s.cores
    torch.set_num_threads(cores)
    res = preview(run, DEMO_EDITS, [], n, quality=False)
    for r, size in zip(rows, ("320x240", "80x60"), strict=True):
        t = res["timing"][size]
        r.command = cmd.format(run=shown([run]), n=n) + f" --threads {cores}"
        r.figure, r.wall_s, r.cpu_s = t["fast"]["wall"], t["fast"]["wall"], t["fast"]["cpu"]
        r.reference, r.ref_name = t["volume"]["wall"], "volume render"
        vol_cpu = t["volume"]["cpu"]
        r.note = f"all the spec's edits, its views, {n} repeat(s); volume CPU {vol_cpu:.2f} s"
    return rows


def target_6(s: Session) -> list[Row]:
    frames, threads = (30 if s.quick else 100), s.threads or 1
    call = shown(
        ["python", "-m", "pipeline.bench.sfm", KITCHEN, "--frames", frames]
        + ["--repeats", s.repeats, "--threads", threads]
    )
    rows = [
        Row("6a", "SfM time against plain pycolmap", "s", Bar("ratio", "<=", 0.5), call),
        Row("6b", "SfM ATE against plain pycolmap", "m", Bar("ratio", "<=", 1.1), call),
    ]
    for r in rows:
        r.ref_name = "pycolmap"
    try:
        from pipeline.bench.sfm import compare  # type: ignore[import-not-found,unused-ignore]
    except ModuleNotFoundError as e:
        if e.name != "pipeline.bench.sfm":
            raise
        return skip(rows, "pipeline.bench.sfm absent")
    if not KITCHEN.is_dir():
        return skip(rows, f"{KITCHEN} absent")
    res = compare(KITCHEN, frames, s.repeats, threads, ())
    rows[0].figure, rows[0].reference = res["ours_s"], res["ref_s"]
    for r in rows:
        r.wall_s, r.cpu_s = res["ours_s"], res.get("ours_cpu_s")
        r.note = f"{frames} views" + (" (quick)" if s.quick else "") + f", {threads} thread(s)"
    rows[1].figure, rows[1].reference = res["ours_ate_m"], res["ref_ate_m"]
    if res.get("ratio_cpu") is not None:
        rows[0].note += f"; CPU {res['ours_cpu_s']:.1f} s against {res['ref_cpu_s']:.1f} s"
        rows[0].note += f" = {res['ratio_cpu']:.2f}x"
    return rows


def target_7(
    s: Session, views: int = 100, size: tuple[int, int] = (640, 480), sets: Sequence[str] = ()
) -> list[Row]:
    """The project stage on the procedural room; `sets`: overrides of every run (tests)."""
    cap = s.capture(views, size)
    name = f"project-{views}-{size[0]}x{size[1]}"
    v = Variant(name, "project", name, ("run.methods=mvr", *sets), fresh_from="project")
    synth = shown(["blunf", "synth", cap, "--views", views, "--size", f"{size[0]}x{size[1]}"])
    opts = shown([x for o in v.sets for x in ("--set", o)])
    cmd = f"{synth}; blunf run {shown([cap])} --out RUN {opts}: project stage"
    text = f"project stage, {views} frames {size[0]}x{size[1]} (sensor depth)"
    row = Row("7", text, "s", Bar("figure", "<=", 5.0), cmd)
    b = Bench(s.out, s.cores)
    got: list[Measured] = []
    for rep in range(s.repeats):
        smp = b.once(v, cap, rep)
        if isinstance(smp, str):
            s.runs[name] = smp
            return skip([row], smp)
        peaks = stage_peaks_of(read_json(s.out / "reports" / f"{name}-r{rep}.json"))
        got.append(Measured(smp, peaks))
    s.runs[name] = got
    row.figure, row.cpu_s = wall_cpu(got, "project")
    row.wall_s = row.figure
    row.note = f"{s.repeats} repeat(s), the stages before it from a warm cache"
    return [row]


def target_8(s: Session) -> list[Row]:
    row = Row(
        "8", "peak memory, every run above", "MB", Bar("figure", "<=", 4096), "the rows above"
    )
    peaks = [
        (p, f"{name} {stage}")
        for name, ms in s.runs.items()
        if not isinstance(ms, str)
        for m in ms
        for stage, p in [*m.stage_peaks.items(), ("process", m.process_peak_mb)]
        if p is not None
    ]
    if not peaks:
        return skip([row], "no run measured (run target 8 with others)")
    top = max(peaks)
    row.figure = top[0]
    row.note = f"highest: {top[1]}, over {len(s.runs)} run(s)"
    return [row]


ROWS: dict[int, Callable[[Session], list[Row]]] = {
    1: target_1,
    2: target_2,
    3: target_3,
    4: target_4,
    5: target_5,
    6: target_6,
    7: target_7,
    8: target_8,
}


def parse_only(text: str | None) -> tuple[int, ...]:
    """ "1,5,7" -> (1, 5, 7); None -> every target. A bad list is a one-line error."""
    if not text:
        return TARGETS
    try:
        got = sorted({int(t) for t in text.split(",") if t.strip()})
    except ValueError:
        raise BlunfError(f"--only {text!r}: expected target numbers, e.g. 1,5,7") from None
    bad = [t for t in got if t not in TARGETS]
    if bad or not got:
        raise BlunfError(f"--only {text!r}: targets are 1..{TARGETS[-1]}")
    return tuple(got)


def targets(
    out: Path,
    quick: bool = False,
    repeats: int | None = None,
    threads: int = 0,
    only: Sequence[int] = TARGETS,
) -> Path:
    """Measure the targets `only` (parse_only); write targets.md/.csv/.json into out.
    Returns the path of targets.md."""
    chosen = tuple(only)
    s = Session(Path(out), quick, repeats or (1 if quick else 3), threads)
    t0 = time.perf_counter()
    header = [
        f"{timestamp()}; {'quick' if quick else 'full'}; targets {','.join(map(str, chosen))}; "
        f"{s.repeats} repeat(s) (medians); threads {threads or 'sized to the free cores'}; "
        f"{len(os.sched_getaffinity(0))} cores, load average {os.getloadavg()[0]:.2f} at start."
    ]
    rows: list[Row] = []

    def written(done: str) -> Path:
        extra = {
            "runs": {k: v if isinstance(v, str) else len(v) for k, v in s.runs.items()},
            "commands": s.commands,
        }
        return write(rows, [*header, done], where_time_went(s), extra, s.out)

    for t in chosen:
        log.info("targets: target %d", t)
        try:
            rows += ROWS[t](s)
        except Exception as e:  # a target that fails costs its rows, not the others'
            log.error("targets: target %d failed", t, exc_info=not isinstance(e, BlunfError))
            why = f"failed: {e}" if isinstance(e, BlunfError) else f"failed: {e!r}"
            rows.append(Row(str(t), f"target {t}", "", Bar("figure", "<=", 0), "", skipped=why))
        written(f"Targets done so far: {len(rows)} row(s).")  # kept if the bench is stopped
    took = time.perf_counter() - t0
    load = os.getloadavg()[0]
    return written(f"The bench took {took:.0f} s; load average {load:.2f} at the end.")

"""`blunf bench`: run time against error over a grid of stage variants, on one machine.

`bench(out)` runs every variant of the grid (grid.py) `repeats` times through the real
pipeline (measure.py), and writes into `out`:
  bench.csv              one row per variant: medians of wall, CPU, peak memory and the
                         seconds of every stage, the error, and every report.json metric
  bench.md               the tables, each group's Pareto points, the cost fits
  pareto-<group>-<capture>.png, cost-frames.png, cost-pixels.png
  reports/<variant>-r<i>.json, logs/<variant>.log   the runs behind each row
Reference points (the paper's recipe) run in the same bench, interleaved with the others, so
the ratios to them hold on a noisy machine.

`blunf bench --targets` (targets.py) measures the speed targets instead: each one's figure,
the reference measured in the same bench (or the target's budget), their ratio, pass or fail
and the command behind it, in targets.md / .csv / .json.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

from pipeline.bench.analysis import cost_fits, fronts, plot_cost, plot_fronts
from pipeline.bench.grid import CaptureSpec, Variant, captures, full_grid, quick_grid
from pipeline.bench.measure import Bench, Sample, capture_facts, summarise, timestamp
from pipeline.bench.tables import markdown, write_csv
from stages.common.errors import BlunfError

log = logging.getLogger(__name__)

COST_STAGES = ("fusion", "project", "blueprint")  # stages whose cost is fitted against size
ERROR_NAMES = {
    "100-": "100 - {m} (%)",
    "poses.ate_rmse_m": "ATE RMSE after a similarity (m)",
    "40-nerf.psnr_heldout": "40 - held-out PSNR (dB)",
}

__all__ = ["bench", "Variant", "CaptureSpec", "quick_grid", "full_grid"]


def bench(
    out: Path,
    quick: bool = False,
    repeats: int | None = None,
    threads: int = 1,
    grid: Sequence[Variant] | None = None,
    specs: dict[str, CaptureSpec] | None = None,
    keep_runs: bool = False,
) -> Path:
    """Run the grid (quick or full, or `grid`); write bench.csv, bench.md and the figures.

    Args:
        repeats: runs per variant, medians reported (default 1 quick, 3 full).
        threads: CPU threads of every run (1 keeps timings steady on a shared machine).
        specs: the captures by name (default grid.captures(quick)).
        keep_runs: keep every run folder (by default only reports and logs are kept).
    Returns the path of bench.md.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    repeats = repeats or (1 if quick else 3)
    variants = list(grid if grid is not None else (quick_grid() if quick else full_grid()))
    specs = specs or captures(quick)
    kind = "custom" if grid is not None else "quick" if quick else "full"
    names = [v.name for v in variants]
    if len(set(names)) != len(names):
        raise BlunfError(
            f"bench: variant names repeat: {sorted(n for n in names if names.count(n) > 1)}"
        )
    header = [
        f"{timestamp()}; {kind} grid of {len(variants)} variants, "
        f"{repeats} repeat(s) each (medians), {threads} thread(s) a run, "
        f"{len(os.sched_getaffinity(0))} cores, load average {os.getloadavg()[0]:.2f} at start.",
    ]
    paths, skipped = _resolve(variants, specs, out)
    for cap, why in skipped.items():
        msg = f"bench: {why}: its {sum(v.capture == cap for v in variants)} variant(s) skipped"
        log.warning(msg)
        header.append(f"Skipped: {why}.")
    variants = [v for v in variants if v.capture in paths]
    keys = dict.fromkeys((v.capture, v.frames) for v in variants)  # each capture read once
    facts = {k: capture_facts(paths[k[0]], k[1]) for k in keys}

    b = Bench(out, threads, keep_runs)
    samples: dict[str, list[Sample]] = {v.name: [] for v in variants}
    errors: dict[str, list[str]] = {v.name: [] for v in variants}
    for rep in range(repeats):  # interleaved: repeat r of every variant, then r + 1
        for i, v in enumerate(variants):
            log.info(
                "bench: repeat %d/%d, %s (%d/%d)", rep + 1, repeats, v.name, i + 1, len(variants)
            )
            s = b.once(v, paths[v.capture], rep)
            if isinstance(s, str):
                log.warning("bench: %s failed: %s", v.name, s)
                errors[v.name].append(s)
            else:
                samples[v.name].append(s)
    rows = [
        summarise(v, samples[v.name], errors[v.name], facts[(v.capture, v.frames)])
        for v in variants
    ]
    _ratios(rows, variants)
    front = fronts(rows)
    names_by_group = {
        g: _error_name(next(v.error for v in variants if v.group == g))
        for g in dict.fromkeys(v.group for v in variants)
    }
    fits = {axis: cost_fits(rows, axis, COST_STAGES) for axis in ("frames", "pixels")}
    figures = plot_fronts(front, names_by_group, out)
    figures += [p for axis, f in fits.items() if (p := plot_cost(f, axis, out)) is not None]
    for axis, per_stage in fits.items():
        for st, (_, _, (a, c, r2)) in per_stage.items():
            log.info("bench: %s against %s: %.4g s each + %.3f s, R² = %.4f", st, axis, a, c, r2)
    write_csv(rows, out / "bench.csv")
    md = out / "bench.md"
    md.write_text(markdown(rows, header, names_by_group, fits, figures))
    return md


def _resolve(
    variants: list[Variant], specs: dict[str, CaptureSpec], out: Path
) -> tuple[dict[str, Path], dict[str, str]]:
    """(capture name -> folder) for the captures the grid uses; real ones that are absent
    go to the second dict with the reason."""
    paths, skipped = {}, {}
    for name in dict.fromkeys(v.capture for v in variants):
        if name not in specs:
            raise BlunfError(f"bench: unknown capture {name!r} (known: {', '.join(specs)})")
        path = specs[name].make(out)
        if specs[name].real and not Path(path).is_dir():
            skipped[name] = f"{path} absent (real capture {name!r})"
            continue
        paths[name] = Path(path)
    return paths, skipped


def _ratios(rows: list[dict], variants: list[Variant]) -> None:
    """ref_ratio = stage_s over that of the first reference of the same group, capture and
    frame budget (measured in the same bench)."""
    refs: dict[tuple, dict] = {}
    for r, v in zip(rows, variants, strict=True):
        if v.reference and "stage_s" in r:
            refs.setdefault((v.group, v.capture, v.frames), r)
    for r, v in zip(rows, variants, strict=True):
        ref = refs.get((v.group, v.capture, v.frames))
        if ref is not None and "stage_s" in r and ref["stage_s"] > 0:
            r["ref_ratio"] = round(r["stage_s"] / ref["stage_s"], 3)


def _error_name(spec: str) -> str:
    if spec.startswith("100-"):
        return ERROR_NAMES["100-"].format(m=spec.rsplit(".", 1)[-1])
    return ERROR_NAMES.get(spec, spec)

"""`blunf bench --scale`: the cost curve, each stage's seconds, CPU-s and memory against views.

The same procedural scene (one room, `stages.synth.make.make_room`, or a home of N rooms,
`stages.synth.home.make_home`) is rendered at each view count with the same seed and size,
and the pipeline runs once on each, from an empty run folder, in a child process of its own
(`pipeline.bench.child`) on one thread, so the figures of one bench compare. By default the
captures carry sensor depth and poses; `photos_only` keeps the images only (SfM path).

How each figure is measured (per stage, per view count):
- seconds, CPU-s: the runner's own (report.json `seconds`, the stage's meta.json
  `cpu_seconds`: CPU of every thread of the process while the stage ran).
- user CPU-s: of that, the CPU outside the kernel (meta.json `cpu_user_seconds`). The rest
  is mostly the kernel zeroing fresh pages, which grows faster than the arrays once they
  pass glibc's mmap threshold (docs/scale.md): the work's own slope is the user one.
- peak MB: the process's resident high-water mark while the stage ran (the runner hands the
  heap's free pages back and resets the kernel's mark, VmHWM, as each stage starts:
  report.json `peak_rss_mb`; stages/common/heap.py).
- added MB: that peak less the resident size as the stage started (recorded by the child
  process). What earlier stages left resident (imports, arrays still held) is in the peak
  but not in what the stage added; the slope of memory is fitted to the latter.
Slopes: least-squares slope of log(figure) against log(views) over the view counts from the
second smallest up (60, 120, 240, 480: from 120 to 480; two counts: between them). A figure
below FLOOR somewhere in that range has no slope (noise, not a cost).

Writes into `out`: scale.json (every figure, the slopes, how they were taken), scale.md (the
tables), scale.svg (log-log plot), reports/v<N>.json and logs/v<N>.log of each run.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.bench.analysis import linear_fit, pyplot
from pipeline.bench.measure import child_run, timestamp
from stages.common.errors import BlunfError
from stages.common.io import read_json, write_json

log = logging.getLogger(__name__)

VIEWS = (60, 120, 240, 480)
FIGURES = ("seconds", "cpu_s", "user_s", "peak_mb", "added_mb")
FLOOR = {"seconds": 0.05, "cpu_s": 0.05, "user_s": 0.05, "peak_mb": 1.0, "added_mb": 4.0}
SHOWN = ("seconds", "cpu_s", "added_mb")  # on the console
LABELS = {
    "seconds": "seconds",
    "cpu_s": "CPU-s",
    "user_s": "user CPU-s",
    "peak_mb": "peak MB",
    "added_mb": "added MB",
}


def make_capture(
    out: Path, views: int, rooms: int, seed: int, size: tuple[int, int], photos_only: bool
) -> Path:
    """The scene at `views` views (reused when already rendered: renders are byte-identical)."""
    out = Path(out)
    if out.is_dir() and any(out.iterdir()):
        return out
    if rooms == 1:
        from stages.synth.make import make_room

        return make_room(out, views=views, seed=seed, size=size, photos_only=photos_only)
    try:
        from stages.synth.home import make_home
    except ImportError as e:
        raise BlunfError(f"--rooms {rooms}: homes are not available in this build ({e})") from None
    return make_home(out, rooms=rooms, views=views, seed=seed, size=size, photos_only=photos_only)


def loglog_slope(x: Sequence[float], y: Sequence[float]) -> float:
    """Least-squares slope of log y against log x (y = c x^k gives k)."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    if not np.all(np.isfinite(ly)):
        raise ValueError("a slope needs two distinct x and positive y")
    return linear_fit(lx, ly)[0]


def fit_range(views: Sequence[int]) -> list[int]:
    """The view counts the slopes are fitted over: all but the smallest when there are 3+."""
    v = sorted(views)
    return v[1:] if len(v) >= 3 else v


def stage_figures(report: dict, run_dir: Path, rss_start: Sequence) -> dict[str, dict]:
    """{label: {seconds, cpu_s, peak_mb, added_mb}} of the stages that ran in one run. A
    stage run under two implementations (blueprint: blunf and mvr) is labelled stage.impl."""
    ran = [s for s in report["stages"] if s["status"] == "ran"]
    names = [s["name"] for s in ran]
    starts: dict[str, list] = {}
    for name, mb in rss_start:
        starts.setdefault(name, []).append(mb)
    out: dict[str, dict] = {}
    for s in ran:
        label = s["name"] if names.count(s["name"]) == 1 else f"{s['name']}.{s.get('impl', '')}"
        meta = run_dir / s["name"] / str(s["key"]) / "meta.json"
        m = read_json(meta) if meta.is_file() else {}
        cpu, user = m.get("cpu_seconds"), m.get("cpu_user_seconds")
        start = starts.get(s["name"], [None]).pop(0) if starts.get(s["name"]) else None
        peak = s.get("peak_rss_mb")
        out[label] = {
            "seconds": float(s["seconds"]),
            "cpu_s": None if cpu is None else float(cpu),
            "user_s": None if user is None else float(user),
            "peak_mb": None if peak is None else float(peak),
            "added_mb": None if peak is None or start is None else round(peak - start, 1),
        }
    return out


def slopes(runs: list[dict], views: Sequence[int]) -> dict[str, dict[str, float | None]]:
    """{stage: {figure: slope or None}} over fit_range(views) (see the module's docstring)."""
    fit = fit_range(views)
    by_v = {r["views"]: r for r in runs}
    stages = list(dict.fromkeys(k for r in runs for k in r["stages"]))
    res: dict[str, dict[str, float | None]] = {}
    for st in [*stages, "run"]:
        res[st] = {}
        for f in FIGURES:
            ys = [_figure(by_v.get(v), st, f) for v in fit]
            ok = all(y is not None and y >= FLOOR[f] for y in ys) and len(fit) >= 2
            res[st][f] = round(loglog_slope(fit, ys), 3) if ok else None  # type: ignore[arg-type]
    return res


def _figure(run: dict | None, stage: str, fig: str) -> float | None:
    if run is None:
        return None
    if stage == "run":
        return run.get({"seconds": "wall_s", "peak_mb": "peak_mb"}.get(fig, fig))
    return run["stages"].get(stage, {}).get(fig)


def scale_bench(
    out: Path,
    views: Sequence[int] = VIEWS,
    rooms: int = 1,
    seed: int = 0,
    size: tuple[int, int] = (320, 240),
    photos_only: bool = False,
    threads: int = 1,
    config: Path | None = None,
    sets: Sequence[str] = (),
    keep_runs: bool = False,
) -> dict:
    """Render, run and measure each view count; write scale.json / .md / .svg into `out`."""
    views = sorted(set(int(v) for v in views))
    if not views or views[0] < 2:
        raise BlunfError(f"--views: at least one count, each >= 2, got {list(views)}")
    if not 1 <= rooms <= 5:
        raise BlunfError(f"--rooms must be in 1..5, got {rooms}")
    out = Path(out)
    for sub in ("captures", "runs", "reports", "logs"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    w, h = size
    tag = f"rooms{rooms}-seed{seed}-{w}x{h}" + ("-photos" if photos_only else "")
    all_sets = [f"run.threads={threads}", f"poses.threads={threads}", *sets]
    head = {
        "started": timestamp(),
        "views": views,
        "rooms": rooms,
        "seed": seed,
        "size": [w, h],
        "photos_only": photos_only,
        "threads": threads,
        "config": None if config is None else str(config),
        "sets": all_sets,
        "cores": len(os.sched_getaffinity(0)),
        "load_average_at_start": round(os.getloadavg()[0], 2),
        "fit_views": fit_range(views),
        "how": __doc__.split("How each figure is measured", 1)[1].split("Writes into")[0].strip(),
    }
    runs = []
    for n in views:
        cap = make_capture(out / "captures" / f"{tag}-v{n}", n, rooms, seed, size, photos_only)
        run_dir = out / "runs" / f"v{n}"
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        log.info("bench --scale: %d views (%s)", n, cap)
        res = child_run(cap, run_dir, all_sets, threads, out / "logs" / f"v{n}.log", config)
        if not res.get("ok"):
            raise BlunfError(f"bench --scale: the {n}-view run failed: {res.get('error')}")
        rep = read_json(run_dir / "report.json")
        shutil.copyfile(run_dir / "report.json", out / "reports" / f"v{n}.json")
        st = stage_figures(rep, run_dir, res.get("rss_start_mb", []))
        peaks = [s["peak_mb"] for s in st.values() if s["peak_mb"] is not None]
        runs.append(
            {
                "views": n,
                "wall_s": round(float(res["wall_s"]), 3),
                "cpu_s": round(float(res["cpu_s"]), 3),
                "user_s": None if res.get("user_s") is None else round(float(res["user_s"]), 3),
                "peak_mb": max(peaks) if peaks else None,
                "stages": st,
            }
        )
        if not keep_runs:
            shutil.rmtree(run_dir, ignore_errors=True)
    result = {**head, "runs": runs, "slopes": slopes(runs, views)}
    write_json(out / "scale.json", result)
    (out / "scale.md").write_text(markdown(result))
    plot(result, out / "scale.svg")
    return result


def markdown(r: dict) -> str:
    """One table per figure: a row per stage, a column per view count, then the slope."""
    views = r["views"]
    fit = r["fit_views"]
    lines = [
        f"# Cost against views ({r['rooms']} room(s), {r['size'][0]}x{r['size'][1]}, seed "
        f"{r['seed']}, {'photos only' if r['photos_only'] else 'sensor depth and poses'})",
        "",
        f"{r['started']}; {r['threads']} thread(s) a run, {r['cores']} cores, load average "
        f"{r['load_average_at_start']} at start. Slopes: log-log, views {fit[0]}-{fit[-1]}.",
    ]
    by_v = {x["views"]: x for x in r["runs"]}
    stages = list(r["slopes"])
    for f in FIGURES:
        lines += ["", f"## {LABELS[f]}", ""]
        lines.append("| stage | " + " | ".join(str(v) for v in views) + " | slope |")
        lines.append("|---" * (len(views) + 2) + "|")
        for st in stages:
            vals = [_figure(by_v[v], st, f) for v in views]
            if all(x is None for x in vals):
                continue
            k = r["slopes"][st][f]
            cells = ["-" if x is None else f"{x:.4g}" for x in vals]
            slope = "-" if k is None else f"{k:.2f}"
            lines.append(f"| {st} | " + " | ".join(cells) + f" | {slope} |")
    lines += ["", "How: " + " ".join(r["how"].split()), ""]
    return "\n".join(lines)


def plot(r: dict, path: Path) -> Path:
    """Seconds, CPU-s and added memory against views, log-log, a dotted line of slope 1."""
    plt = pyplot()
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    views = np.asarray(r["views"], float)
    by_v = {x["views"]: x for x in r["runs"]}
    for ax, f in zip(axes, ("seconds", "cpu_s", "added_mb"), strict=True):
        for i, st in enumerate(r["slopes"]):
            ys = [_figure(by_v[int(v)], st, f) for v in views]
            pts = [(v, y) for v, y in zip(views, ys, strict=True) if y is not None and y > 0]
            if len(pts) < 2:
                continue
            k = r["slopes"][st][f]
            name = st if k is None else f"{st} (slope {k:.2f})"
            x, y = zip(*pts, strict=True)
            ax.plot(x, y, "o-", color=f"C{i % 10}", lw=1.2, ms=4, label=name)
        ref = views / views[0]
        top = ax.get_ylim()[1] if ax.lines else 1.0
        ax.plot(views, top * 0.5 * ref / ref[-1], ":", color="grey", label="slope 1")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(views, [str(int(v)) for v in views])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("views")
        ax.set_ylabel(LABELS[f])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6.5)
    fig.suptitle(
        f"cost against views: {r['rooms']} room(s), {r['size'][0]}x{r['size'][1]}, "
        f"{'photos only' if r['photos_only'] else 'sensor depth and poses'}, "
        f"{r['threads']} thread(s)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, format="svg")
    plt.close(fig)
    return Path(path)


def table(r: dict) -> str:
    """The console summary: seconds and added MB per stage per view count, and the slopes."""
    views = r["views"]
    by_v = {x["views"]: x for x in r["runs"]}
    head = f"{'stage':<16}" + "".join(f"{v:>16}" for v in views) + f"{'slope s/CPU/MB':>20}"
    rows = [head, f"{'':<16}" + "".join(f"{'s CPU-s MB+':>16}" for _ in views)]
    for st, k in r["slopes"].items():
        cells = []
        for v in views:
            s, c, m = (_figure(by_v[v], st, f) for f in SHOWN)
            cells.append(f"{_n(s)} {_n(c)} {_n(m)}".rjust(16))
        ks = "/".join(
            "-" if k[f] is None else f"{k[f]:.2f}" for f in ("seconds", "cpu_s", "added_mb")
        )
        rows.append(f"{st:<16}" + "".join(cells) + f"{ks:>20}")
    return "\n".join(rows)


def _n(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}" if abs(x) < 100 else f"{x:.0f}"

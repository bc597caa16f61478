"""Summary of a batch of runs: `python -m pipeline.summary RUNS_DIR` → summary.csv, index.html."""

from __future__ import annotations

import csv
import html
import json
import sys
from pathlib import Path

COLUMNS = [
    "scene",
    "ok",
    "seconds_total",
    "stages_ran",
    "stages_cached",
    "stages_skipped",
    "blunf_fwiou",
    "blunf_pacc",
    "mvr_fwiou",
    "ate_rmse_m",
    "components",
    "error",
    "log",
]


def row(run: Path) -> dict:
    """One run folder's line of the summary (ok = a report with an exported plan)."""
    rep_path = run / "report.json"
    log = run.parent / f"{run.name}.log"
    r: dict = {"scene": run.name, "ok": False, "log": str(log) if log.exists() else ""}
    if not rep_path.is_file():
        return r
    rep = json.loads(rep_path.read_text())
    st = [s["status"] for s in rep.get("stages", [])]
    bp = rep.get("metrics", {}).get("blueprint", {})
    r.update(
        {
            "ok": (run / "blueprint.png").is_file() and "blueprint.png" in rep.get("outputs", {}),
            "seconds_total": rep.get("seconds_total"),
            "stages_ran": st.count("ran"),
            "stages_cached": st.count("cached"),
            "stages_skipped": st.count("skipped"),
            "blunf_fwiou": bp.get("blunf", {}).get("fwiou"),
            "blunf_pacc": bp.get("blunf", {}).get("pacc"),
            "mvr_fwiou": bp.get("mvr", {}).get("fwiou"),
            "ate_rmse_m": rep.get("metrics", {}).get("poses", {}).get("ate_rmse_m"),
            "components": len(rep.get("plan", {}).get("components", [])),
        }
    )
    return r


def summarise(
    runs_dir: Path, errors: dict[str, str] | None = None, scenes: list[str] | None = None
) -> tuple[Path, Path]:
    """summary.csv and index.html over the run folders in `runs_dir` and `scenes` (runs that
    may have failed before making their folder); `errors`: scene -> its one-line error."""
    runs_dir = Path(runs_dir)
    errors = errors or {}
    names = {p.name for p in runs_dir.iterdir() if p.is_dir() and not p.name.startswith(".")}
    rows = [row(runs_dir / n) for n in sorted(names | set(scenes or ()))]
    for r in rows:
        if r["scene"] in errors:  # this batch's word beats a report left by an earlier run
            r.update(ok=False, error=errors[r["scene"]])
    csv_path, html_path = runs_dir / "summary.csv", runs_dir / "index.html"
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows({k: r.get(k, "") for k in COLUMNS} for r in rows)
    cells = []
    for r in rows:
        name = html.escape(r["scene"])
        img = f'<img src="{name}/blueprint.png" alt="{name}">' if r["ok"] else "<p>failed</p>"
        facts = "".join(
            f"<li>{html.escape(k)}: {html.escape(str(r.get(k, '')))}</li>"
            for k in COLUMNS[1:]
            if r.get(k) not in (None, "")
        )
        page = runs_dir / r["scene"] / "report.html"  # the run's own page, when it has one
        title = f'<a href="{name}/report.html">{name}</a>' if page.exists() else name
        cells.append(f'<div class="run"><h2>{title}</h2>{img}<ul>{facts}</ul></div>')
    html_path.write_text(
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>blunf batch</title><style>"
        "body{font-family:sans-serif}.run{display:inline-block;vertical-align:top;margin:1em;"
        "max-width:480px}img{max-width:100%}</style></head><body><h1>blunf batch</h1>"
        + "".join(cells)
        + "</body></html>\n"
    )
    return csv_path, html_path


if __name__ == "__main__":
    if len(sys.argv) != 2 or not Path(sys.argv[1]).is_dir():
        print("usage: python -m pipeline.summary RUNS_DIR", file=sys.stderr)
        sys.exit(2)
    for p in summarise(Path(sys.argv[1])):
        print(p)

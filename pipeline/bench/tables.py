"""bench.csv (every measure and metric of every variant) and bench.md (tables, Pareto points,
cost fits)."""

from __future__ import annotations

import csv
from pathlib import Path

# the first columns of bench.csv, in this order; then seconds.<stage> and cpu.<stage>, then
# every flattened report.json metric (blueprint.blunf.fwiou, poses.ate_rmse_m, ...)
FIELDS = [
    "variant",
    "group",
    "capture",
    "frames",
    "width",
    "height",
    "pixels",
    "reference",
    "cost",
    "sets",
    "repeats",
    "failed",
    "note",
    "wall_s",
    "wall_s_min",
    "wall_s_max",
    "cpu_s",
    "peak_rss_mb",
    "stage_s",
    "ref_ratio",
    "error",
    "pareto",
]


def columns(rows: list[dict]) -> list[str]:
    """FIELDS, then the stage timings, then the metrics (sorted), as they occur in rows."""
    keys = {k for r in rows for k in r} - set(FIELDS)
    timing = sorted(k for k in keys if k.startswith(("seconds.", "cpu.")))
    return FIELDS + timing + sorted(keys - set(timing))


def write_csv(rows: list[dict], path: Path) -> None:
    cols = columns(rows)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in cols})


def _fmt(v: object, nd: int = 3) -> str:
    """Numbers with `nd` decimals (trailing zeros dropped), large ones with nd digits."""
    if isinstance(v, float):
        if abs(v) >= 1000 or nd == 0:
            return f"{v:.0f}"
        t = f"{v:.{nd}f}"
        return t.rstrip("0").rstrip(".") if "." in t else t
    return "" if v is None else str(v)


def markdown(
    rows: list[dict],
    header: list[str],
    error_names: dict[str, str],
    fits: dict[str, dict[str, tuple]],
    figures: list[Path],
) -> str:
    """The report: one table per group, its Pareto points, the cost fits, the figures."""
    lines = ["# blunf bench", "", *header, ""]
    for group in dict.fromkeys(r["group"] for r in rows):
        g = [r for r in rows if r["group"] == group]
        lines += [
            f"## {group}",
            "",
            f"stage s = median seconds of the stages under study; x ref = that over the "
            f"reference's; error = {error_names.get(group, 'error')}.",
            "",
            "| variant | capture | frames | size | runs | stage s | x ref | wall s | cpu s |"
            " peak MB | error | Pareto |",
            "|" + "---|" * 12,
        ]
        for r in g:
            size = f"{r['width']}x{r['height']}" if r.get("width") else ""
            ratio = r.get("ref_ratio", "")
            ref = "ref" if r.get("reference") else f"{ratio:.3g}" if ratio != "" else ""
            cells = [
                r["variant"] + (f" ({r['note']})" if r.get("note") else ""),
                r["capture"],
                _fmt(r.get("frames")),
                size,
                f"{r.get('repeats', 0)}" + (f" ({r['failed']} failed)" if r.get("failed") else ""),
                _fmt(r.get("stage_s", "")),
                ref,
                _fmt(r.get("wall_s", "")),
                _fmt(r.get("cpu_s", "")),
                _fmt(r.get("peak_rss_mb", ""), 0),
                _fmt(r.get("error", "")),
                "yes" if r.get("pareto") else "",
            ]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
        for cap in dict.fromkeys(r["capture"] for r in g):
            front = sorted(
                (r for r in g if r["capture"] == cap and r.get("pareto")),
                key=lambda r: r["stage_s"],
            )
            if front:
                pts = ", ".join(
                    f"{r['variant']} ({_fmt(r['stage_s'])} s, {_fmt(r['error'])})" for r in front
                )
                lines += [f"Pareto front on {cap}: {pts}.", ""]
    for axis, per_stage in fits.items():
        if not per_stage:
            continue
        lines += [
            f"## Cost against {axis}",
            "",
            "| stage | sizes | seconds | fit | R² | fitted change over the sweep |",
            "|---|---|---|---|---|---|",
        ]
        for st, (x, y, (a, b, r2)) in sorted(per_stage.items()):
            xs = ", ".join(_fmt(float(v), 6) for v in x)
            ys = ", ".join(_fmt(float(v)) for v in y)
            lo, hi = a * min(x) + b, a * max(x) + b
            change = f"{100 * (hi - lo) / lo:+.0f} %" if lo > 0 else ""
            fit = f"{a:.4g} s/{axis[:-1]} + {b:.3f} s"
            lines.append(f"| {st} | {xs} | {ys} | {fit} | {r2:.4f} | {change} |")
        lines += [
            "",
            "R² is low for a stage whose cost does not grow with the size (a flat line fits "
            "noise); the last column tells the two apart.",
            "",
        ]
    if figures:
        lines += ["## Figures", "", *(f"- {p.name}" for p in figures), ""]
    return "\n".join(lines)

"""What the bench draws: Pareto fronts of time against error, linear fits of cost against size.

Plots use matplotlib's Agg backend (files only, no display).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point dominates, both coordinates to be minimised,
    ordered by x. A point is dominated by one that is <= on both and < on at least one;
    equal points do not dominate each other (both stay)."""
    p = [(float(x), float(y)) for x, y in points]
    keep = [
        i
        for i, (x, y) in enumerate(p)
        if not any(a <= x and b <= y and (a < x or b < y) for a, b in p)
    ]
    return sorted(keep, key=lambda i: (p[i][0], p[i][1]))


def linear_fit(x: Sequence[float], y: Sequence[float]) -> tuple[float, float, float]:
    """Least-squares line y = a x + b over >= 2 points. Returns (a, b, R²); R² = 1 - SS_res /
    SS_tot (1 when y is constant and fitted exactly)."""
    xa, ya = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if len(xa) < 2 or np.ptp(xa) == 0:
        raise ValueError("a line needs at least two distinct x")
    a, b = np.polyfit(xa, ya, 1)
    res = float(((ya - (a * xa + b)) ** 2).sum())
    tot = float(((ya - ya.mean()) ** 2).sum())
    r2 = 1.0 - res / tot if tot > 0 else (1.0 if res <= 1e-24 else 0.0)
    return float(a), float(b), r2


def pyplot():  # noqa: ANN202 (matplotlib's pyplot module)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _num(v: object) -> float | None:
    if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return None


def fronts(rows: list[dict]) -> dict[tuple[str, str], list[dict]]:
    """(group, capture) -> its rows with a time and an error, Pareto rows flagged `pareto`;
    a capture with one such row in a group (a point of a size sweep) has no front."""
    out: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if _num(r.get("stage_s")) is not None and _num(r.get("error")) is not None:
            out.setdefault((r["group"], r["capture"]), []).append(r)
    out = {k: pts for k, pts in out.items() if len(pts) >= 2}
    for pts in out.values():
        front = set(pareto_front([(max(r["stage_s"], 1e-6), r["error"]) for r in pts]))
        for i, r in enumerate(pts):
            r["pareto"] = int(i in front)
    return out


def plot_fronts(
    groups: dict[tuple[str, str], list[dict]], error_names: dict[str, str], folder: Path
) -> list[Path]:
    """One figure per (group, capture) of `fronts(rows)`: stage seconds (log x) against
    error, every variant a point (references as squares), the Pareto front drawn and its
    points labelled."""
    plt = pyplot()
    files = []
    for (group, capture), pts in sorted(groups.items()):
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for r in pts:
            ax.scatter(
                r["stage_s"],
                r["error"],
                marker="s" if r["reference"] else "o",
                color="tab:red" if r["pareto"] else "tab:gray",
                zorder=3,
            )
        front = sorted((r for r in pts if r["pareto"]), key=lambda r: r["stage_s"])
        xs = [max(r["stage_s"], 1e-6) for r in front]
        ys = [r["error"] for r in front]
        ax.step(xs, ys, where="post", color="tab:red", lw=1, zorder=2)
        for r in front:
            ax.annotate(
                r["variant"],
                (r["stage_s"], r["error"]),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
            )
        ax.set_xscale("log")
        ax.set_xlabel(f"{group} seconds (median; log scale)")
        ax.set_ylabel(error_names.get(group, "error"))
        ax.set_title(f"{group} on {capture}: time against error (red: Pareto front)")
        ax.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        path = Path(folder) / f"pareto-{group}-{capture}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files.append(path)
    return files


def cost_fits(rows: list[dict], axis: str, stages: Sequence[str]) -> dict[str, tuple]:
    """stage -> (x [n], seconds [n], (slope, intercept, R²)) over the rows of the `axis` sweep
    ("frames" or "pixels"); stages with fewer than two distinct sizes are left out."""
    sweep = [r for r in rows if r.get("cost") == axis]
    out = {}
    for st in stages:
        pts = [(_num(r.get(axis)), _num(r.get(f"seconds.{st}"))) for r in sweep]
        pts = [(x, y) for x, y in pts if x is not None and y is not None]
        if len({x for x, _ in pts}) >= 2:
            x, y = zip(*sorted(pts), strict=True)
            out[st] = (list(x), list(y), linear_fit(x, y))
    return out


def plot_cost(fits: dict[str, tuple], axis: str, folder: Path) -> Path | None:
    """Seconds against frames (or pixels) per stage, with the fitted line and its R²."""
    if not fits:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (st, (x, y, (a, b, r2))) in enumerate(sorted(fits.items())):
        c = f"C{i}"
        ax.scatter(x, y, color=c, zorder=3)
        xs = np.linspace(0, max(x), 50)
        ax.plot(
            xs,
            a * xs + b,
            color=c,
            lw=1,
            label=f"{st}: {a:.3g} s/{axis[:-1]} + {b:.2f} s, R² = {r2:.3f}",
        )
    ax.set_xlabel(axis if axis == "frames" else "pixels per image")
    ax.set_ylabel("seconds (median)")
    ax.set_title(f"cost against {axis}")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    path = Path(folder) / f"cost-{axis}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

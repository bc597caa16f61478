"""The rows of `blunf bench --targets` and their files: targets.md, targets.csv, targets.json.

A row is one bar of one speed target: the figure, the reference it is read against (measured
in the same bench, or the target's budget when nothing natural is measured alongside), their
ratio, pass or fail against the bar, the wall and CPU seconds behind the figure, and the
command that reproduces it. A row that could not be measured keeps its reason instead.
"""

from __future__ import annotations

import csv
import json
import operator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

BUDGET = "budget"  # the reference of a row with no measured one: the target's own bar
_OPS = {"<=": operator.le, ">=": operator.ge}


@dataclass(frozen=True)
class Bar:
    """What a target asks: `on` ("figure" or "ratio") `op` ("<=" or ">=") `limit`."""

    on: str
    op: str
    limit: float

    def __post_init__(self) -> None:
        if self.on not in ("figure", "ratio") or self.op not in _OPS:
            raise ValueError(f"bar {self.on} {self.op} {self.limit}: on figure|ratio, op <=|>=")

    def text(self, unit: str) -> str:
        return f"{'ratio' if self.on == 'ratio' else ''} {self.op} {_num(self.limit)}" + (
            f" {unit}" if self.on == "figure" and unit else ""
        )


@dataclass
class Row:
    """One bar of one target (see the module doc)."""

    target: str  # "1a", "5b", ...: the target's number in the speed list, and which bar
    text: str  # the target, short
    unit: str  # of the figure and the reference ("s", "MB", "" for a score)
    bar: Bar
    command: str  # the command(s) that reproduce the figure
    figure: float | None = None
    reference: float | None = None  # None with a budget row: the bar's limit is used
    ref_name: str = BUDGET  # what the reference is: BUDGET or the measured thing
    wall_s: float | None = None  # wall seconds behind the figure (the run, stage or render)
    cpu_s: float | None = None  # CPU seconds of the same (steadier on a shared machine)
    note: str = ""
    skipped: str = ""  # why there is no figure ("" when measured)

    @property
    def ref_value(self) -> float | None:
        return self.bar.limit if self.ref_name == BUDGET else self.reference

    @property
    def ratio(self) -> float | None:
        """figure / reference, None when either is missing or the reference is 0."""
        ref = self.ref_value
        if self.figure is None or ref is None or ref == 0:
            return None
        return self.figure / ref

    @property
    def verdict(self) -> str:
        """ "pass" | "FAIL" | "" (no figure, or a ratio bar without a ratio)."""
        v = self.ratio if self.bar.on == "ratio" else self.figure
        if self.skipped or v is None:
            return ""
        return "pass" if _OPS[self.bar.op](v, self.bar.limit) else "FAIL"

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        bar = d.pop("bar")
        d["bar"] = f"{bar['on']} {bar['op']} {bar['limit']}"
        d["reference"] = self.ref_value
        d["ratio"] = None if self.ratio is None else round(self.ratio, 4)
        d["verdict"] = self.verdict
        return d


FIELDS = (
    "target",
    "text",
    "figure",
    "unit",
    "reference",
    "ref_name",
    "ratio",
    "bar",
    "verdict",
    "wall_s",
    "cpu_s",
    "command",
    "note",
    "skipped",
)


def _num(v: float | None, nd: int = 3) -> str:
    """3 significant decimals, trailing zeros dropped; whole numbers from 1000 on."""
    if v is None:
        return ""
    if abs(v) >= 1000:
        return f"{v:.0f}"
    t = f"{v:.{nd}f}".rstrip("0").rstrip(".")
    return t if t not in ("", "-0") else "0"


def markdown(rows: list[Row], header: list[str], runs: list[str]) -> str:
    """targets.md: the table, then where the time went in each run."""
    lines = ["# blunf speed targets", "", *header, ""]
    lines += [
        "| # | target | figure | reference | ratio | bar | result | wall s | CPU s | command |",
        "|" + "---|" * 10,
    ]
    for r in rows:
        fig = f"{_num(r.figure)} {r.unit}".strip() if r.figure is not None else ""
        if r.skipped:
            fig = f"not measured: {r.skipped}"
        ref = _num(r.ref_value)
        ref = f"{ref} {r.unit} ({r.ref_name})".replace("  ", " ") if ref else ""
        ratio = "" if r.ratio is None else f"{r.ratio:.3g}"
        text = r.text + (f" ({r.note})" if r.note else "")
        cells = [r.target, text, fig, ref, ratio, r.bar.text(r.unit).strip(), r.verdict]
        cells += [_num(r.wall_s, 2), _num(r.cpu_s, 2), f"`{r.command}`"]
        lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    lines += ["", "ratio = figure / reference. Budget rows read the figure against the bar."]
    if runs:
        lines += ["", "## Where the time went", "", *runs]
    return "\n".join(lines) + "\n"


def write(rows: list[Row], header: list[str], runs: list[str], extra: dict, out: Path) -> Path:
    """targets.md, targets.csv and targets.json (rows, header, `extra`) into out; returns
    the path of targets.md."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    dicts = [r.as_dict() for r in rows]
    with open(out / "targets.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for d in dicts:
            w.writerow({k: "" if d.get(k) is None else d[k] for k in FIELDS})
    doc = {"header": header, "rows": dicts, **extra}
    (out / "targets.json").write_text(json.dumps(doc, indent=1, default=str) + "\n")
    md = out / "targets.md"
    md.write_text(markdown(rows, header, runs))
    return md

"""`blunf bench --targets`: the table's ratios, verdicts and skipped rows on hand-made rows,
and one real target row (the project stage on a tiny room) end to end."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest

from pipeline.bench.measure import Sample
from pipeline.bench.target_runs import Measured, Session, timed_command
from pipeline.bench.target_table import BUDGET, Bar, Row, write
from pipeline.bench.targets import parse_only, target_7, target_8, worst_view
from pipeline.cli import main
from stages.common.errors import BlunfError


def test_rows_ratio_verdict_budget_and_skip(tmp_path: Path):
    measured = Row(
        "5a", "edited view", "s", Bar("figure", "<=", 1.0), "cmd a", figure=0.5, wall_s=0.5,
        cpu_s=0.9, reference=2.0, ref_name="volume render",
    )  # fmt: skip
    ratio_bar = Row(
        "6a", "SfM time", "s", Bar("ratio", "<=", 0.5), "cmd b", figure=30.0, reference=50.0,
        ref_name="pycolmap",
    )  # fmt: skip
    budget = Row("7", "project stage", "s", Bar("figure", "<=", 5.0), "cmd c", figure=6.0)
    score = Row("1b", "fwIoU", "", Bar("figure", ">=", 84), "cmd d", figure=84.0)
    gone = Row("2", "kitchen", "s", Bar("figure", "<=", 300), "cmd e", skipped="/x absent")
    # 0.5 / 2.0; 30 / 50 = 0.6 > 0.5 fails though the figure alone is small; a budget row's
    # reference is its bar (6 / 5 = 1.2, over it); 84 >= 84 holds; a skipped row has neither
    assert measured.ratio == pytest.approx(0.25) and measured.verdict == "pass"
    assert ratio_bar.ratio == pytest.approx(0.6) and ratio_bar.verdict == "FAIL"
    assert budget.ref_name == BUDGET and budget.ref_value == 5.0
    assert budget.ratio == pytest.approx(1.2) and budget.verdict == "FAIL"
    assert score.ratio == pytest.approx(1.0) and score.verdict == "pass"
    assert gone.ratio is None and gone.verdict == ""
    zero = Row("x", "x", "s", Bar("figure", "<=", 1), "c", figure=1.0, reference=0.0, ref_name="m")
    assert zero.ratio is None and zero.verdict == "pass"  # no division by a zero reference

    md = write([measured, ratio_bar, budget, score, gone], ["head"], ["- run a: 1 s"], {}, tmp_path)
    lines = md.read_text().splitlines()
    row = {ln.split(" | ")[0].strip("| "): ln for ln in lines if ln.startswith("| ")}
    want = "| 0.5 s | 2 s (volume render) | 0.25 | <= 1 s | pass | 0.5 | 0.9 | `cmd a` |"
    assert want in row["5a"]
    assert "| 6 s | 5 s (budget) | 1.2 | <= 5 s | FAIL |" in row["7"]
    assert "| 30 s | 50 s (pycolmap) | 0.6 | ratio <= 0.5 | FAIL |" in row["6a"]
    assert "not measured: /x absent" in row["2"] and "`cmd e`" in row["2"]
    assert "- run a: 1 s" in lines
    rows = list(csv.DictReader(open(tmp_path / "targets.csv")))
    assert [r["verdict"] for r in rows] == ["pass", "FAIL", "FAIL", "pass", ""]
    assert rows[2]["reference"] == "5.0" and rows[2]["ref_name"] == "budget"
    assert rows[4]["skipped"] == "/x absent" and rows[4]["figure"] == ""
    doc = json.loads((tmp_path / "targets.json").read_text())
    assert doc["header"] == ["head"] and doc["rows"][1]["ratio"] == pytest.approx(0.6)


def test_only_list_and_its_errors(tmp_path: Path, capsys):
    assert parse_only("7, 1,5") == (1, 5, 7) and parse_only(None) == tuple(range(1, 9))
    for bad in ("1,x", "9", ","):
        with pytest.raises(BlunfError, match="--only"):
            parse_only(bad)
    # the command: one line, exit 2, nothing measured
    assert main(["bench", "--targets", "--only", "0", "--out", str(tmp_path / "t")]) == 2
    assert main(["bench", "--only", "1", "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("blunf: error: --only") for e in err)
    assert not (tmp_path / "t").exists() and not (tmp_path / "b").exists()


def test_timed_command_counts_the_child_cpu_and_memory(tmp_path: Path):
    # the child spins ~0.3 s of CPU and holds ~200 MB: both show in the kernel's account
    code = "import time; b = bytearray(200 << 20); t = time.process_time()\n"
    code += "while time.process_time() - t < 0.3: b[0] = 1"
    r = timed_command([sys.executable, "-c", code], tmp_path / "log", {}, 60)
    assert r["error"] == "" and r["cpu_s"] >= 0.25 and r["wall_s"] >= r["cpu_s"] * 0.9
    assert 200 <= r["peak_mb"] < 400
    r = timed_command([sys.executable, "-c", "raise SystemExit(3)"], tmp_path / "log", {}, 60)
    assert r["error"].startswith("exit 3")
    r = timed_command([sys.executable, "-c", "import time; time.sleep(60)"], tmp_path / "l", {}, 1)
    assert r["error"] == "timed out after 1 s" and 1 <= r["wall_s"] < 30  # killed at its limit


def test_project_target_row_end_to_end(tmp_path: Path):
    """Target 7 on an 8-view 64x48 room: the warm-up builds the stages before `project`, the
    timed run reruns it; the row has its seconds, CPU, command and verdict, and target 8
    reads that run's peak memory."""
    s = Session(tmp_path / "t", quick=True, repeats=1, threads=1)
    (row,) = target_7(s, views=8, size=(64, 48), sets=("fusion.voxel=0.05",))
    assert row.skipped == "", row.skipped
    assert row.figure is not None and 0 < row.figure < 5.0 and row.verdict == "pass"
    assert row.cpu_s is not None and row.cpu_s > 0 and row.ref_name == BUDGET
    assert "--views 8 --size 64x48" in row.command and "run.methods=mvr" in row.command
    report = json.loads((tmp_path / "t" / "reports" / "project-8-64x48-r0.json").read_text())
    ran = {st["name"]: st for st in report["stages"] if st["status"] == "ran"}
    assert "project" in ran and "fusion" not in ran  # fusion came from the warm cache
    assert row.figure == pytest.approx(ran["project"]["seconds"], abs=1e-3)
    (mem,) = target_8(s)
    assert mem.figure == pytest.approx(max(st["peak_rss_mb"] for st in ran.values()))
    assert mem.verdict == "pass" and "project-8-64x48" in mem.note


def test_worst_view_is_the_lowest_changed_iou_of_any_edit_in_any_view():
    def run(remove: list, recolor: list) -> Measured:
        edits = [
            {"index": 0, "op": "remove", "changed_iou": 0.9, "changed_iou_views": remove},
            {"index": 1, "op": "recolor", "changed_iou": 0.97, "changed_iou_views": recolor},
        ]
        return Measured(Sample(1.0, 1.0, None, {}, {}, {"edit": edits}), {})

    # run 1's lowest is 0.87 (remove, second view = input view 24), run 2's 0.95 (recolor,
    # None skipped), run 3's 0.89: the median of 0.87, 0.95, 0.89 is 0.89
    runs = [
        run([0.91, 0.87, 0.93], [0.97, 0.98, 0.99]),
        run([0.96, None, 0.97], [0.95, 0.98, 0.99]),
        run([0.95, 0.89, 0.92], [0.97, 0.98, 0.99]),
    ]
    low, where = worst_view(runs, (4, 24, 39))
    assert low == pytest.approx(0.89) and where == "edit 0 (remove) in view 24"
    assert worst_view([run([], [])], (4,)) == (None, "")

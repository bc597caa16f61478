"""`blunf bench --scale` (pipeline.bench.curve): the cost curve's table, slopes and files."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from pipeline.bench.curve import FIGURES, fit_range, loglog_slope, markdown, scale_bench, slopes
from pipeline.cli import main
from stages.common.io import read_json

CHEAP = [  # the cheapest settings of every stage: this test checks the table, not the plan
    "run.methods=[mvr]",
    "fusion.voxel=0.1",
    "fusion.raycast=false",
    "project.stride=8",
    "project.cell=0.1",
]


def _run(views: int, law: dict[str, tuple[float, float]], off: float = 1.0) -> dict:
    """A run whose every figure is c * views^k (times `off`: a point off the law)."""
    st = {name: {f: c * views**k * off for f in FIGURES} for name, (c, k) in law.items()}
    return {"views": views, "wall_s": 2.0 * views * off, "cpu_s": 1.0 * views, "peak_mb": None,
            "stages": st}  # fmt: skip


def test_slope_recovers_a_power_law_over_the_range_it_fits() -> None:
    assert loglog_slope([3, 7, 50], [2.5 * x**1.37 for x in (3, 7, 50)]) == pytest.approx(1.37)
    assert fit_range([480, 60, 240, 120]) == [120, 240, 480]  # from 120 to 480
    assert fit_range([8, 16]) == [8, 16]
    law = {"fusion": (0.1, 1.0), "project": (0.001, 2.0), "tiny": (1e-4, 1.0)}
    views = [60, 120, 240, 480]
    # the 60-view point is off its law by 5x: it is not in the fit, so the slopes are exact
    runs = [_run(v, law, off=5.0 if v == 60 else 1.0) for v in views]
    k = slopes(runs, views)
    for f in FIGURES:
        assert k["fusion"][f] == pytest.approx(1.0, abs=1e-3)
        assert k["project"][f] == pytest.approx(2.0, abs=1e-3)
        assert k["tiny"][f] is None  # below the floor somewhere in the range: no slope
    assert k["run"]["seconds"] == pytest.approx(1.0, abs=1e-3)  # the whole run's wall
    assert k["run"]["added_mb"] is None
    # a stage absent at one count has no slope
    del runs[2]["stages"]["fusion"]
    assert slopes(runs, views)["fusion"]["seconds"] is None
    with pytest.raises(ValueError):
        loglog_slope([10, 10], [1.0, 2.0])


def test_scale_bench_tiny_table_and_files(tmp_path) -> None:
    out = tmp_path / "scale"
    r = scale_bench(out, views=[16, 8], size=(64, 48), sets=CHEAP)
    assert r["views"] == [8, 16] and r["fit_views"] == [8, 16]
    assert [x["views"] for x in r["runs"]] == [8, 16]
    on_disk = read_json(out / "scale.json")
    assert on_disk["slopes"] == r["slopes"] and on_disk["threads"] == 1
    for run in r["runs"]:
        assert run["wall_s"] > 0 and run["cpu_s"] > 0 and run["peak_mb"] > 0
        assert 0 < run["user_s"] <= run["cpu_s"] + 0.01
        st = run["stages"]
        for name in ("ingest", "fusion", "project", "blueprint", "layout", "export"):
            assert name in st, name
            f = st[name]
            assert set(f) == set(FIGURES)
            assert f["seconds"] >= 0 and f["cpu_s"] >= 0
            # the user CPU is part of the CPU (the kernel's share is the rest)
            assert 0 <= f["user_s"] <= f["cpu_s"] + 0.01, f
            # what a stage added is within the process's high-water mark during it
            assert 0 < f["peak_mb"] and -1.0 <= f["added_mb"] <= f["peak_mb"]
        assert "poses" not in st and "depth" not in st  # sensor depth and given poses
    assert set(r["slopes"]) == {*r["runs"][0]["stages"], *r["runs"][1]["stages"], "run"}
    # a slope is that of the two points when both are above the floor
    fus = [x["stages"]["fusion"]["seconds"] for x in r["runs"]]
    assert r["slopes"]["fusion"]["seconds"] == pytest.approx(loglog_slope([8, 16], fus), abs=1e-3)
    md = (out / "scale.md").read_text()
    assert md == markdown(r) and "| fusion |" in md and "## added MB" in md
    assert "## user CPU-s" in md
    assert ET.parse(out / "scale.svg").getroot().tag.endswith("svg")
    assert sorted(p.name for p in (out / "reports").iterdir()) == ["v16.json", "v8.json"]
    assert not any((out / "runs").iterdir())  # run folders are not kept by default


def test_scale_bench_bad_arguments_fail_in_one_line(tmp_path, capsys) -> None:
    assert main(["bench", "--scale", "--views", "8,x", "--out", str(tmp_path)]) == 2
    assert "--views" in capsys.readouterr().err
    assert main(["bench", "--scale", "--views", "1", "--out", str(tmp_path)]) == 2
    assert main(["bench", "--scale", "--rooms", "9", "--out", str(tmp_path / "r")]) == 2
    assert "--rooms must be in 1..5" in capsys.readouterr().err
    assert main(["bench", "--set", "fusion.voxel=0.1", "--out", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists()


def test_matching_bench_refuses_unknown_kinds_before_any_work(tmp_path, capsys) -> None:
    from pipeline.bench.matching import main as matching_main

    out = tmp_path / "m"
    assert matching_main([str(tmp_path), "--out", str(out), "--kinds", "sequential,vocab"]) == 2
    assert "vocab" in capsys.readouterr().err and not out.exists()

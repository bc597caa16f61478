"""The bench: a tiny grid end to end, the Pareto front and the linear fit on hand-made data."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from pipeline.bench import CaptureSpec, Variant, bench
from pipeline.bench.analysis import linear_fit, pareto_front
from pipeline.bench.grid import full_grid, quick_grid, synthetic
from pipeline.bench.measure import error_of, flatten
from pipeline.bench.tables import FIELDS


def test_pareto_front_drops_exactly_the_dominated_points():
    # (seconds, error). Worked out by hand, both to be minimised:
    #   0 (1, 9)   nothing is faster: front
    #   1 (2, 5)   only 0 is faster, and it is worse: front
    #   2 (3, 5)   dominated by 1 (slower, same error)
    #   3 (4, 2)   front (the best error among those faster than 5 s)
    #   4 (5, 2)   dominated by 3 (slower, same error)
    #   5 (6, 1)   front (the best error)
    #   6 (2, 6)   dominated by 1 (same time, worse error)
    #   7 (4, 2)   equal to 3: neither dominates the other, both stay
    #   8 (10, 8)  dominated by 1, 3, 5 ...
    pts = [(1, 9), (2, 5), (3, 5), (4, 2), (5, 2), (6, 1), (2, 6), (4, 2), (10, 8)]
    assert pareto_front(pts) == [0, 1, 3, 7, 5]
    assert pareto_front([]) == []
    assert pareto_front([(3.0, 3.0)]) == [0]


def test_linear_fit_is_exact_on_linear_data():
    x = [9, 18, 45, 90]
    y = [0.25 * v + 1.5 for v in x]  # 0.25 s a frame + 1.5 s
    a, b, r2 = linear_fit(x, y)
    assert a == pytest.approx(0.25, abs=1e-12) and b == pytest.approx(1.5, abs=1e-10)
    assert r2 == pytest.approx(1.0, abs=1e-12)
    # not linear: y = x² on 0, 1, 2 -> least squares y = 2x - 1/3, residuals 1/3, -2/3, 1/3;
    # SS_res = 2/3, SS_tot = sum (y - 5/3)² = 25/9 + 4/9 + 49/9 = 26/3, R² = 1 - 1/13
    a, b, r2 = linear_fit([0, 1, 2], [0, 1, 4])
    assert (a, b) == pytest.approx((2.0, -1.0 / 3.0)) and r2 == pytest.approx(12.0 / 13.0)
    with pytest.raises(ValueError):
        linear_fit([1, 1], [2, 3])


def test_error_and_flatten():
    m = flatten({"blueprint": {"blunf": {"fwiou": 80.0, "frame": "gt"}}, "poses": {"ate": 0.1}})
    assert m == {"blueprint.blunf.fwiou": 80.0, "blueprint.blunf.frame": "gt", "poses.ate": 0.1}
    assert error_of("100-blueprint.blunf.fwiou", m) == pytest.approx(20.0)
    assert error_of("poses.ate", m) == pytest.approx(0.1)
    assert error_of("poses.missing", m) == ""


def test_grids_are_well_formed():
    """Unique names; every group of the issue is in the full grid; both sweeps have >= 3 sizes."""
    for grid in (quick_grid(), full_grid()):
        names = [v.name for v in grid]
        assert len(set(names)) == len(names)
        assert {"blueprint", "poses", "depth"} <= {v.group for v in grid}
        assert len({v.frames for v in grid if v.cost == "frames"}) >= 3
        assert len({v.capture for v in grid if v.cost == "pixels"}) >= 3
    from pipeline.config import load_config

    for v in full_grid():  # every variant's settings are keys of today's configs
        load_config(None, list(v.sets))
    encodings = {s for v in full_grid() for s in v.sets if "blunf.encoding=" in s}
    assert encodings == {f"blueprint.blunf.encoding={e}" for e in ("pe", "hash", "siren", "none")}


MVR_ERROR = "100-blueprint.mvr.fwiou"


def test_tiny_bench_end_to_end(tmp_path: Path):
    """Three variants on an 8-view 64x48 room, one repeat each: the CSV has every fixed
    column, the stage timings and the flattened metrics; bench.md and the figures exist; a
    variant on an absent real capture is skipped with a message."""
    specs = {
        "tiny": CaptureSpec("tiny", synthetic(8, (64, 48), seed=3)),
        "gone": CaptureSpec("gone", lambda out: tmp_path / "no-such-capture", real=True),
    }
    fast = ("fusion.voxel=0.05", "blueprint.blunf.steps=20", "blueprint.blunf.batch=1024")
    grid = [
        Variant("blunf", "blueprint", "tiny", ("run.methods=blunf", *fast), reference=True),
        Variant("mvr", "blueprint", "tiny", ("run.methods=mvr", *fast), error=MVR_ERROR),
        Variant(
            "fused",
            "depth",
            "tiny",
            ("run.methods=mvr", *fast),
            fresh_from="fusion",
            timed=("fusion", "project"),
            error=MVR_ERROR,
        ),
        Variant("real", "blueprint", "gone"),  # a real capture that is absent: skipped
    ]
    md = bench(tmp_path / "b", grid=grid, specs=specs, repeats=1)
    rows = list(csv.DictReader(open(tmp_path / "b" / "bench.csv")))
    cols = list(rows[0])
    assert cols[: len(FIELDS)] == FIELDS
    want = {"seconds.blueprint", "cpu.blueprint", "seconds.fusion", "blueprint.blunf.fwiou"}
    assert want | {"blueprint.mvr.fwiou", "blueprint.mvr.pacc"} <= set(cols)
    by = {r["variant"]: r for r in rows}
    assert set(by) == {"blunf", "mvr", "fused"}
    for r in rows:
        assert r["failed"] == "0" and r["repeats"] == "1", r["note"]
        assert float(r["wall_s"]) > 0 and float(r["cpu_s"]) > 0 and float(r["peak_rss_mb"]) > 0
        assert r["width"] == "64" and r["height"] == "48" and r["frames"] == "8"
    # the error is 100 - the metric it names
    assert float(by["mvr"]["error"]) == pytest.approx(100 - float(by["mvr"]["blueprint.mvr.fwiou"]))
    # blueprint variants reran only the blueprint stage (the rest came from the warm cache);
    # the depth variant reran fusion onwards
    assert by["blunf"]["seconds.fusion"] == "" and float(by["blunf"]["seconds.blueprint"]) > 0
    assert float(by["fused"]["seconds.fusion"]) > 0
    assert float(by["fused"]["stage_s"]) == pytest.approx(
        float(by["fused"]["seconds.fusion"]) + float(by["fused"]["seconds.project"]), abs=2e-3
    )
    assert by["blunf"]["ref_ratio"] == "1.0" and math.isfinite(float(by["mvr"]["ref_ratio"]))
    text = md.read_text()
    assert "| blunf |" in text and "Pareto front on tiny" in text
    assert "Skipped:" in text and "no-such-capture" in text
    assert (tmp_path / "b" / "pareto-blueprint-tiny.png").stat().st_size > 1000
    # one warm-up built the upstream stages (all three variants share them; kept, the warm
    # cache links to it); the timed runs are removed once read
    assert [p.name for p in (tmp_path / "b" / "warm" / "tiny" / "runs").iterdir()] == ["w0"]
    assert not any((tmp_path / "b" / "runs").iterdir())

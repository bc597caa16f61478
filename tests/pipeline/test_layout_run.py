"""An L-shaped procedural room with two doors through the whole pipeline (sensor depth): the
architectural plan holds the layout targets against the exact gt/layout.json."""

from __future__ import annotations

import json
import time

import pytest

from pipeline.cli import main
from stages.synth import make_room

# 40 views of 240x180 (half of them on each arm's loop), the default settings
VIEWS, SIZE = 40, (240, 180)


@pytest.mark.slow
@pytest.mark.xfail(
    reason="measured: room F1 1.0 but corner / angle F1 0.42, wall length 0.37 m, one door of "
    "two (the north arm's west wall half seen from the arms' loops); not met yet",
    strict=False,
)
def test_l_room_with_doors_meets_the_layout_targets(tmp_path):
    t0 = time.perf_counter()
    cap = make_room(tmp_path / "cap", views=VIEWS, seed=4, size=SIZE, doors=2, shape="L")
    out = tmp_path / "run"
    assert main(["run", str(cap), "--out", str(out)]) == 0
    s = json.loads((out / "report.json").read_text())["metrics"]["layout"]
    assert s["room_f1"] >= 0.95 and s["corner_f1"] >= 0.9 and s["angle_f1"] >= 0.9, s
    assert s["wall_length_err_m"] <= 0.03, s
    assert s["doors_found"] == s["doors_total"] == 2, s
    assert s["door_width_err_m"] <= 0.05, s
    plan = json.loads((out / "plan.json").read_text())
    assert len(plan["rooms"]) == 1 and len(plan["rooms"][0]["polygon"]) == 6
    print(f"L room seed 4: {s}, {time.perf_counter() - t0:.0f} s")

"""bench.wallfit: a drawn wall against the vertical surfaces the views saw behind it."""

from __future__ import annotations

import json

import pytest
import trimesh

from pipeline.bench.wallfit import main, measure
from stages.synth.furniture import box_mesh


def _run(tmp_path, north_y: float):  # noqa: ANN202
    """A run folder: a 4 x 3 m room's walls as one-sided faces (facing in), a 0.6 m deep
    counter along the north wall, and a plan whose north wall is drawn at north_y."""
    h = 2.5
    quads, corners = [], [(0, 0), (4, 0), (4, 3), (0, 3)]
    for (ax, ay), (bx, by) in zip(corners, corners[1:] + corners[:1], strict=True):
        quads.append(trimesh.Trimesh([(bx, by, 0), (ax, ay, 0), (ax, ay, h), (bx, by, h)],
                                     [[0, 1, 2], [0, 2, 3]]))  # fmt: skip
    counter = box_mesh(0.5, 3.5, 2.4, 3.0, 0.0, 0.9)
    mesh = trimesh.util.concatenate([*quads, counter])
    # small triangles, as a fused surface's (the figures read triangle centres)
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=0.05)
    mesh = trimesh.Trimesh(v, f, process=False)
    run = tmp_path / f"run{north_y}"
    run.mkdir()
    mesh.export(run / "mesh.ply")
    poly = [[0, 0], [4, 0], [4, north_y], [0, north_y]]
    walls = [
        {"start": poly[i], "end": poly[(i + 1) % 4], "thickness": 0.1, "room": 0} for i in range(4)
    ]
    (run / "plan.json").write_text(json.dumps({"walls": walls}))
    return run


def test_a_wall_drawn_at_the_counters_front_lies_0_6_m_before_the_wall(tmp_path, capsys):
    at_wall = measure(_run(tmp_path, 3.0))
    at_front = measure(_run(tmp_path, 2.4))
    north = [w for w in at_wall["walls"] if w["start"][1] == 3.0][0]
    # the wall's face over the counter and beside it: the outermost surface on the face
    assert north["outer_m"] == pytest.approx(0.0, abs=0.02) and north["outer_ok"] == 1.0
    assert at_wall["seen"] == 1.0
    front = [w for w in at_front["walls"] if w["start"][1] == 2.4][0]
    # drawn on the counter's front: the wall behind it lies 0.6 m out along all of it; the
    # front is within 10 cm where the counter stands (0.5 to 3.5 m of the 4 m: its inner
    # 90 % is read, 0.2 to 3.8 m, so 3.0 of 3.6 m)
    assert front["outer_m"] == pytest.approx(0.6, abs=0.02) and front["outer_ok"] == 0.0
    assert front["seen"] == pytest.approx(3.0 / 3.6, abs=0.03)
    assert main([str(tmp_path / "run3.0")]) == 0
    assert "100.0 %" in capsys.readouterr().out
    assert main([str(tmp_path / "missing")]) == 1

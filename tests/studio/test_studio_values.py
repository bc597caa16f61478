"""Every value the page sends is checked against what the server offered, and every path
inside the run's studio folder, before any file is touched (viser checks neither a
dropdown's value against its options nor a slider's against its range, and lets a client
set a dropdown's options)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.studio.state import Session
from stages.common.errors import BlunfError
from tests.bomb import bomb_png
from tests.test_bad_input import snapshot

ESCAPES = [
    "../../../pipeline/cli.py",  # the case: a copy of the project's file beside the run
    "../tiles.png",
    "/etc/hostname",
    "textures/../../x.png",
    ".hidden.png",
]


def _centre(cap: Path, name: str) -> tuple[float, float]:
    inst = json.loads((cap / "gt" / "instances.json").read_text())
    b = next(v["bbox"] for v in inst.values() if v["name"] == name)
    return (b[0] + b[3]) / 2, (b[1] + b[4]) / 2


def test_texture_names_out_of_the_folder_write_nothing(studio_run) -> None:
    cap, run = studio_run
    base = run.parent  # the capture, the run and what lies beside them
    s = Session(run)
    s.select_class("table")
    before = snapshot(base)
    for name in ESCAPES:
        with pytest.raises(BlunfError, match="not one of the choices offered"):
            s.apply("retexture", texture=name)
    # a name forged into the offer (as a client can forge a dropdown's options): the path
    # check inside the studio's folder still refuses it, before any copy
    s.uploaded.extend(ESCAPES)
    for name in ESCAPES:
        with pytest.raises(BlunfError, match="not a file name of"):
            s.apply("retexture", texture=name)
    assert snapshot(base) == before, "a refused texture wrote a file"
    assert s.edits == [] and s.version == 0


def test_values_outside_the_offer_are_refused(studio_run) -> None:
    cap, run = studio_run
    s = Session(run)
    with pytest.raises(BlunfError, match="class"):
        s.select_class("../../etc")
    s.click(*_centre(cap, "sofa_1"))
    bad = [
        ("rm", {}),  # an operation not offered
        ("recolor", {"color": (300, 0, 0)}),
        ("recolor", {"color": (float("nan"), 0, 0)}),
        ("recolor", {"color": "red"}),
        ("recolor", {"color": (1, 2, 3), "strength": float("inf")}),
        ("recolor", {"color": (1, 2, 3), "strength": 5.0}),
        ("retexture", {"texture": None}),
    ]
    for op, kw in bad:
        with pytest.raises(BlunfError):
            s.apply(op, **kw)
    s.add_stroke_point(0.0, 0.0)
    s.add_stroke_point(0.5, 0.0)
    with pytest.raises(BlunfError, match="stroke width"):
        s.apply("sketch", color=(1, 2, 3), width=1e9)
    with pytest.raises(BlunfError, match="not a point"):
        s.add_stroke_point(float("nan"), 0.0)
    assert s.edits == [] and s.version == 0 and len(s.stroke) == 2
    s.apply("recolor", color=(1, 2, 3), strength=0.5)  # and a good one goes through
    assert len(s.edits) == 1


def test_uploads_that_are_bombs_or_huge_are_refused(studio_run) -> None:
    _, run = studio_run
    s = Session(run)
    before = snapshot(run.parent)
    with pytest.raises(BlunfError, match="bomb.png: not an image"):
        s.add_texture("bomb.png", bomb_png())  # PIL's DecompressionBombError
    with pytest.raises(BlunfError, match="pixels"):
        s.add_texture("big.png", bomb_png(5000, 5000))  # opens, but no texture needs that
    assert snapshot(run.parent) == before and s.uploaded == []

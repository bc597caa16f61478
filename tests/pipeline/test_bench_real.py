"""The real-capture bench scores only the reference's observed cells (pipeline/bench/real.py)."""

from __future__ import annotations

import numpy as np

from pipeline.bench.real import observed
from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN
from stages.common.io import write_json


def test_reference_cells_beyond_its_points_bounds_are_not_scored(tmp_path):
    """A 1 m grid of 0.1 m cells whose points spanned x, y in [0.2, 0.8]: the padding band
    round them (where the plan's field is clamped) becomes unknown, the inside is kept."""
    grid = Grid((0.0, 0.0), 0.1, (10, 10))
    ref = Blueprint(np.ones((10, 10), np.uint8), grid, {0: "floor", 1: "wall"})
    (tmp_path / "project" / "k").mkdir(parents=True)
    write_json(tmp_path / "project" / "k" / "grid.json", {"bounds": [0.2, 0.2, 0.8, 0.8]})
    got = observed(tmp_path, ref).labels
    want = np.full((10, 10), UNKNOWN, np.uint8)
    want[2:8, 2:8] = 1  # cell centres 0.25 .. 0.75
    np.testing.assert_array_equal(got, want)
    assert observed(tmp_path / "none", ref) is ref  # no project stage: the plan as it is


def test_references_draw_walls_as_the_photos_run_does():
    # phone.yaml draws no wall_face; the default does. The references take the photos-only
    # run's choice (else the drawing is scored as depth error), and their own --ref-set
    # still has the last word.
    from pathlib import Path

    from pipeline.bench.real import drawn_alike
    from pipeline.config import load_config

    root = Path(__file__).resolve().parents[2]
    phone = root / "configs" / "phone.yaml"
    assert load_config()["blueprint"].blunf.wall_face
    assert not load_config(phone)["blueprint"].blunf.wall_face
    ref = drawn_alike(phone, [])
    assert not load_config(None, ref)["blueprint"].blunf.wall_face
    moved = drawn_alike(
        phone, ["blueprint.blunf.wall_face=true", "blueprint.blunf.wall_face_margin=0"]
    )
    assert load_config(None, moved)["blueprint"].blunf.wall_face_margin == 0
    last = load_config(None, ref + ["blueprint.blunf.wall_face=true"])["blueprint"].blunf
    assert last.wall_face

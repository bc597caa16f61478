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
    # phone.yaml cuts the wall cells in front of a face to the nearest class the field drew;
    # the default cuts them to floor. The references take the photos-only run's choices (else
    # the drawing is scored as depth error), and their own --ref-set still has the last word.
    from pathlib import Path

    from pipeline.bench.real import drawn_alike
    from pipeline.config import load_config

    root = Path(__file__).resolve().parents[2]
    phone = root / "configs" / "phone.yaml"
    default, photos = load_config()["blueprint"].blunf, load_config(phone)["blueprint"].blunf
    assert default.wall_face and default.wall_face_fill == "floor"
    assert photos.wall_face and photos.wall_face_fill == "nearest"
    ref = load_config(None, drawn_alike(phone, []))["blueprint"].blunf
    assert ref.wall_face and ref.wall_face_fill == "nearest"
    off = drawn_alike(phone, ["blueprint.blunf.wall_face=false"])
    assert not load_config(None, off)["blueprint"].blunf.wall_face
    moved = drawn_alike(
        phone, ["blueprint.blunf.wall_face_margin=0", "blueprint.blunf.wall_face_fill=floor"]
    )
    drawn = load_config(None, moved)["blueprint"].blunf
    assert drawn.wall_face_margin == 0 and drawn.wall_face_fill == "floor"
    last = load_config(None, off + ["blueprint.blunf.wall_face=true"])["blueprint"].blunf
    assert last.wall_face

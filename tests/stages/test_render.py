"""The plan picture: class colours where the plan is, a legend, north up."""

from __future__ import annotations

import numpy as np
from PIL import Image

from stages.common.blueprint import Blueprint, Grid
from stages.common.classes import UNKNOWN_COLOR, class_color
from stages.common.plan_picture import plan_picture, plan_png

# 3 rows x 4 columns; row 0 is north (highest y). Class 7 appears only in the north-east
# corner, so a picture drawn south up would show it bottom-right instead of top-right.
LABELS = np.array([[0, 0, 1, 7], [0, 2, 1, 255], [0, 0, 2, 2]], np.uint8)
BP = Blueprint(
    LABELS, Grid((10.0, 20.0), 0.5, (3, 4)), {0: "floor", 1: "wall", 2: "chair", 7: "lamp"}
)


def test_plan_pixels_have_the_class_colours(tmp_path):
    plan_png(BP, tmp_path / "plan.png", title="test")
    img = np.asarray(Image.open(tmp_path / "plan.png").convert("RGB"))
    _, box = plan_picture(BP, "test")
    assert box.scale >= 8  # a 4-cell-wide plan is upscaled to be readable
    for r in range(3):
        for c in range(4):
            block = img[
                box.y0 + r * box.scale : box.y0 + (r + 1) * box.scale,
                box.x0 + c * box.scale : box.x0 + (c + 1) * box.scale,
            ]
            want = UNKNOWN_COLOR if LABELS[r, c] == 255 else class_color(int(LABELS[r, c]))
            assert (block == want).all(), (r, c)  # the whole upscaled cell, nearest neighbour


def test_colours_are_distinct_stable_and_the_legend_shows_them(tmp_path):
    colors = [class_color(i) for i in range(60)]
    assert len(set(colors)) == 60 and UNKNOWN_COLOR not in colors
    assert class_color(7) == class_color(7)
    img, box = plan_picture(BP)
    a = np.asarray(img)
    legend = a[:, box.x0 + 4 * box.scale + 2 :]  # right of the plan
    for k in (0, 1, 2, 7):
        assert (legend == class_color(k)).all(axis=-1).sum() >= 100, k  # a 14 x 14 swatch
    assert (legend == UNKNOWN_COLOR).all(axis=-1).sum() >= 100  # the plan has unknown cells
    assert (legend == class_color(3)).all(axis=-1).sum() == 0  # class 3 is not in the plan


def test_vector_writers_use_the_picture_colours():
    # one colour function for the PNG, SVG and DXF: the vector module uses the picture's
    from stages.common import components
    from stages.export import vector

    assert vector.class_color is class_color
    assert not hasattr(components, "class_color")

"""The SVG export, drawn by a real SVG renderer (resvg, as a browser would draw it), shows the
same plan as the PNG export: checked cell by cell on the procedural room's plan."""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET

import numpy as np
import resvg_py
from PIL import Image
from scipy import ndimage as ndi

from stages.common.blueprint import Blueprint
from stages.common.classes import class_color
from stages.common.plan_picture import plan_picture
from stages.export.vector import write_svg

NS = {"s": "http://www.w3.org/2000/svg"}


def test_rendered_svg_shows_the_png_plan(tiny_room, tmp_path):
    bp = Blueprint.load(tiny_room / "gt" / "blueprint.npz")  # circles, rotated boxes, holes
    path = tmp_path / "plan.svg"
    write_svg(bp, path, title="room")
    drawn = Image.open(io.BytesIO(bytes(resvg_py.svg_to_bytes(svg_string=path.read_text()))))
    svg = np.asarray(drawn.convert("RGB"))
    plan = ET.parse(path).getroot().find("s:svg", NS)  # the plan's box on the page (px)
    x, y, pw, ph = (float(plan.get(k)) for k in ("x", "y", "width", "height"))
    h, w = bp.grid.shape
    i, j = np.mgrid[0:h, 0:w]
    at_svg = svg[(y + (i + 0.5) * ph / h).astype(int), (x + (j + 0.5) * pw / w).astype(int)]
    pic, box = plan_picture(bp, title="room")
    png = np.asarray(pic)
    at_png = png[box.y0 + i * box.scale + box.scale // 2, box.x0 + j * box.scale + box.scale // 2]

    lut = np.array([class_color(c) for c in range(256)], np.int64)  # [256, 3]
    np.testing.assert_array_equal(at_png, lut[bp.labels])  # the PNG shows the labels exactly
    ids = np.unique(bp.labels)
    dist = ((at_svg[..., None, :].astype(np.int64) - lut[ids]) ** 2).sum(-1)  # [H, W, K]
    seen = ids[dist.argmin(-1)]  # the class whose colour each SVG cell centre shows
    # measured 99.6 % of cells; the rest is the polygons' 2 cm simplification and the
    # renderer's anti-aliasing, so every disagreement lies within 2 cells of a class border
    assert (seen == bp.labels).mean() > 0.99
    border = np.zeros((h, w), bool)
    for c in ids:
        m = bp.labels == c
        border |= m & ~ndi.binary_erosion(m, np.ones((5, 5)), border_value=1)
    assert not ((seen != bp.labels) & ~border).any()

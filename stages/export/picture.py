"""blueprint.png with the architecture over it: the blueprint's class colours at a readable
size (at least `LONG_PX` on the long side), the layout's walls black over them, openings as
gaps, object outlines with sizes, wall lengths, room names and areas (stages/common/architect.py),
and beside it a legend of the classes with a north arrow and a scale bar."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from stages.common.architect import PAD_M, overlay
from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import class_color, label_name
from stages.common.plan_picture import nice_length

LONG_PX = 1400  # the plan's longer side (px)
MARGIN = 24
INK = (0, 0, 0)


def _font(size: int):  # noqa: ANN202 - a Pillow font of either kind
    try:
        return ImageFont.load_default(size=size)
    except (OSError, ImportError, TypeError):
        return ImageFont.load_default()


def architect_png(bp: Blueprint, plan: dict, path: Path, title: str = "") -> tuple[int, int]:
    """Write the picture; returns its (width, height) in pixels."""
    lut = np.array([class_color(i) for i in range(256)], np.uint8)  # [256, 3]
    labels = np.asarray(bp.labels, np.uint8)
    plan_img = overlay(lut[labels], bp.grid, plan, long_px=LONG_PX)
    font = _font(22)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    line = int(probe.textbbox((0, 0), "Ag", font=font)[3]) + 10
    ids = sorted((int(c) for c in np.unique(labels)), key=lambda c: (c == UNKNOWN, c))
    names = [label_name(bp.classes, c) for c in ids]
    legend_w = 40 + max(int(probe.textlength(n, font=font)) for n in names + ["walls (plan)"])
    top = MARGIN + (line + 6 if title else 0)
    w, h = plan_img.size
    img = Image.new("RGB", (MARGIN + w + MARGIN + legend_w + MARGIN, top + h + MARGIN), "white")
    img.paste(plan_img, (MARGIN, top))
    d = ImageDraw.Draw(img)
    if title:
        d.text((MARGIN, MARGIN), title, fill=INK, font=font)
    x = MARGIN + w + MARGIN
    d.text((x + 4, top), "N", fill=INK, font=font)  # north (+y) up
    d.polygon([(x + 10, top + 30), (x + 2, top + 46), (x + 18, top + 46)], fill=INK)
    d.line([(x + 10, top + 46), (x + 10, top + 62)], fill=INK, width=3)
    y = top + 80
    for c, n in [
        (INK, "walls (plan)"),
        *((class_color(c), n) for c, n in zip(ids, names, strict=True)),
    ]:
        d.rectangle([x, y, x + 22, y + 22], fill=c, outline=INK)
        d.text((x + 32, y), n, fill=INK, font=font)
        y += line
    # scale bar: a round length that fits the legend's column
    pad = math.ceil(PAD_M / bp.grid.cell)  # overlay's paper round the raster (cells)
    px_per_m = w / ((bp.grid.shape[1] + 2 * pad) * bp.grid.cell)
    length = nice_length(legend_w / px_per_m)
    y += line
    d.rectangle([x, y, x + round(length * px_per_m), y + 8], fill=INK)
    d.text((x, y + 14), f"{length:g} m", fill=INK, font=font)
    img.save(path)
    return img.size

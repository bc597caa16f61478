"""The blueprint as a picture: class colours, legend, scale bar, north up (PIL only)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.classes import class_color, label_name

BACKGROUND = (255, 255, 255)
INK = (0, 0, 0)
TARGET_PX = 480  # small plans are upscaled (nearest neighbour) to about this many pixels
MAX_UPSCALE = 64
MARGIN = 16


@dataclass(frozen=True)
class PlanBox:
    """Where the plan raster sits in the picture: top-left pixel and pixels per cell."""

    x0: int
    y0: int
    scale: int


def plan_png(bp: Blueprint, path: Path, title: str = "") -> None:
    """Write the blueprint as a PNG with a legend, a scale bar in metres and a north arrow."""
    plan_picture(bp, title)[0].save(path)


def plan_picture(bp: Blueprint, title: str = "") -> tuple[Image.Image, PlanBox]:
    """The picture plan_png writes, and where the plan raster is in it."""
    labels = np.asarray(bp.labels, np.uint8)  # [H, W], row 0 = north
    h, w = labels.shape
    s = max(1, min(MAX_UPSCALE, TARGET_PX // max(h, w)))
    font = _font(14)
    lut = np.array([class_color(i) for i in range(256)], np.uint8)  # [256, 3]
    raster = Image.fromarray(lut[labels]).resize((w * s, h * s), Image.Resampling.NEAREST)

    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    line = _text_size(probe, "Ag", font)[1] + 6
    ids = [int(c) for c in np.unique(labels)]
    entries = [
        (class_color(c), label_name(bp.classes, c))
        for c in sorted(ids, key=lambda c: (c == UNKNOWN, c))
    ]
    legend_w = 24 + max([_text_size(probe, n, font)[0] for _, n in entries] + [40])
    top = MARGIN + (line + 4 if title else 0)
    box = PlanBox(MARGIN, top, s)
    north_h = 44
    legend_h = north_h + line * len(entries)
    width = MARGIN + w * s + MARGIN + legend_w + MARGIN
    height = max(top + h * s + MARGIN + 2 * line, top + legend_h) + MARGIN
    img = Image.new("RGB", (width, height), BACKGROUND)
    img.paste(raster, (box.x0, box.y0))
    d = ImageDraw.Draw(img)
    d.rectangle([box.x0 - 1, box.y0 - 1, box.x0 + w * s, box.y0 + h * s], outline=INK)
    if title:
        d.text((MARGIN, MARGIN), title, fill=INK, font=font)
    lx = box.x0 + w * s + MARGIN
    _north_arrow(d, lx + 12, top, font)
    for i, (color, name) in enumerate(entries):
        y = top + north_h + i * line
        d.rectangle([lx, y, lx + 14, y + 14], fill=color, outline=INK)
        d.text((lx + 22, y), name, fill=INK, font=font)
    _scale_bar(d, bp.grid.cell, w, box, top + h * s + MARGIN // 2, font)
    return img, box


def _north_arrow(d: ImageDraw.ImageDraw, x: int, y: int, font) -> None:
    """An upward arrow under an N: the plan is drawn north (+y) up."""
    d.text((x - 5, y), "N", fill=INK, font=font)
    d.polygon([(x, y + 18), (x - 6, y + 30), (x + 6, y + 30)], fill=INK)
    d.line([(x, y + 30), (x, y + 40)], fill=INK, width=2)


def _scale_bar(d: ImageDraw.ImageDraw, cell: float, w: int, box: PlanBox, y: int, font) -> None:
    """A bar of a round length (1, 2 or 5 x 10^k metres) close to a third of the plan width."""
    length = nice_length(w * cell / 3.0)
    px = max(1, round(length / cell * box.scale))
    x0 = box.x0
    d.rectangle([x0, y, x0 + px, y + 5], fill=INK)
    d.line([(x0, y - 3), (x0, y + 8)], fill=INK)
    d.line([(x0 + px, y - 3), (x0 + px, y + 8)], fill=INK)
    d.text((x0 + px + 6, y - 5), f"{length:g} m", fill=INK, font=font)


def nice_length(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above x (x > 0)."""
    k = math.floor(math.log10(x))
    for m in (5, 2, 1):
        if m * 10.0**k <= x:
            return float(f"{m * 10.0**k:.12g}")
    return float(f"{10.0**k:.12g}")


def _text_size(d: ImageDraw.ImageDraw, text: str, font) -> tuple[int, int]:
    x0, y0, x1, y1 = d.textbbox((0, 0), text, font=font)
    return int(x1 - x0), int(y1 - y0)


def _font(size: int):
    """Pillow's bundled font at `size` (its bitmap font where FreeType is missing)."""
    try:
        return ImageFont.load_default(size=size)
    except (OSError, ImportError, TypeError):
        return ImageFont.load_default()

"""What makes real photos of a room hard, as options of the procedural room.

The default room carries a strong random texture on every surface and a perfect camera: the
easy case for SIFT and stereo. Real rooms have plain painted walls and ceilings, smooth
floors, and a phone that changes its exposure from shot to shot, moves while exposing and
adds sensor noise. `Realism` adds these:
  surfaces  "textured" (as before) or "plain": walls and ceilings take their flat paint
            colour with a faint large-scale variation (uneven light across a wall, no detail
            a window can match), floors a weak fine grain (SMOOTH_CONTRAST of the textured
            contrast); furniture keeps its texture;
  exposure  relative exposure of each view, 2 ** N(0, exposure) (stops, 1 sigma);
  blur      motion blur: a straight streak of up to `blur` pixels (length uniform in
            [blur / 4, blur], any direction) per view, then a slight defocus (Gaussian of
            DEFOCUS x the streak length);
  noise     sensor noise in linear intensity: shot noise of sd noise * sqrt(I) and read
            noise of sd noise / 4 (I in [0, 1], white = 1).
Camera effects act on the linear image before the display gamma; depth, labels and
instances stay exact. Each view's draws come from (seed, view index): the same options give
the same files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from scipy import ndimage

from stages.common.errors import BlunfError

SURFACES = ("textured", "plain")
PLAIN_VARIATION = 0.03  # plain walls / ceilings: +-3 % albedo over PLAIN_CELL
PLAIN_CELL = 1.5  # metres: lattice spacing of that variation (smooth across a wall)
SMOOTH_CONTRAST = 0.3  # plain floors: noise contrast (the textured rooms use 3.0)
DEFOCUS = 0.3  # Gaussian sigma of the defocus, as a fraction of the motion streak
PRESETS: dict[str, dict[str, Any]] = {
    "none": {},
    # a hand-held phone in a plain room: measured against the real captures' photos (7-Scenes
    # kitchen: streaks of a few pixels at 640 px; exposure steps between frames)
    "honest": {"surfaces": "plain", "exposure": 0.25, "blur": 2.0, "noise": 0.015},
}


@dataclass(frozen=True)
class Realism:
    """How real the synthetic photos look; the defaults are today's rooms (byte for byte)."""

    surfaces: str = "textured"  # "textured" | "plain" (walls, ceiling plain; floor smooth)
    exposure: float = 0.0  # stops (1 sigma) of the views' exposure about the mean
    blur: float = 0.0  # pixels: longest motion streak of a view (0 = sharp)
    noise: float = 0.0  # sensor noise sd at white, linear intensity (0 = none)

    def __post_init__(self) -> None:
        if self.surfaces not in SURFACES:
            raise BlunfError(f"realism surfaces: {self.surfaces!r} is not one of {SURFACES}")
        for name, top in (("exposure", 2.0), ("blur", 50.0), ("noise", 0.5)):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and 0 <= v <= top):
                raise BlunfError(f"realism {name}: must be a number in [0, {top:g}], got {v!r}")

    @property
    def camera(self) -> bool:
        """Whether any camera effect is on."""
        return self.exposure > 0 or self.blur > 0 or self.noise > 0

    @property
    def default(self) -> bool:
        return self == Realism()

    def to_json(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def parse(spec: str) -> Realism:
        """A preset and/or key=value settings, comma-separated: "honest", "surfaces=plain",
        "honest,blur=0", "exposure=0.5,noise=0.02"."""
        out = Realism()
        for item in (s.strip() for s in spec.split(",")):
            if not item:
                continue
            if "=" not in item:
                if item not in PRESETS:
                    raise BlunfError(
                        f"--realism: {item!r} is no preset ({', '.join(PRESETS)}) nor key=value"
                    )
                out = replace(out, **PRESETS[item])
                continue
            key, val = (s.strip() for s in item.split("=", 1))
            names = [f.name for f in fields(Realism)]
            if key not in names:
                raise BlunfError(f"--realism: {key!r} is not one of {names}")
            if key == "surfaces":
                out = replace(out, surfaces=val)
                continue
            try:
                num = float(val)
            except ValueError:
                raise BlunfError(f"--realism: {key}={val!r} is not a number") from None
            kw: dict[str, Any] = {key: num}
            out = replace(out, **kw)
        return out


def plain_albedo(base: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Albedo [N, 3] of plain walls and ceilings: base colours [N, 3] varied by
    +-PLAIN_VARIATION with the large-scale value noise `noise` [N] in [0, 1]."""
    return base * (1.0 + 2.0 * PLAIN_VARIATION * (noise - 0.5))[:, None]


def smooth_floor(base: np.ndarray, grain: np.ndarray) -> np.ndarray:
    """Albedo [N, 3] of a smooth floor: base colours [N, 3] with the fine noise `grain` [N]
    (fbm in [0, 1]) at SMOOTH_CONTRAST; the mean brightness of the textured floor."""
    v = np.clip(0.5 + SMOOTH_CONTRAST * (grain - 0.5), 0.0, 1.0)
    return base * (0.35 + 0.9 * v)[:, None]


def camera_effects(
    lin: np.ndarray, opts: Realism, rng: np.random.Generator
) -> tuple[np.ndarray, dict]:
    """The phone's exposure, blur and noise on a linear image [H, W, 3] (float64, white = 1).
    Returns the image (not clipped) and what was drawn (JSON-ready)."""
    drawn: dict = {}
    # draw every number first, in a fixed order, so one effect's setting never moves another's
    gain = 2.0 ** (opts.exposure * rng.standard_normal())
    length = opts.blur * rng.uniform(0.25, 1.0)
    angle = rng.uniform(0.0, math.pi)
    if opts.exposure > 0:
        lin = lin * gain
        drawn["exposure_gain"] = round(float(gain), 4)
    if opts.blur > 0:
        k = streak_kernel(length, angle, DEFOCUS * length)
        lin = np.stack(
            [ndimage.convolve(lin[..., c], k, mode="nearest") for c in range(lin.shape[2])], -1
        )
        drawn["blur_px"] = round(float(length), 3)
        drawn["blur_deg"] = round(math.degrees(angle), 1)
    if opts.noise > 0:
        sd = np.sqrt(opts.noise**2 * np.clip(lin, 0.0, None) + (opts.noise / 4) ** 2)
        lin = lin + sd * rng.standard_normal(lin.shape)
    return lin, drawn


def streak_kernel(length: float, angle: float, sigma: float) -> np.ndarray:
    """A normalised blur kernel: a line of `length` pixels at `angle` (radians from the
    image's x axis), drawn with bilinear weights, then a Gaussian of `sigma` pixels."""
    r = int(math.ceil(length / 2 + 3 * sigma)) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1))
    n = max(2, int(math.ceil(4 * length)))
    t = np.linspace(-length / 2, length / 2, n)
    x, y = r + t * math.cos(angle), r + t * math.sin(angle)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    np.add.at(k, (y0 + 1, x0 + 1), fx * fy)
    if sigma > 0:
        k = ndimage.gaussian_filter(k, sigma, mode="constant")
    return k / k.sum()

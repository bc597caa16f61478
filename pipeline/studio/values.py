"""The values a studio page sends, checked: the choices and ranges the server offers it, and
the checks that a value is one of them (viser lets a client set any value on any handle, its
options and ranges too). A value that fails is a one-line BlunfError naming it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stages.common.errors import BlunfError

OPS = ("remove", "recolor", "retexture", "sketch", "mask")  # the page's operations
STRENGTH = (0.0, 1.0)  # the strength slider's range
WIDTH = (0.02, 0.5)  # the stroke width slider's range (metres)


def offered(value: Any, options: Any, what: str) -> Any:
    """`value` when it is one of the `options` the page was given, else a one-line error."""
    if not isinstance(value, str | int) or isinstance(value, bool) or value not in options:
        raise BlunfError(f"{what}: {str(value)[:80]!r} is not one of the choices offered")
    return value


def in_range(value: Any, lo: float, hi: float, what: str) -> float:
    """A finite number within [lo, hi] (the slider's range), else a one-line error."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (np.isfinite(v) and lo <= v <= hi):
        raise BlunfError(f"{what}: must be a number in {lo}..{hi}, got {str(value)[:80]!r}")
    return v


def rgb(value: Any) -> list[int]:
    """[r, g, b] with integer values in 0..255, else a one-line error."""
    ok = isinstance(value, list | tuple) and len(value) == 3
    if ok:
        try:
            return [int(in_range(c, 0, 255, "colour")) for c in value]
        except BlunfError:
            pass
    raise BlunfError(f"colour: must be [r, g, b] in 0..255, got {str(value)[:80]!r}")


def inside(folder: Path, name: Any, what: str) -> Path:
    """`folder / name` resolved, when `name` is a plain file name that stays inside `folder`
    (a request's value: anything else is a one-line error)."""
    bad = not isinstance(name, str) or not name or name != Path(name).name or name[0] == "."
    p = (folder / str(name)).resolve()
    if bad or not p.is_relative_to(folder.resolve()):
        raise BlunfError(f"{what} {str(name)[:80]!r}: not a file name of {folder}")
    return p


def floor_point(origin: Any, direction: Any) -> tuple[float, float]:
    """Where a ray meets the floor plane z = 0, or a one-line error when it does not."""
    o, d = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    if o.shape != (3,) or d.shape != (3,) or not np.all(np.isfinite(o) & np.isfinite(d)):
        raise BlunfError("click: not a ray")
    if abs(d[2]) < 1e-9 or -o[2] / d[2] <= 0:
        raise BlunfError("click: off the plan (the ray does not meet the floor)")
    t = -o[2] / d[2]
    return float(o[0] + t * d[0]), float(o[1] + t * d[1])

"""The edit spec (YAML, DESIGN.md "Edit spec"): parsed and checked before any work.

Every error is one line naming the file and the entry at fault, e.g.
`edits.yaml: edits[2].texture: ../x.png lies outside the spec's folder`. `load_spec` checks
what the file alone decides (keys, types, ranges, textures); what needs the plan (a click on
it, a class it has, a view index) is checked by `stages.edit.select.select_cells` and
`check_views`, still before anything is rendered or written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image, UnidentifiedImageError
from shapely.geometry import Polygon

from stages.common.errors import BlunfError
from stages.common.io import read_yaml

OPS = ("mask", "recolor", "retexture", "sketch", "remove")
SELECTORS = ("click", "pixel", "class", "polygon", "stroke")
# keys each op takes besides `select` and `op`, and which of them are required
OP_KEYS: dict[str, dict[str, bool]] = {
    "mask": {},
    "remove": {},
    "recolor": {"color": True, "strength": False},
    "sketch": {"color": True, "strength": False},
    "retexture": {"texture": True, "strength": False},
}
ORBIT_KEYS = ("center", "radius", "height", "frames")
MAX_ORBIT_FRAMES = 720


@dataclass(frozen=True)
class Selector:
    """What an edit selects on the plan. `value` by kind: click (x, y) metres, pixel (u, v)
    cell column / row, class name, polygon ((x, y), ...) metres, stroke ((x, y), ...) metres."""

    kind: str  # one of SELECTORS
    value: Any
    width: float = 0.0  # stroke: width in metres
    where: str = ""  # "<spec>: edits[i].select", for errors


@dataclass(frozen=True)
class Edit:
    """One entry of `edits`."""

    index: int
    op: str  # one of OPS
    select: Selector
    color: tuple[float, float, float] | None = None  # RGB 0-255 (recolor, sketch)
    strength: float = 1.0  # blend weight of the new colour / texture, in [0, 1]
    texture: Path | None = None  # resolved texture file (retexture)
    where: str = ""  # "<spec>: edits[i]"


@dataclass(frozen=True)
class Orbit:
    """A camera path around `center` (look-at point, world metres), cameras at z = height."""

    center: tuple[float, float, float]
    radius: float  # metres from the centre, horizontally
    height: float  # camera z (metres)
    frames: int  # views along the full turn


@dataclass(frozen=True)
class EditSpec:
    path: Path
    edits: tuple[Edit, ...]
    views: tuple[int, ...]  # frame indices: (0,) when the spec has no views, () with an orbit
    orbit: Orbit | None = None

    @property
    def textures(self) -> tuple[Path, ...]:
        """Texture files the edits use, each once, in order."""
        return tuple(dict.fromkeys(e.texture for e in self.edits if e.texture is not None))


def spec_textures(path: Path) -> tuple[Path, ...]:
    """The texture files a spec names (for `EditInputs.textures`); validates the spec."""
    return load_spec(path).textures


def load_spec(path: Path) -> EditSpec:
    """Read and check an edit spec. Raises BlunfError naming the bad entry."""
    path = Path(path)
    return parse_spec(read_yaml(path, "edit spec"), path)


def parse_spec(data: Any, path: Path) -> EditSpec:
    """Check an edit spec already read (`path` names it in errors and anchors textures)."""
    path = Path(path)
    if not isinstance(data, dict):
        raise BlunfError(f"{path}: an edit spec is a mapping with 'edits' (and 'views')")
    _only(data, ("edits", "views"), f"{path}")
    edits = data.get("edits")
    if not isinstance(edits, list) or not edits:
        raise BlunfError(f"{path}: edits: must be a non-empty list of edits")
    parsed = tuple(_edit(e, i, path) for i, e in enumerate(edits))
    views: tuple[int, ...] = (0,)
    orbit = None
    if "views" in data:
        views, orbit = _views(data["views"], f"{path}: views")
    return EditSpec(path, parsed, views, orbit)


def check_views(spec: EditSpec, n_frames: int) -> None:
    """Every requested frame index must name a frame of frames.json."""
    for i, v in enumerate(spec.views):
        if v >= n_frames:
            raise BlunfError(
                f"{spec.path}: views[{i}]: frame {v} does not exist "
                f"(frames.json has {n_frames} frames, 0..{n_frames - 1})"
            )


# ---- pieces ------------------------------------------------------------------------------
def _only(d: dict, allowed: tuple[str, ...], where: str) -> None:
    for k in d:
        if k not in allowed:
            raise BlunfError(f"{where}: unknown key {k!r} (expected: {', '.join(allowed)})")


def _edit(e: Any, i: int, path: Path) -> Edit:
    where = f"{path}: edits[{i}]"
    if not isinstance(e, dict):
        raise BlunfError(f"{where}: must be a mapping with 'select' and 'op'")
    op = e.get("op")
    if op is None:
        raise BlunfError(f"{where}: missing 'op' (one of {', '.join(OPS)})")
    if op not in OPS:
        raise BlunfError(f"{where}.op: unknown op {op!r} (one of {', '.join(OPS)})")
    if "select" not in e:
        raise BlunfError(f"{where}: missing 'select' ({', '.join(SELECTORS)})")
    keys = OP_KEYS[op]
    for k in e:
        if k not in ("select", "op", *keys):
            extra = f"{op} takes {', '.join(keys)}" if keys else f"{op} takes no settings"
            raise BlunfError(f"{where}: unknown key {k!r} ({extra})")
    for k, required in keys.items():
        if required and k not in e:
            raise BlunfError(f"{where}: {op} needs '{k}'")
    sel = _selector(e["select"], f"{where}.select")
    color = _color(e["color"], f"{where}.color") if "color" in e else None
    strength = _number(e.get("strength", 1.0), f"{where}.strength", 0.0, 1.0)
    texture = _texture(e["texture"], f"{where}.texture", path) if "texture" in e else None
    return Edit(i, op, sel, color, strength, texture, where)


def _selector(s: Any, where: str) -> Selector:
    if not isinstance(s, dict) or not s:
        raise BlunfError(f"{where}: must be a mapping with one of {', '.join(SELECTORS)}")
    kinds = [k for k in s if k in SELECTORS]
    if len(kinds) != 1:
        got = ", ".join(map(str, s)) or "nothing"
        raise BlunfError(f"{where}: give exactly one of {', '.join(SELECTORS)} (got {got})")
    kind = kinds[0]
    _only(s, (kind, "width") if kind == "stroke" else (kind,), where)
    v, w = s[kind], f"{where}.{kind}"
    if kind == "click":
        return Selector(kind, _xy(v, w), where=where)
    if kind == "pixel":
        if not (isinstance(v, list) and len(v) == 2 and all(_is_int(x) and x >= 0 for x in v)):
            raise BlunfError(f"{w}: must be [u, v], two whole cell indices >= 0, got {v!r}")
        return Selector(kind, (int(v[0]), int(v[1])), where=where)
    if kind == "class":
        if not isinstance(v, str) or not v.strip():
            raise BlunfError(f"{w}: must be a class name, got {v!r}")
        return Selector(kind, v.strip(), where=where)
    pts = _points(v, w, 3 if kind == "polygon" else 2)
    if kind == "polygon":
        if not Polygon(pts).buffer(0).area > 0:
            raise BlunfError(f"{w}: the polygon encloses no area")
        return Selector(kind, pts, where=where)
    if "width" not in s:
        raise BlunfError(f"{where}: a stroke needs 'width' (metres)")
    width = _number(s["width"], f"{where}.width", 0.0, math.inf)
    if width <= 0:
        raise BlunfError(f"{where}.width: must be > 0 metres, got {width}")
    return Selector(kind, pts, width, where)


def _views(v: Any, where: str) -> tuple[tuple[int, ...], Orbit | None]:
    if isinstance(v, list):
        if not v or not all(_is_int(x) and x >= 0 for x in v):
            raise BlunfError(f"{where}: must be a non-empty list of frame indices >= 0, got {v!r}")
        return tuple(int(x) for x in v), None
    if not isinstance(v, dict) or list(v) != ["orbit"] or not isinstance(v["orbit"], dict):
        raise BlunfError(
            f"{where}: must be a list of frame indices or {{orbit: {{{', '.join(ORBIT_KEYS)}}}}}"
        )
    o, w = v["orbit"], f"{where}.orbit"
    _only(o, ORBIT_KEYS, w)
    for k in ORBIT_KEYS:
        if k not in o:
            raise BlunfError(f"{w}: missing '{k}'")
    c = o["center"]
    if not (isinstance(c, list) and len(c) == 3 and all(_finite(x) for x in c)):
        raise BlunfError(f"{w}.center: must be [x, y, z] in metres, got {c!r}")
    radius = _number(o["radius"], f"{w}.radius", 0.0, math.inf)
    if radius <= 0:
        raise BlunfError(f"{w}.radius: must be > 0 metres, got {radius}")
    height = _number(o["height"], f"{w}.height", -math.inf, math.inf)
    n = o["frames"]
    if not _is_int(n) or not 1 <= n <= MAX_ORBIT_FRAMES:
        raise BlunfError(f"{w}.frames: must be a whole number in 1..{MAX_ORBIT_FRAMES}, got {n!r}")
    center = (float(c[0]), float(c[1]), float(c[2]))
    return (), Orbit(center, radius, height, int(n))


def _texture(v: Any, where: str, spec: Path) -> Path:
    if not isinstance(v, str) or not v.strip():
        raise BlunfError(f"{where}: must be a file path relative to the spec, got {v!r}")
    folder = spec.resolve().parent
    p = (folder / v).resolve()
    if not p.is_relative_to(folder):
        raise BlunfError(f"{where}: {v} lies outside the spec's folder")
    if not p.is_file():
        raise BlunfError(f"{where}: {v} not found (next to the spec: {p})")
    try:
        with Image.open(p) as img:
            img.verify()
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise BlunfError(f"{where}: {v} is not a readable image ({e.__class__.__name__})") from None
    return p


def _color(v: Any, where: str) -> tuple[float, float, float]:
    if not (isinstance(v, list) and len(v) == 3 and all(_finite(x) and 0 <= x <= 255 for x in v)):
        raise BlunfError(f"{where}: must be [r, g, b] with values in 0..255, got {v!r}")
    return (float(v[0]), float(v[1]), float(v[2]))


def _xy(v: Any, where: str) -> tuple[float, float]:
    if not (isinstance(v, list) and len(v) == 2 and all(_finite(x) for x in v)):
        raise BlunfError(f"{where}: must be [x, y] in metres, got {v!r}")
    return (float(v[0]), float(v[1]))


def _points(v: Any, where: str, n_min: int) -> tuple[tuple[float, float], ...]:
    if not isinstance(v, list) or len(v) < n_min:
        raise BlunfError(f"{where}: must be a list of at least {n_min} points [x, y], got {v!r}")
    return tuple(_xy(p, f"{where}[{i}]") for i, p in enumerate(v))


def _number(v: Any, where: str, lo: float, hi: float) -> float:
    if not _finite(v) or not lo <= v <= hi:
        rng = f"in [{lo:g}, {hi:g}]" if math.isfinite(hi) else "a finite number"
        raise BlunfError(f"{where}: must be {rng}, got {v!r}")
    return float(v)


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)

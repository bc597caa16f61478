"""report.html: the run for a person to read, one file that opens from disk.

Built from report.json's content and the run's published outputs (blueprint.png and .npz,
transforms.json, plan.svg, edits/): the plan with its legend and scale, the architectural
drawing, the cameras seen from above over the plan, the stage table, the metrics, a strip
of input photos and the edited renders. Every picture is inlined (base64 PNG, SVG or GIF),
nothing is fetched. A picture that cannot be read leaves its section out with a note; the
report itself never fails a run.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

THUMBS = 24  # input photos shown at most (spread along the capture)
THUMB_H = 72  # their height in pixels
EDIT_VIEWS = 12  # edited renders shown at most
GIF_MAX_BYTES = 4 * 2**20  # a larger orbit GIF is named, not inlined
LABEL_CAMERAS = 40  # cameras numbered on the plan up to this many
STATUS_COLORS = {"ran": "#d7f0d2", "cached": "#dde8f7", "skipped": "#eeeeee"}
CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:24px auto;max-width:1100px;color:#222;padding:0 12px}
h1{font-size:22px;margin-bottom:4px}h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ccc}
table{border-collapse:collapse}
td,th{padding:3px 8px;border-bottom:1px solid #e4e4e4;text-align:left}
td.n{text-align:right;font-variant-numeric:tabular-nums}.note{color:#777}
.warn{background:#fff3cd;border:1px solid #e0c36c;padding:6px 8px 6px 28px}
.strip{display:flex;flex-wrap:wrap;gap:6px}.strip figure{margin:0;font-size:11px;color:#555}
img{max-width:100%}.pics{display:flex;flex-wrap:wrap;gap:16px;align-items:flex-start}
"""


def report_html(folder: Path, report: dict) -> str:
    """The page for the run whose outputs are in `folder` (report.json's content: `report`)."""
    folder = Path(folder)
    parts = [_header(report)]
    for title, make in _SECTIONS:
        try:
            body = make(folder, report)
        except Exception as e:  # a damaged or missing output: say so, keep the rest
            log.warning("report.html: %s left out (%s)", title.lower(), _short(e))
            body = f"<p class=note>Not available: {html.escape(_short(e))}</p>"
        if body:
            parts.append(f"<section><h2>{html.escape(title)}</h2>\n{body}</section>")
    title = html.escape(f"blunf: {report.get('scene', '')}")
    return (
        f"<!DOCTYPE html>\n<html lang=en><head><meta charset=utf-8><title>{title}</title>"
        f"<style>{CSS}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n"
    )


def _header(report: dict) -> str:
    total = report.get("seconds_total")
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime())
    facts = [f"capture {report.get('capture', '?')}", f"written {when}"]
    if isinstance(total, (int, float)):
        facts.append(f"{total:.1f} s in all")
    plan = report.get("plan") or {}
    if plan.get("known_area_m2") is not None:
        facts.append(f"{plan['known_area_m2']:.1f} m² mapped")
    warned = "".join(
        f"<li>{html.escape(stage)}: {html.escape(w)}</li>" for stage, w in warnings(report)
    )
    return (
        f"<h1>{html.escape(str(report.get('scene', 'run')))}</h1>"
        f"<p class=note>{html.escape(' · '.join(facts))}</p>"
        + (f"<ul class=warn>{warned}</ul>" if warned else "")
    )


def warnings(report: dict) -> list[tuple[str, str]]:
    """(stage, line) of every warning a stage put in its facts (`facts["warnings"]`: SfM's
    models that split, photos left out, a model that contradicts its own matches), in stage
    order: shown first on the page, and counted on the command line."""
    out = []
    for s in report.get("stages", []):
        facts = s.get("facts") if isinstance(s, dict) else None
        ws = facts.get("warnings") if isinstance(facts, dict) else None
        out += [(str(s.get("name", "")), str(w)) for w in ws or []]
    return out


# ---- pictures ------------------------------------------------------------------------------
def _plan(folder: Path, report: dict) -> str:
    png = folder / "blueprint.png"
    if not png.is_file():
        return "<p class=note>No blueprint.png in this run.</p>"
    _check_png(png.read_bytes())
    pic = _img(png.read_bytes(), "image/png", "the plan, with its legend and scale")
    return pic + _known(folder, report)


KNOWN = (  # the blueprint's shares of its cells (Blueprint.shares), as the report names them
    ("seen_pct", "seen", "a projected point within reach"),
    ("inferred_pct", "inferred", "inside the room, filled between observations"),
    ("unknown_pct", "unknown", "inside the room, too far from any observation to guess"),
    ("outside_pct", "outside", "beyond what the views observed or looked through"),
)


def _known(folder: Path, report: dict) -> str:
    """What the plan knows: its cells seen, inferred, unknown and outside (percent)."""
    shares = _facts(report, "blueprint").get("observed")
    if not isinstance(shares, dict):
        return ""
    rows = "".join(
        f"<tr class=known><td>{name}</td><td class=n>{shares[k]:.1f} %</td>"
        f"<td>{html.escape(what)}</td></tr>"
        for k, name, what in KNOWN
        if isinstance(shares.get(k), (int, float))
    )
    walls = [w for w in _plan_walls(folder) if isinstance(w, dict)]
    inferred = sum(float(w.get("length", 0)) for w in walls if w.get("seen") is False)
    total = sum(float(w.get("length", 0)) for w in walls)
    note = (
        f"<p class=note>Walls: {total - inferred:.2f} m seen, {inferred:.2f} m inferred "
        "(dashed: the outline closes over space no view saw as a wall).</p>"
        if walls
        else ""
    )
    return f"<h3>What the plan knows</h3><table>{rows}</table>{note}"


def _plan_walls(folder: Path) -> list:
    """plan.json's walls, when the run holds a readable plan.json."""
    try:
        return json.loads((folder / "plan.json").read_text()).get("walls", [])
    except (OSError, ValueError, AttributeError):
        return []


def _drawing(folder: Path, report: dict) -> str:
    svg = folder / "plan.svg"
    if not svg.is_file():
        return ""
    facts = _facts(report, "layout")
    why = facts.get("error")  # an empty drawing says why
    note = f"<p class=note>Empty drawing: {html.escape(str(why))}</p>" if why else ""
    return _img(svg.read_bytes(), "image/svg+xml", "the architectural drawing") + note


def _cameras(folder: Path, report: dict) -> str:
    """The cameras seen from above: a dot at each centre, a wedge along its view."""
    from PIL import ImageDraw

    from stages.common.blueprint import Blueprint
    from stages.common.nerfstudio import GL_CV
    from stages.common.plan_picture import plan_picture

    cams = _transforms(folder)
    if not cams or not (folder / "blueprint.npz").is_file():
        return ""
    bp = Blueprint.load(folder / "blueprint.npz")
    img, box = plan_picture(bp)
    d = ImageDraw.Draw(img)
    h = bp.labels.shape[0]
    (ox, oy), cell, s = bp.grid.origin, bp.grid.cell, box.scale

    def px(x: float, y: float) -> tuple[float, float]:
        return box.x0 + (x - ox) / cell * s, box.y0 + (h - (y - oy) / cell) * s

    reach = 18.0  # wedge length in pixels
    for i, (c2w, half) in enumerate(cams):
        pose = np.asarray(c2w, np.float64) @ GL_CV  # OpenCV axes: column 2 = forward
        x, y = px(pose[0, 3], pose[1, 3])
        fwd = pose[:2, 2]
        norm = float(np.hypot(*fwd))
        if norm > 1e-6:
            a = math.atan2(-fwd[1], fwd[0])  # picture y runs down
            tips = [
                (x + reach * math.cos(a + t), y + reach * math.sin(a + t)) for t in (-half, half)
            ]
            d.polygon([(x, y), *tips], outline=(200, 0, 0), fill=(255, 120, 120))
        d.ellipse([x - 3, y - 3, x + 3, y + 3], fill=(160, 0, 0))
        if len(cams) <= LABEL_CAMERAS:
            d.text((x + 4, y + 2), str(i), fill=(0, 0, 0))
    buf = io.BytesIO()
    img.save(buf, "PNG")
    note = f"<p class=note>{len(cams)} cameras, numbered in capture order.</p>"
    return _img(buf.getvalue(), "image/png", "the cameras over the plan") + note


def _photos(folder: Path, report: dict) -> str:
    from PIL import Image

    paths = _image_paths(folder)
    if not paths:
        return ""
    pick = sorted({round(i) for i in np.linspace(0, len(paths) - 1, min(THUMBS, len(paths)))})
    figs, missing = [], 0
    for i in pick:
        p = paths[i]
        try:
            with Image.open(p) as src:
                w = max(1, round(src.width * THUMB_H / max(1, src.height)))
                thumb = src.convert("RGB").resize((w, THUMB_H), Image.Resampling.BILINEAR)
            buf = io.BytesIO()
            thumb.save(buf, "PNG", optimize=True)
        except OSError:
            missing += 1
            continue
        cap = html.escape(Path(p).stem)
        figs.append(f"<figure>{_img(buf.getvalue(), 'image/png', cap)}<figcaption>{cap}"
                    "</figcaption></figure>")  # fmt: skip
    shown = f"{len(figs)} of {len(paths)} photos" + (f"; {missing} unreadable" if missing else "")
    return f"<p class=note>{shown}</p><div class=strip>{''.join(figs)}</div>"


def _edits(folder: Path, report: dict) -> str:
    ed = folder / "edits"
    if not ed.is_dir():
        return ""
    views = sorted(p for p in ed.glob("*.png") if not p.name.startswith("blueprint"))
    out = []
    for p in views[:EDIT_VIEWS]:
        data = p.read_bytes()
        _check_png(data)
        out.append(f"<figure>{_img(data, 'image/png', p.stem)}<figcaption>{html.escape(p.stem)}"
                   ": before | after</figcaption></figure>")  # fmt: skip
    pics = []
    for name, kind in (("blueprint_edited.png", "image/png"), ("plan.svg", "image/svg+xml")):
        if (ed / name).is_file():
            pics.append(_img((ed / name).read_bytes(), kind, f"edited {name}"))
    gif = ed / "orbit.gif"
    if gif.is_file() and gif.stat().st_size <= GIF_MAX_BYTES:
        pics.append(_img(gif.read_bytes(), "image/gif", "the edited scene along an orbit"))
    elif gif.is_file():
        out.append(f"<p class=note>orbit: edits/orbit.gif ({gif.stat().st_size >> 20} MB)</p>")
    if not out and not pics:
        return ""
    return "".join(out) + (f"<div class=pics>{''.join(pics)}</div>" if pics else "")


# ---- tables --------------------------------------------------------------------------------
def _stages(folder: Path, report: dict) -> str:
    rows = ["<tr><th>stage</th><th>impl</th><th>status</th><th>why</th><th>seconds</th>"
            "<th>peak MB</th></tr>"]  # fmt: skip
    for s in report.get("stages", []):
        status = str(s.get("status", ""))
        color = STATUS_COLORS.get(status, "#fff")
        secs, mb = s.get("seconds"), s.get("peak_rss_mb")
        rows.append(
            f"<tr class=stage data-stage='{html.escape(str(s.get('name', '')))}'>"
            f"<td>{html.escape(str(s.get('name', '')))}</td>"
            f"<td>{html.escape(str(s.get('impl', '')))}</td>"
            f"<td class=status style='background:{color}'>{html.escape(status)}</td>"
            f"<td>{html.escape(str(s.get('reason') or ''))}</td>"
            f"<td class=n>{f'{secs:.1f}' if status == 'ran' and secs is not None else '–'}</td>"
            f"<td class=n>{f'{mb:.0f}' if isinstance(mb, (int, float)) else '–'}</td></tr>"
        )
    return f"<table>{''.join(rows)}</table>"


def _metrics(folder: Path, report: dict) -> str:
    flat = _flatten(report.get("metrics") or {})
    if not flat:
        return "<p class=note>No metrics: the capture has no ground truth to score against.</p>"
    rows = "".join(
        f"<tr class=metric><td>{html.escape(k)}</td><td class=n>{html.escape(_value(v))}</td></tr>"
        for k, v in flat
    )
    return f"<table>{rows}</table>"


def _flatten(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted name, value) of every leaf; short lists of numbers stay one value."""
    if isinstance(d, dict):
        out: list[tuple[str, Any]] = []
        for k, v in d.items():
            out += _flatten(v, f"{prefix}{k}.")
        return out
    return [(prefix[:-1], d)]


def _value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
    if isinstance(v, list):
        text = json.dumps(v)
        return text if len(text) <= 120 else text[:117] + "..."
    return str(v)


# ---- helpers -------------------------------------------------------------------------------
def _img(data: bytes, mime: str, alt: str) -> str:
    b64 = base64.b64encode(data).decode("ascii")
    return f"<img src='data:{mime};base64,{b64}' alt='{html.escape(alt, quote=True)}'>"


def _check_png(data: bytes) -> None:
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise ValueError("not a PNG file")


def _transforms(folder: Path) -> list[tuple[list, float]]:
    """(camera-to-world in nerfstudio's OpenGL axes, half horizontal field of view) a frame."""
    p = folder / "transforms.json"
    if not p.is_file():
        return []
    t = json.loads(p.read_text())
    out = []
    for f in t.get("frames", []):
        fx, w = f.get("fl_x", t.get("fl_x")), f.get("w", t.get("w"))
        half = math.atan2(w / 2, fx) if fx and w else math.radians(30)
        out.append((f["transform_matrix"], half))
    return out


def _image_paths(folder: Path) -> list[Path]:
    p = folder / "transforms.json"
    if not p.is_file():
        return []
    frames = json.loads(p.read_text()).get("frames", [])
    return [Path(f["file_path"]) if Path(f["file_path"]).is_absolute()
            else folder / f["file_path"] for f in frames]  # fmt: skip


def _facts(report: dict, stage: str) -> dict:
    for s in report.get("stages", []):
        if s.get("name") == stage and isinstance(s.get("facts"), dict):
            return s["facts"]
    return {}


def _short(e: Exception) -> str:
    return (str(e).splitlines() or [type(e).__name__])[0][:200]


_SECTIONS: list[tuple[str, Callable[[Path, dict], str]]] = [
    ("Plan", _plan),
    ("Architectural drawing", _drawing),
    ("Cameras seen from above", _cameras),
    ("Stages", _stages),
    ("Metrics", _metrics),
    ("Input photos", _photos),
    ("Edits", _edits),
]

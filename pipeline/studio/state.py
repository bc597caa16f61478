"""The studio's session: the selection, the applied edits (undo / redo), save and load.

Kept apart from the web page so that it can be tested without a browser. Edits are held as
entries of an edit spec (`stages/edit/spec.py`, the YAML the pipeline reads) and checked by
the same parser; a bad request (a click off the plan or on an unknown cell, a sketch with
no stroke, an upload that is not an image) raises a one-line BlunfError and changes nothing.

The page is a client like any other (viser does not check a dropdown's value against its
options, nor a slider's against its range): every value it sends is checked here against what
the server offered (`pipeline.studio.values`), and every path is resolved and checked
inside the studio's folder before any file is written.
"""

from __future__ import annotations

import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError

from pipeline.publish import STUDIO
from pipeline.render import RunFiles, Scene, run_files
from pipeline.studio.values import OPS, STRENGTH, WIDTH, floor_point, in_range, inside, offered, rgb
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.edit.select import select_cells
from stages.edit.spec import Edit, Selector, load_spec, parse_spec

SPEC_NAME = "studio.yaml"
TEXTURES = Path(__file__).resolve().parents[2] / "configs" / "edits" / "textures"
MAX_UPLOAD = 20_000_000  # bytes
BOMB = Image.DecompressionBombError  # PIL's refusal of a header claiming too many pixels
MAX_UPLOAD_PIXELS = 4096 * 4096  # an upload's pixels (a texture; a larger one: refused)
MAX_STROKE = 10_000  # points of a sketch's stroke


@dataclass(frozen=True)
class Selection:
    """What is selected: the spec's `select` entry, the cells, and what they are."""

    select: dict  # e.g. {"click": [x, y]} or {"class": "sofa"}
    cells: np.ndarray  # bool [H, W]
    info: dict  # class, instance, area_m2, bbox [xmin, ymin, xmax, ymax] (metres), cells


class Session:
    """One run open in the studio; every tab shares it (methods hold `lock`)."""

    def __init__(self, run: Path):
        self.files: RunFiles = run_files(run)
        self.scene = Scene(self.files)
        # where the spec, its textures and renders are kept: outside the published run (a
        # rerun replaces RUN/edits), never removed by a run (pipeline/publish.py)
        self.folder = self.files.run / STUDIO
        self.edits: list[dict] = []
        self.uploaded: list[str] = []  # textures uploaded from the page (offered with shipped)
        self.undone: list[dict] = []
        self.selection: Selection | None = None
        self.stroke: list[tuple[float, float]] = []
        self.lock = threading.RLock()
        self.version = 0  # bumped on every change of the edits (renders compare it)

    def reload(self) -> None:
        """Read the run folder again (after a run trained its NeRF); the edits stay."""
        with self.lock:
            self.files = run_files(self.files.run)
            self.scene = Scene(self.files)
            self.selection = None
            self.version += 1

    # ---- selection -----------------------------------------------------------------------
    def _select(self, select: dict) -> Selection:
        kind, value = next(iter(select.items()))
        sel = Selector(kind, tuple(value) if isinstance(value, list) else value, where="select")
        cells = select_cells(sel, self.scene.bp, self.scene.cmap)
        return Selection(select, cells, self._info(cells))

    def _info(self, cells: np.ndarray) -> dict:
        bp = self.scene.bp
        ids = np.unique(self.scene.cmap[cells])
        comps = [self.scene.components[int(i)] for i in ids if int(i) in self.scene.components]
        rows, cols = np.nonzero(cells)
        (ox, oy), cell, h = bp.grid.origin, bp.grid.cell, bp.grid.shape[0]
        classes = sorted({c["class"] for c in comps})
        return {
            "class": ", ".join(classes),
            "instance": sorted({c["instance"] for c in comps}),
            "components": len(comps),
            "cells": int(cells.sum()),
            "area_m2": round(float(cells.sum()) * cell * cell, 3),
            "bbox": [
                round(ox + cols.min() * cell, 3),
                round(oy + (h - 1 - rows.max()) * cell, 3),
                round(ox + (cols.max() + 1) * cell, 3),
                round(oy + (h - rows.min()) * cell, 3),
            ],
        }

    def click(self, x: float, y: float) -> Selection:
        """Select the component under world point (x, y), as a spec's `click` does."""
        with self.lock:
            s = self._select({"click": [round(float(x), 4), round(float(y), 4)]})
            self.selection = s
            return s

    def click_ray(self, origin: Any, direction: Any) -> Selection:
        return self.click(*floor_point(origin, direction))

    def select_class(self, name: str) -> Selection:
        with self.lock:
            offered(name, self.classes(), "class")
            s = self._select({"class": name})
            self.selection = s
            return s

    def classes(self) -> list[str]:
        lab = self.scene.bp.labels
        present = {int(c) for c in np.unique(lab) if c != UNKNOWN}
        return sorted({n for k, n in self.scene.bp.classes.items() if k in present})

    # ---- sketch strokes ------------------------------------------------------------------
    def add_stroke_point(self, x: float, y: float, min_step: float = 0.0) -> int:
        """Add a point to the stroke (none closer than `min_step` metres to the last one);
        returns the stroke's length."""
        with self.lock:
            try:
                x, y = float(x), float(y)
            except (TypeError, ValueError):
                x = y = float("nan")
            if not (np.isfinite(x) and np.isfinite(y)):
                raise BlunfError("stroke: not a point on the plan")
            if len(self.stroke) >= MAX_STROKE:
                raise BlunfError(f"stroke: {MAX_STROKE} points at most")
            p = (round(float(x), 4), round(float(y), 4))
            last = self.stroke[-1] if self.stroke else None
            if last is None or np.hypot(p[0] - last[0], p[1] - last[1]) >= max(min_step, 1e-9):
                self.stroke.append(p)
            return len(self.stroke)

    def clear_stroke(self) -> None:
        with self.lock:
            self.stroke = []

    # ---- textures ------------------------------------------------------------------------
    def shipped_textures(self) -> list[str]:
        return sorted(p.name for p in TEXTURES.glob("*.png")) if TEXTURES.is_dir() else []

    def textures(self) -> list[str]:
        """The textures the page offers: the shipped ones and this session's uploads."""
        return list(dict.fromkeys([*self.shipped_textures(), *self.uploaded]))

    def add_texture(self, name: str, content: bytes) -> str:
        """Keep an uploaded image among the spec's textures; returns its name there. Raises
        (nothing kept) when it is not a readable image."""
        import io

        if len(content) > MAX_UPLOAD:
            raise BlunfError(f"{name}: the upload is larger than {MAX_UPLOAD // 1_000_000} MB")
        try:
            with Image.open(io.BytesIO(content)) as img:
                img.verify()
            with Image.open(io.BytesIO(content)) as img:
                if img.width * img.height > MAX_UPLOAD_PIXELS:
                    raise BlunfError(
                        f"{name}: {img.width}x{img.height} pixels, more than a texture needs "
                        f"({MAX_UPLOAD_PIXELS} at most)"
                    )
                pixels = img.convert("RGB")
        except (
            UnidentifiedImageError,
            OSError,
            SyntaxError,
            ValueError,
            Image.DecompressionBombError,
        ):
            raise BlunfError(f"{name}: not an image (PNG or JPEG expected)") from None
        stem = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in Path(str(name)).stem)
        dst = inside(self.folder / "textures", f"{stem[:64] or 'upload'}.png", "upload")
        dst.parent.mkdir(parents=True, exist_ok=True)
        pixels.save(dst)
        with self.lock:
            self.uploaded = list(dict.fromkeys([*self.uploaded, dst.name]))
        return dst.name

    def _texture(self, name: str) -> tuple[str, Path | None]:
        """The texture's path relative to the spec's folder, and the file copied there (when
        a shipped one was copied). Checked, before any file is touched: one of the textures
        offered, a plain name resolving inside the spec's textures/ (and the shipped one's
        inside the shipped folder)."""
        offered(name, self.textures(), "texture")
        dst = inside(self.folder / "textures", name, "texture")
        copied = None
        if not dst.is_file():
            src = inside(TEXTURES, name, "texture")
            if not src.is_file():
                raise BlunfError(f"texture {name}: not found (shipped: {self.shipped_textures()})")
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            copied = dst
        return f"textures/{name}", copied

    # ---- edits ---------------------------------------------------------------------------
    def entry(self, op: str, **kw: Any) -> dict:
        """The spec entry `op` on the selection (or on the stroke for a sketch), its values
        checked against what the page offers; a texture is not copied here (`apply`)."""
        offered(op, OPS, "operation")
        if op == "sketch":
            if len(self.stroke) < 2:
                raise BlunfError("sketch: draw a stroke first (two points or more on the plan)")
            select: dict = {"stroke": [list(p) for p in self.stroke]}
            select["width"] = in_range(kw.pop("width", 0.1), *WIDTH, "stroke width")
        else:
            if self.selection is None:
                raise BlunfError(f"{op}: select something on the plan first")
            select = dict(self.selection.select)
        e: dict = {"select": select, "op": op}
        if op in ("recolor", "sketch"):
            e["color"] = rgb(kw.get("color"))
        if op in ("recolor", "sketch", "retexture"):
            e["strength"] = round(in_range(kw.get("strength", 1.0), *STRENGTH, "strength"), 3)
        if op == "retexture":
            name = kw.get("texture")
            offered(name, self.textures(), "texture")
            inside(self.folder / "textures", name, "texture")
            e["texture"] = f"textures/{name}"
        return e

    def apply(self, op: str, **kw: Any) -> Edit:
        """Add an edit; checked (spec and plan) before anything changes."""
        with self.lock:
            e = self.entry(op, **kw)
            copied = self._texture(kw["texture"])[1] if op == "retexture" else None
            try:
                parsed = self._parse(self.edits + [e])[-1]
                self.scene.selection(parsed)  # a selection on no known cell fails here
            except BlunfError:
                if copied is not None:  # not applied: nothing of it kept
                    copied.unlink(missing_ok=True)
                raise
            self.edits.append(e)
            self.undone = []
            if op == "sketch":
                self.stroke = []
            self.version += 1
            return parsed

    def undo(self) -> bool:
        with self.lock:
            if not self.edits:
                return False
            self.undone.append(self.edits.pop())
            self.version += 1
            return True

    def redo(self) -> bool:
        with self.lock:
            if not self.undone:
                return False
            self.edits.append(self.undone.pop())
            self.version += 1
            return True

    def _parse(self, entries: list[dict]) -> tuple[Edit, ...]:
        return parse_spec({"edits": entries}, self.folder / SPEC_NAME).edits if entries else ()

    def parsed(self) -> tuple[Edit, ...]:
        with self.lock:
            return self._parse(self.edits)

    def describe(self) -> list[str]:
        out = []
        for i, e in enumerate(self.edits):
            kind, value = next((k, v) for k, v in e["select"].items() if k != "width")
            what = f"{kind} {value}" if kind != "stroke" else f"stroke of {len(value)} points"
            extra = ""
            if "color" in e:
                extra = f" colour {e['color']}"
            if "texture" in e:
                extra = f" texture {Path(e['texture']).name}"
            out.append(f"{i + 1}. {e['op']} ({what}){extra}")
        return out

    # ---- save / load ---------------------------------------------------------------------
    def spec_data(self, views: list[int]) -> dict:
        with self.lock:
            return {"edits": [dict(e) for e in self.edits], "views": list(views) or [0]}

    def save(self, views: list[int]) -> Path:
        """Write RUN/studio/studio.yaml (views: the input views the run renders)."""
        with self.lock:
            if not self.edits:
                raise BlunfError("save: no edits to save")
            data = self.spec_data(views)
            path = self.folder / SPEC_NAME
            parse_spec(data, path)
            self.folder.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{SPEC_NAME}.tmp")
            header = (
                "# Saved by blunf studio. Reproduce its renders with:\n"
                f"#   blunf run {self.files.capture} --out {self.files.run} "
                f"--edits {path}\n"
            )
            tmp.write_text(header + yaml.safe_dump(data, sort_keys=False))
            tmp.replace(path)
            return path

    def load(self, path: Path | None = None) -> int:
        """Replace the session's edits by a saved spec's; returns how many."""
        path = Path(path) if path is not None else self.folder / SPEC_NAME
        with self.lock:
            spec = load_spec(path)  # one-line error on a bad spec, nothing changed
            for e in spec.edits:
                self.scene.selection(e)
            data = yaml.safe_load(path.read_text())
            if spec.textures and path.resolve().parent != self.folder.resolve():
                raise BlunfError(f"{path}: a spec with textures must lie in {self.folder}")
            self.edits = [dict(e) for e in data["edits"]]
            self.undone = []
            self.version += 1
            return len(self.edits)

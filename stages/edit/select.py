"""Selections on the plan and their 3-D extent.

A selection is a set of plan cells: the component under a click or a cell (same class,
8-connected, `stages.common.components.component_map`), every component of a class, or the
known cells whose centres fall inside a polygon or a stroke (a polyline buffered by half its
width). Unknown cells (255) are never selected.

Its extent is a height range per cell: each selected cell takes the range of its component,
measured on the fused geometry (mesh vertices, z up, floor at z = 0) over the component's
inner cells: from `floor_clear` above the floor (so removing a chair keeps the floor under
it) up to the top of the first substantial run of vertices above the floor band, a run ending
at a vertical gap of `gap` metres (so the ceiling above is not part of the chair). A
component of the floor class keeps its own slab |z| <= floor_band. The footprint then grows
by `pad` metres, the new cells taking their neighbours' ranges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
import torch
from shapely.geometry import LineString, Polygon
from torch import Tensor

from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN
from stages.common.classes import FLOOR_NAME
from stages.common.components import class_name
from stages.common.errors import BlunfError
from stages.edit.config import EditConfig
from stages.edit.spec import EditSpec, Selector

NEIGHBOURS = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]


@dataclass(frozen=True)
class Extent:
    """A selection in 3-D: cell (r, c) of `grid` spans z in [zlo, zhi] (empty when zlo > zhi)."""

    grid: Grid
    zlo: np.ndarray  # [H, W] float32, +inf outside the selection
    zhi: np.ndarray  # [H, W] float32, -inf outside the selection

    @property
    def footprint(self) -> np.ndarray:
        """Cells of the selection. Returns bool [H, W]."""
        return self.zlo <= self.zhi

    def _cells(self, xy: Tensor) -> tuple[Tensor, Tensor]:
        """Flat cell index [N] (clipped) and inside-the-grid [N] of world points xy [N, >= 2]."""
        (ox, oy), cell = self.grid.origin, self.grid.cell
        h, w = self.grid.shape
        col = torch.floor((xy[:, 0] - ox) / cell).long()  # [N]
        row = h - 1 - torch.floor((xy[:, 1] - oy) / cell).long()  # [N]
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        return row.clamp(0, h - 1) * w + col.clamp(0, w - 1), inside

    def contains(self, x: np.ndarray | Tensor) -> np.ndarray | Tensor:
        """Which world points x [N, 3] lie inside; bool [N], numpy or torch as x."""
        xt = torch.as_tensor(x)
        flat, inside = self._cells(xt)
        zlo = torch.from_numpy(self.zlo).view(-1)[flat]
        zhi = torch.from_numpy(self.zhi).view(-1)[flat]
        z = xt[:, 2]
        res = inside & (z >= zlo) & (z <= zhi)
        return res.numpy() if isinstance(x, np.ndarray) else res

    def over(self, xy: np.ndarray | Tensor) -> np.ndarray | Tensor:
        """Which world points xy [N, 2] lie over the footprint (any height); bool [N]."""
        flat, inside = self._cells(torch.as_tensor(xy))
        res = inside & torch.from_numpy(self.footprint).view(-1)[flat]
        return res.numpy() if isinstance(xy, np.ndarray) else res

    def bbox(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in metres of the footprint's cells."""
        rows, cols = np.nonzero(self.footprint)
        (ox, oy), cell, h = self.grid.origin, self.grid.cell, self.grid.shape[0]
        return (
            ox + cols.min() * cell,
            oy + (h - 1 - rows.max()) * cell,
            ox + (cols.max() + 1) * cell,
            oy + (h - rows.min()) * cell,
        )


def select_cells(sel: Selector, bp: Blueprint, cmap: np.ndarray) -> np.ndarray:
    """The plan cells a selector picks. Returns bool [H, W]; raises when it picks none."""
    lab = bp.labels
    h, w = bp.grid.shape
    where = f"{sel.where}.{sel.kind}"
    if sel.kind in ("click", "pixel"):
        if sel.kind == "click":
            row, col, inside = bp.grid.cell_of(np.asarray([sel.value], np.float64))
            r, c, ok = int(row[0]), int(col[0]), bool(inside[0])
            if not ok:
                (x0, y0), cell = bp.grid.origin, bp.grid.cell
                raise BlunfError(
                    f"{where}: ({sel.value[0]:g}, {sel.value[1]:g}) lies outside the plan "
                    f"(x {x0:g}..{x0 + w * cell:g}, y {y0:g}..{y0 + h * cell:g} m)"
                )
        else:
            c, r = sel.value
            if c >= w or r >= h:
                raise BlunfError(f"{where}: [{c}, {r}] lies outside the plan ({w} x {h} cells)")
        if cmap[r, c] == 0:
            raise BlunfError(f"{where}: lands on an unknown (unseen) cell of the plan")
        return cmap == cmap[r, c]
    if sel.kind == "class":
        ids = [k for k, n in bp.classes.items() if n == sel.value]
        if not ids:
            names = ", ".join(sorted(set(bp.classes.values())))
            raise BlunfError(f"{where}: no class {sel.value!r} in the plan (classes: {names})")
        cells = np.isin(lab, ids)
        if not cells.any():
            raise BlunfError(f"{where}: no cell of class {sel.value!r} on the plan")
        return cells
    if sel.kind == "polygon":
        shape = Polygon(sel.value).buffer(0)
    else:
        shape = LineString(sel.value).buffer(sel.width / 2)
    xy = bp.grid.centers()  # [H, W, 2]
    cells = shapely.contains_xy(shape, xy[..., 0], xy[..., 1]) & (lab != UNKNOWN)
    if not cells.any():
        raise BlunfError(f"{where}: covers no known cell of the plan")
    return cells


def extent_of(
    cells: np.ndarray, bp: Blueprint, cmap: np.ndarray, vertices: np.ndarray, cfg: EditConfig
) -> tuple[Extent, list[dict]]:
    """The 3-D extent of selected cells [H, W] over the fused geometry `vertices` [N, 3].

    Returns the extent and, per component touched, its id, class, cells selected, height
    range and how it was measured.
    """
    zlo = np.full(bp.grid.shape, np.inf, np.float32)  # [H, W]
    zhi = np.full(bp.grid.shape, -np.inf, np.float32)  # [H, W]
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    rows, cols, inside = bp.grid.cell_of(v[:, :2])
    vcomp = np.where(inside, cmap[rows, cols], 0)  # [N] component under each vertex
    vinner = np.where(inside, _inner(cmap)[rows, cols], 0)  # [N] ... when an inner cell
    info = []
    for cid in np.unique(cmap[cells]):
        if cid == 0:
            continue
        part = cells & (cmap == cid)
        r0, c0 = np.argwhere(part)[0]
        cls = class_name(bp, int(bp.labels[r0, c0]))
        if cls == cfg.select.floor_class:
            lo, hi, how = -cfg.select.floor_band, cfg.select.floor_band, "floor slab"
        else:
            z = v[vinner == cid, 2]
            how = "inner cells"
            if len(z) == 0:
                z, how = v[vcomp == cid, 2], "all cells (no vertex over the inner cells)"
            lo, hi = cfg.select.floor_clear, np.inf
            if len(z) == 0:
                how = "no fused geometry over it: the whole column above the floor"
            else:
                hi = _top(z, cfg) + cfg.select.top_margin
        zlo[part], zhi[part] = lo, hi
        info.append(
            {
                "component": int(cid),
                "class": cls,
                "cells": int(part.sum()),
                "z_range": [round(float(lo), 4), round(float(hi), 4) if np.isfinite(hi) else None],
                "measured_on": how,
            }
        )
    for _ in range(int(round(cfg.select.pad / bp.grid.cell))):
        zlo, zhi = _grow(zlo, zhi)
    return Extent(bp.grid, zlo, zhi), info


def _top(z: np.ndarray, cfg: EditConfig) -> float:
    """Top of an object from the heights z [N] of the vertices over it: the highest vertex of
    the first run (runs split at gaps > cfg.select.gap) holding >= min_run of the vertices above the
    floor band; the floor band itself when nothing stands above it."""
    z = np.sort(z[z > cfg.select.floor_band])
    if len(z) == 0:
        return cfg.select.floor_band
    runs = np.split(z, np.flatnonzero(np.diff(z) > cfg.select.gap) + 1)
    need = cfg.select.min_run * len(z)
    run = next((r for r in runs if len(r) >= need), max(runs, key=len))
    return float(run[-1])


def _inner(cmap: np.ndarray) -> np.ndarray:
    """Component ids kept only where all 8 neighbours share them (0 elsewhere). [H, W]"""
    pad = np.pad(cmap, 1)
    h, w = cmap.shape
    same = np.ones(cmap.shape, bool)
    for dr, dc in NEIGHBOURS:
        same &= pad[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w] == cmap
    return np.where(same, cmap, 0)


def _grow(zlo: np.ndarray, zhi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One ring of cells around the selection, each taking the widest range of its selected
    neighbours."""
    h, w = zlo.shape
    free = zlo > zhi
    lo_p = np.pad(zlo, 1, constant_values=np.inf)
    hi_p = np.pad(zhi, 1, constant_values=-np.inf)
    new_lo, new_hi = zlo.copy(), zhi.copy()
    for dr, dc in NEIGHBOURS:
        nl = lo_p[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w]
        nh = hi_p[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w]
        new_lo = np.where(free, np.minimum(new_lo, nl), new_lo)
        new_hi = np.where(free, np.maximum(new_hi, nh), new_hi)
    return new_lo, new_hi


# ---- the edited plan ----------------------------------------------------------------------
def edited_plan(
    cfg: EditConfig, bp: Blueprint, spec: EditSpec, cells: list[np.ndarray]
) -> tuple[Blueprint, int]:
    """The plan with removed selections relabelled (floor or unknown; no instance). Returns
    it and the number of cells changed.

    `seen` and `inside` describe the capture, not the labels: they are kept as they are. A
    removed object's cells become floor only inside the room's outline (when the plan knows
    it); outside it they stay unknown, as every cell outside the outline is."""
    lab = bp.labels.copy()
    room = np.ones(lab.shape, bool) if bp.inside is None else bp.inside > 0
    inst = None if bp.instances is None else bp.instances.copy()
    floor_ids = [k for k, n in bp.classes.items() if n == cfg.select.floor_class]
    for e, sel in zip(spec.edits, cells, strict=True):
        if e.op != "remove":
            continue
        if cfg.removed_label == FLOOR_NAME and floor_ids:
            is_floor = np.isin(bp.labels, floor_ids)
            lab[sel & ~is_floor & room] = floor_ids[0]
            lab[sel & (is_floor | ~room)] = UNKNOWN
        else:
            lab[sel] = UNKNOWN
        if inst is not None:
            inst[sel] = 0
    new = Blueprint(lab, bp.grid, dict(bp.classes), inst, bp.seen, bp.inside)
    return new, int((lab != bp.labels).sum())

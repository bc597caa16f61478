"""Blueprint instances: connected components of one class, as cells and as exact polygons.

A component is a maximal 8-connected set of cells of one class (the paper's click selects
the component under the pointer) and, when the plan has an instance layer, of one object
instance: two chairs that touch are two components. Unknown cells (255) belong to none.
Polygons follow the cell edges exactly: cell corner (column c, row r) is world
(origin_x + c * cell, origin_y + (H - r) * cell).
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry.base import BaseGeometry
from skimage import measure

from stages.common.blueprint import Blueprint
from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError


def class_name(bp: Blueprint, class_id: int) -> str:
    """The class name from the plan's table, or `class_<id>` when the table lacks it."""
    return bp.classes.get(int(class_id), f"class_{int(class_id)}")


def _labels(bp: Blueprint) -> np.ndarray:
    """The plan's labels after checking they (and its instances) fit the grid. uint8 [H, W]"""
    lab = np.asarray(bp.labels)
    if lab.ndim != 2 or lab.dtype != np.uint8:
        raise BlunfError(f"blueprint labels must be uint8 [H, W], got {lab.dtype} {lab.shape}")
    if lab.size == 0:
        raise BlunfError(f"blueprint has no cells (shape {lab.shape})")
    if tuple(lab.shape) != tuple(bp.grid.shape):
        raise BlunfError(f"blueprint labels {lab.shape} do not match grid {bp.grid.shape}")
    if not bp.grid.cell > 0:
        raise BlunfError(f"blueprint cell must be > 0 metres, got {bp.grid.cell}")
    if bp.instances is not None and np.shape(bp.instances) != lab.shape:
        raise BlunfError(
            f"blueprint instances {np.shape(bp.instances)} do not match labels {lab.shape}"
        )
    return lab


def _instances(bp: Blueprint) -> np.ndarray:
    """The instance of every cell (0 = none; all 0 when the plan has no instance layer)."""
    if bp.instances is None:
        return np.zeros(bp.labels.shape, np.int64)
    return np.asarray(bp.instances, np.int64)


def component_map(bp: Blueprint) -> np.ndarray:
    """Component id of every cell (0 = unknown), ids 1.. in raster order. Returns int32 [H, W].

    Cells join when 8-connected with the same class and the same instance.
    """
    lab = _labels(bp)
    # One key per (class, instance); 0 = unknown, so class 0 is a class like any other.
    key = np.where(lab == UNKNOWN, 0, _instances(bp) * 256 + lab.astype(np.int64) + 1)
    return measure.label(key, background=0, connectivity=2).astype(np.int32)


def _r(v: float) -> float:
    """A world coordinate rounded to the nanometre (drops float noise such as 0.15000000002)."""
    return round(float(v), 9)


def _components(bp: Blueprint, cmap: np.ndarray, min_area_m2: float) -> list[dict]:
    lab, inst = bp.labels, _instances(bp)
    (ox, oy), cell, h = bp.grid.origin, bp.grid.cell, bp.grid.shape[0]
    out = []
    for reg in measure.regionprops(cmap):
        cells = int(reg.area)
        area = cells * cell * cell
        if area < min_area_m2:
            continue
        r0, c0, r1, c1 = reg.bbox  # rows / cols, end exclusive
        rc, cc = reg.centroid  # mean (row, col) of the cells' indices
        first = tuple(reg.coords[0])
        cls = int(lab[first])
        out.append(
            {
                "id": int(reg.label),
                "class_id": cls,
                "class": class_name(bp, cls),
                "instance": int(inst[first]),
                "cells": cells,
                "area_m2": _r(area),
                "centroid": [_r(ox + (cc + 0.5) * cell), _r(oy + (h - rc - 0.5) * cell)],
                "bbox": [
                    _r(ox + c0 * cell),
                    _r(oy + (h - r1) * cell),
                    _r(ox + c1 * cell),
                    _r(oy + (h - r0) * cell),
                ],
            }
        )
    return out


def components(bp: Blueprint, min_area_m2: float = 0.0) -> list[dict]:
    """The plan's components, by id (ids are those of `component_map`).

    Each: id, class_id, class, instance (0 = none), cells, area_m2, centroid [x, y] and bbox
    [xmin, ymin, xmax, ymax] in world metres. Components smaller than `min_area_m2` are left
    out (their ids too).
    """
    return _components(bp, component_map(bp), float(min_area_m2))


def _runs(cmap: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Horizontal runs of equal non-zero id: (row, col0, col1 exclusive, id), each [N]."""
    h, w = cmap.shape
    pad = np.pad(cmap, ((0, 0), (1, 1)))  # [H, W + 2], 0 on both sides of every row
    row, j = np.nonzero(pad[:, 1:] != pad[:, :-1])  # boundary before column j, j in 0..W
    ids = cmap[row, np.minimum(j, w - 1)]
    start = np.flatnonzero((j < w) & (ids != 0))
    # A run of a non-zero id always ends on a boundary of its own row (at worst the pad at W).
    return row[start], j[start], j[start + 1], ids[start]


def _polygonal(g: BaseGeometry) -> BaseGeometry:
    """Valid polygonal geometry: make_valid, then keep only the (multi)polygon parts."""
    if g.is_valid:
        return g
    g = shapely.make_valid(g)
    parts = [p for p in shapely.get_parts(g) if p.geom_type in ("Polygon", "MultiPolygon")]
    return shapely.union_all(parts)


def component_geometries(
    bp: Blueprint, tolerance_m: float = 0.0, cmap: np.ndarray | None = None
) -> dict[int, BaseGeometry]:
    """Component id -> (Multi)Polygon in world metres, exterior counter-clockwise.

    Exact union of the component's cells, simplified (Douglas-Peucker, topology kept) by
    `tolerance_m` metres; tolerance 0 only drops collinear corners. A component whose cells
    touch only at a corner (8-connectivity) is a MultiPolygon whose parts meet at that point.
    `cmap` is `component_map(bp)` when the caller has it already.
    """
    if not tolerance_m >= 0:
        raise BlunfError(f"polygon tolerance must be >= 0 metres, got {tolerance_m}")
    cmap = component_map(bp) if cmap is None else cmap  # [H, W]
    (ox, oy), cell, h = bp.grid.origin, bp.grid.cell, bp.grid.shape[0]
    row, c0, c1, ids = _runs(cmap)
    if len(ids) == 0:
        return {}
    # Work on the integer lattice (u = column, v = H - row) where the union is exact.
    boxes = shapely.box(c0, h - row - 1, c1, h - row)  # [N]
    order = np.argsort(ids, kind="stable")
    ids, boxes = ids[order], boxes[order]
    cut = np.flatnonzero(np.diff(ids)) + 1
    out = {}
    for cid, group in zip(ids[np.r_[0, cut]], np.split(boxes, cut), strict=True):
        g = group[0] if len(group) == 1 else shapely.union_all(group)
        g = _polygonal(shapely.simplify(g, tolerance_m / cell, preserve_topology=True))
        g = shapely.transform(g, lambda uv: (uv * cell + np.array([ox, oy])).round(9))
        out[int(cid)] = shapely.orient_polygons(g)
    return out


def polygons(bp: Blueprint, tolerance_m: float = 0.02, min_area_m2: float = 0.0) -> list[dict]:
    """Each component as a polygon with holes: the `components` entry plus `geometry`.

    `geometry` is a shapely Polygon or MultiPolygon in world metres (see
    `component_geometries`); `area_m2` stays the exact cell area.
    """
    cmap = component_map(bp)  # [H, W]
    geoms = component_geometries(bp, tolerance_m, cmap)
    comps = _components(bp, cmap, float(min_area_m2))
    return [{**c, "geometry": geoms[c["id"]]} for c in comps]


def rings(geom: BaseGeometry) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """(exterior [N, 2], holes [[M, 2], ...]) of every polygon part; rings are closed."""
    out = []
    for p in shapely.get_parts(geom):
        if p.geom_type != "Polygon" or p.is_empty:
            continue
        holes = [np.asarray(i.coords)[:, :2] for i in p.interiors]
        out.append((np.asarray(p.exterior.coords)[:, :2], holes))
    return out


def plan_summary(bp: Blueprint, min_area_m2: float = 0.0) -> dict:
    """The plan for report.json: grid, per-class area and component count, the components."""
    lab = _labels(bp)
    comps = components(bp, min_area_m2)
    cell2 = bp.grid.cell**2
    ids, counts = np.unique(lab[lab != UNKNOWN], return_counts=True)
    classes = {}
    for cid, n in zip(ids.tolist(), counts.tolist(), strict=True):
        classes[class_name(bp, cid)] = {
            "class_id": cid,
            "area_m2": _r(n * cell2),
            "cells": n,
            "components": sum(c["class_id"] == cid for c in comps),
        }
    unknown = int((lab == UNKNOWN).sum())
    return {
        "grid": bp.grid.to_json(),
        "known_area_m2": _r((lab.size - unknown) * cell2),
        "unknown_area_m2": _r(unknown * cell2),
        "classes": classes,
        "min_area_m2": float(min_area_m2),
        "components": comps,
    }


def with_heights(summary: dict, objects: list[dict]) -> dict:
    """`plan_summary` with each object component's `height` (its highest point) and `top` (its
    upper surface), metres above the floor, from the layout's plan.json objects of the same
    instance (None where no object of that instance was drawn: no mesh, or too small)."""
    by_inst = {int(o["instance"]): o for o in objects if o.get("instance")}
    comps = []
    for c in summary["components"]:
        o = by_inst.get(int(c["instance"])) if c["instance"] else None
        if c["instance"]:
            c = {**c, "height": o and o.get("height"), "top": o and o.get("top")}
        comps.append(c)
    return {**summary, "components": comps}

"""The export stage: the files a user takes away (plan picture, vector plans, mesh, poses)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

from shapely.errors import GEOSException

from stages.common.blueprint import Blueprint
from stages.common.capture import Capture
from stages.common.components import plan_summary, polygons, with_heights
from stages.common.io import read_json, write_json
from stages.common.nerfstudio import write_transforms
from stages.common.plan_picture import plan_png
from stages.export.config import ExportConfig, ExportInputs, ExportOutputs
from stages.export.picture import architect_png
from stages.export.vector import write_dxf, write_geojson, write_svg


def run(cfg: ExportConfig, inputs: ExportInputs, out: Path) -> ExportOutputs:
    bp = Blueprint.load(inputs.blueprint)
    shutil.copyfile(inputs.blueprint, out / "blueprint.npz")
    _picture(bp, inputs, out / "blueprint.png", cfg.title)
    # the vector plans in the capture's own (aligned) world: the offset ingest took off far
    # poses put back (Capture.origin); the raster and the run's own files stay near 0
    world = put_back(bp, Capture.load(inputs.frames).origin)
    polys = polygons(world, cfg.tolerance)  # traced once, written in three formats
    write_svg(world, out / "blueprint.svg", title=cfg.title, polys=polys)
    write_geojson(world, out / "blueprint.geojson", polys=polys)
    write_dxf(world, out / "blueprint.dxf", polys=polys)
    summary = plan_summary(bp, min_area_m2=cfg.min_area)
    if inputs.layout and Path(inputs.layout).is_file():  # object heights from the plan
        summary = with_heights(summary, read_json(inputs.layout).get("objects", []))
    write_json(out / "components.json", summary)
    write_json(
        out / "export.json",
        {
            "components": len(summary["components"]),
            "classes": {k: v["area_m2"] for k, v in summary["classes"].items()},
        },
    )
    shutil.copyfile(inputs.mesh, out / "mesh.ply")
    write_transforms(Capture.load(inputs.frames), out / "transforms.json")
    return ExportOutputs.at(out)


def _picture(bp: Blueprint, inputs: ExportInputs, path: Path, title: str) -> None:
    """blueprint.png: the classes with the architectural plan over them; the classes alone
    when the plan has no room (nothing to draw over them)."""
    try:
        # the layout stage's plan (a stage reads another's outputs, never its code): without
        # one, the classes alone
        plan = read_json(inputs.layout) if inputs.layout and Path(inputs.layout).is_file() else {}
        if plan.get("rooms"):
            architect_png(bp, plan, path, title)
            return
    except GEOSException:
        pass  # the layout stage says why in its layout.json; the plain picture stands
    plan_png(bp, path, title=title)


def put_back(bp: Blueprint, origin: tuple[float, float, float]) -> Blueprint:
    """The blueprint with its grid moved by the capture's offset (x, y)."""
    if not any(origin[:2]):
        return bp
    g = bp.grid
    grid = replace(g, origin=(g.origin[0] + origin[0], g.origin[1] + origin[1]))
    return replace(bp, grid=grid)

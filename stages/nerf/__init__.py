"""NeRF stage: a CPU radiance field (+ semantics) with empty-space skipping; rendered depth."""

from stages.nerf import grid
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs
from stages.nerf.field import NerfModel, load_model
from stages.nerf.render import render_rays, render_view, top_view_labels

IMPLS = {"grid": grid.run}

__all__ = [
    "IMPLS",
    "NerfConfig",
    "NerfInputs",
    "NerfModel",
    "NerfOutputs",
    "load_model",
    "render_rays",
    "render_view",
    "top_view_labels",
]

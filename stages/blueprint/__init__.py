"""Blueprint stage: projected points → the plan raster (BluNF field or the MVR baseline)."""

from stages.blueprint.config import (
    BlueprintConfig,
    BlueprintInputs,
    BlueprintOutputs,
    BlunfConfig,
    MvrConfig,
    NerfTopConfig,
    NerfTopInputs,
    paper_recipe,
)
from stages.common.registry import LazyImpls

IMPLS = LazyImpls(
    {
        "blunf": "stages.blueprint.blunf:run",
        "mvr": "stages.blueprint.mvr:run",
        "nerf_top": "stages.blueprint.nerf_top:run",
    }
)

__all__ = [
    "IMPLS",
    "BlueprintConfig",
    "BlueprintInputs",
    "BlueprintOutputs",
    "BlunfConfig",
    "MvrConfig",
    "NerfTopConfig",
    "NerfTopInputs",
    "paper_recipe",
]

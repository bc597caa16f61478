"""Blueprint stage: projected points → the plan raster (BluNF field or the MVR baseline)."""

from stages.blueprint import blunf, mvr
from stages.blueprint.config import (
    BlueprintConfig,
    BlueprintInputs,
    BlueprintOutputs,
    BlunfConfig,
    MvrConfig,
    paper_recipe,
)

IMPLS = {"blunf": blunf.run, "mvr": mvr.run}

__all__ = [
    "IMPLS",
    "BlueprintConfig",
    "BlueprintInputs",
    "BlueprintOutputs",
    "BlunfConfig",
    "MvrConfig",
    "paper_recipe",
]

"""Layout: the architectural plan over the blueprint: straight walls with thickness and
lengths, room outlines with areas, openings, object footprints with sizes (plan.json, .svg,
.dxf)."""

from stages.common.registry import LazyImpls
from stages.layout.config import LayoutConfig, LayoutInputs, LayoutOutputs

IMPLS = LazyImpls({"walls": "stages.layout.walls:run"})

__all__ = ["IMPLS", "LayoutConfig", "LayoutInputs", "LayoutOutputs"]

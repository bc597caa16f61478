"""NeRF stage: a CPU radiance field (+ semantics) with empty-space skipping; rendered depth.

Torch loads on first use: the implementation registry is lazy, and so are the model and
renderer names below (a cached run, or a config check, never imports torch).
"""

from typing import Any

from stages.common.registry import LazyImpls
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs

IMPLS = LazyImpls({"grid": "stages.nerf.grid:run"})

_LAZY = LazyImpls(
    {
        "NerfModel": "stages.nerf.field:NerfModel",
        "load_model": "stages.nerf.field:load_model",
        "render_rays": "stages.nerf.render:render_rays",
        "render_view": "stages.nerf.render:render_view",
        "top_view_labels": "stages.nerf.render:top_view_labels",
    }
)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return _LAZY[name]
    raise AttributeError(f"module 'stages.nerf' has no attribute {name!r}")


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

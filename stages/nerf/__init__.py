"""NeRF stage: train a CPU radiance field (+ semantics) on the capture, for edits and the
NeRF top view.

The field, its occupancy grid, its renderer and its training live in
`stages.common.radiance` (the depth stage's field fill, the edit and blueprint stages use
them too). Torch loads on first use: the implementation registry is lazy (a cached run, or a
config check, never imports torch).
"""

from stages.common.registry import LazyImpls
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs

IMPLS = LazyImpls({"grid": "stages.nerf.grid:run"})

__all__ = ["IMPLS", "NerfConfig", "NerfInputs", "NerfOutputs"]

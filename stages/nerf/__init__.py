"""NeRF stage: train a CPU radiance field (+ semantics) on the capture; rendered depth.

The field, its occupancy grid and its renderer live in `stages.common.radiance` (the edit and
blueprint stages render through them too). Torch loads on first use: the implementation
registry is lazy (a cached run, or a config check, never imports torch).
"""

from stages.common.registry import LazyImpls
from stages.nerf.config import NerfConfig, NerfInputs, NerfOutputs, StereoOutputs

IMPLS = LazyImpls({"grid": "stages.nerf.grid:run", "stereo": "stages.nerf.sweep:run"})

__all__ = ["IMPLS", "NerfConfig", "NerfInputs", "NerfOutputs", "StereoOutputs"]

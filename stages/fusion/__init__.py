"""Fusion stage: depth of every view fused into one surface, and clean depth ray-cast back.

`IMPLS[cfg.impl]` picks the implementation; `tsdf` is Open3D's tensor VoxelBlockGrid.
"""

from stages.common.registry import LazyImpls
from stages.fusion.config import FusionConfig, FusionInputs, FusionOutputs

IMPLS = LazyImpls({"tsdf": "stages.fusion.tsdf:run"})

__all__ = ["IMPLS", "FusionConfig", "FusionInputs", "FusionOutputs"]

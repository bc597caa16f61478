"""Semantics stage: per-view class maps derived from the fused geometry when the capture has
no labels (floor, walls, ceiling, object instances).

`IMPLS[cfg.impl]` picks the implementation; `geometry` segments the fused mesh (planes and
clusters) and ray-casts the classes into every view. The config value "height" has no
implementation: the pipeline then skips this stage and the project stage labels by height.
"""

from stages.common.registry import LazyImpls
from stages.semantics.config import SemanticsConfig, SemanticsInputs, SemanticsOutputs

IMPLS = LazyImpls({"geometry": "stages.semantics.geometry:run"})

__all__ = ["IMPLS", "SemanticsConfig", "SemanticsInputs", "SemanticsOutputs"]

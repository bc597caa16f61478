"""Align stage: a rigid transform T making the world z up with the floor at z = 0.

`IMPLS[cfg.impl]` picks the implementation: `gravity` (capture's gravity vector), `floor`
(floor plane from depth), `auto` (gravity if given, else floor) or `none` (identity).
All but `none` then turn the world about z so that the walls lie on x and y (manhattan.py).
"""

from stages.align.config import AlignConfig, AlignInputs, AlignOutputs
from stages.common.registry import LazyImpls

IMPLS = LazyImpls(
    {
        "auto": "stages.align.auto:run",
        "gravity": "stages.align.gravity:run",
        "floor": "stages.align.floor:run",
        "none": "stages.align.none:run",
    }
)

__all__ = ["IMPLS", "AlignConfig", "AlignInputs", "AlignOutputs"]

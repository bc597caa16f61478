"""Depth stage: depth for fusion from the photos alone (no sensor depth in the capture).

Its parts, in order: the plane sweep (sweep.py, checked across views by consistency.py),
the plane fill (planes/), the field fill (field.py: a radiance field, stages.common.radiance,
trained on what the parts before found, its render filling the holes). stage.py runs them.
Torch loads on first use: the implementation registry is lazy.
"""

from stages.common.registry import LazyImpls
from stages.depth.config import DepthConfig, DepthInputs, DepthOutputs

IMPLS = LazyImpls(
    {"stereo": "stages.depth.stage:run_stereo", "field": "stages.depth.stage:run_field"}
)

__all__ = ["IMPLS", "DepthConfig", "DepthInputs", "DepthOutputs"]

"""Poses stage: camera-to-world poses for every frame, given by the capture or from SfM.

`IMPLS[cfg.impl]` picks the implementation; with `impl = "sfm"`, `cfg.mapper` picks COLMAP's
incremental mapper or the global one (GLOMAP), and `cfg.matching` the image pairs (matching.py).
"""

from stages.common.registry import LazyImpls
from stages.poses.config import PosesConfig, PosesInputs, PosesOutputs

IMPLS = LazyImpls({"given": "stages.poses.given:run", "sfm": "stages.poses.sfm:run"})

__all__ = ["IMPLS", "PosesConfig", "PosesInputs", "PosesOutputs"]

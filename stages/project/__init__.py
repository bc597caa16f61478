"""Project stage: labelled pixels with depth → world points and the plan grid (the paper's Π).

SciPy loads on first use: the implementation registry is lazy.
"""

from stages.common.registry import LazyImpls
from stages.project.config import ProjectConfig, ProjectInputs, ProjectOutputs

IMPLS = LazyImpls({"pinhole": "stages.project.points:run"})

__all__ = ["IMPLS", "ProjectConfig", "ProjectInputs", "ProjectOutputs"]

"""Project stage: labelled pixels with depth → world points and the plan grid (the paper's Π)."""

from stages.project import points
from stages.project.config import ProjectConfig, ProjectInputs, ProjectOutputs

IMPLS = {"pinhole": points.run}

__all__ = ["IMPLS", "ProjectConfig", "ProjectInputs", "ProjectOutputs"]

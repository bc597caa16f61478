"""Edit stage: an edit spec applied on the blueprint, rendered through the trained NeRF.

`IMPLS[cfg.impl]` picks the implementation; `nerf` wraps the field while rendering (no
retraining) and edits the fused mesh the same way.
"""

from stages.common.registry import LazyImpls
from stages.edit.config import EditConfig, EditInputs, EditOutputs
from stages.edit.spec import EditSpec, load_spec, spec_textures

IMPLS = LazyImpls({"nerf": "stages.edit.nerf:run"})

__all__ = [
    "IMPLS",
    "EditConfig",
    "EditInputs",
    "EditOutputs",
    "EditSpec",
    "load_spec",
    "spec_textures",
]

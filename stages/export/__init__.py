"""Export: the run's user-facing files."""

from stages.common.registry import LazyImpls

IMPLS = LazyImpls({"files": "stages.export.files:run"})

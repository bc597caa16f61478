"""Export: the run's user-facing files."""

from stages.export import files

IMPLS = {"files": files.run}

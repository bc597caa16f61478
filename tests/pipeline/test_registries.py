"""Stage registries name their implementations and import them on first use: a cached run
imports no implementation module (and so neither torch nor Open3D through one)."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from stages.common.registry import LazyImpls

LAZY = ("align", "blueprint", "depth", "edit", "evaluate", "export", "fusion", "ingest",
        "layout", "nerf", "poses", "project", "semantics")  # fmt: skip


@pytest.mark.parametrize("stage", LAZY)
def test_a_stage_registry_is_lazy(stage):
    impls = importlib.import_module(f"stages.{stage}").IMPLS
    assert isinstance(impls, LazyImpls)
    for name in impls:  # every entry names a function that exists
        assert callable(impls[name])


def test_importing_a_stage_package_imports_none_of_its_implementations():
    code = (
        "import sys; import stages.evaluate, stages.export, stages.ingest, stages.poses, "
        "stages.project; print(sorted(m for m in ('stages.evaluate.gt', 'stages.export.files', "
        "'stages.ingest.select', 'stages.poses.sfm', 'pycolmap', 'stages.project.points') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"

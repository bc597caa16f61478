"""Stages stand on `stages/common` only: no module of a stage package imports another stage.

Every module under `stages/<pkg>/` (the generator `stages/synth` included) may import its
own package, `stages.common...` and third-party packages; `stages/common` imports only
itself; none imports `pipeline/`. Imports are read with `ast` wherever they are (module
level, inside functions), and so are the "module:attr" strings of lazy registries, by the
cache's own reader (`pipeline.cache.imported_names`, what a stage's cache key follows). What
several stages share moves to `stages/common`, so that the cache key, which follows
imports, sees what a stage runs.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.cache import imported_names

ROOT = Path(__file__).resolve().parents[1]
SHARED = "common"


def cross_stage_imports(root: Path) -> set[tuple[str, str]]:
    """(importing module, imported module) for every import of one stage by another under
    `root/stages`, of any stage by stages/common, or of pipeline/ by any of them."""
    edges = set()
    for path in sorted((root / "stages").glob("*/**/*.py")):
        rel = path.relative_to(root).with_suffix("").parts  # ("stages", pkg, ..., module)
        own = rel[1]
        module = ".".join(rel[:-1] if rel[-1] == "__init__" else rel)
        bad = {
            t
            for t in imported_names(path, root)  # `from m import n` gives m and m.n
            if (len(t) >= 2 and t[0] == "stages" and t[1] not in {own, SHARED})
            or t[0] == "pipeline"  # a stage is a pure function of its config and inputs
        }
        # each import once, by the module it names (m, not m.n as well)
        edges.update(
            (module, ".".join(t)) for t in bad if not any(t[:i] in bad for i in range(len(t)))
        )
    return edges


def test_stages_import_only_the_shared_ground():
    edges = cross_stage_imports(ROOT)
    new = sorted(edges)  # that any edge would be read: the test below
    assert not new, "stage imports another stage (move the piece to stages/common):\n" + "\n".join(
        f"  {a} -> {b}" for a, b in new
    )


def test_every_kind_of_cross_stage_import_is_caught(tmp_path):
    shutil.copytree(ROOT / "stages", tmp_path / "stages", ignore=shutil.ignore_patterns("*.pyc"))
    base = cross_stage_imports(tmp_path)
    smuggled = {
        "blueprint/mvr.py": "\nfrom stages.export.vector import write_svg\n",
        "blueprint/instances.py": "\n\ndef _late():\n    import stages.evaluate.gt\n",
        "edit/spec.py": "\nfrom stages import project\n",
        "fusion/carve.py": "\nfrom ..semantics import floorfill\n",
        "poses/scale.py": '\n_LAZY = {"x": "stages.align.floor:run"}\n',
        "common/io.py": "\nfrom stages.ingest import select\n",
        "export/files.py": "\nfrom pipeline.cache import code_version\n",
    }
    for rel, code in smuggled.items():
        with open(tmp_path / "stages" / rel, "a") as f:
            f.write(code)
    assert cross_stage_imports(tmp_path) - base == {
        ("stages.blueprint.mvr", "stages.export.vector"),
        ("stages.blueprint.instances", "stages.evaluate.gt"),
        ("stages.edit.spec", "stages.project"),
        ("stages.fusion.carve", "stages.semantics"),
        ("stages.poses.scale", "stages.align.floor"),
        ("stages.common.io", "stages.ingest"),
        ("stages.export.files", "pipeline.cache"),
    }

"""The code version in a stage's cache key covers every project file the stage imports,
transitively: editing a module a stage runs rekeys that stage, and only the stages that run it;
and the stage's code reads every field of its config (the key's other half).
Each test works on a copy of `stages/`, so that editing it leaves the project alone."""

from __future__ import annotations

import ast
import dataclasses
import shutil
from pathlib import Path

import pytest

from pipeline.cache import PROJECT_ROOT, code_version, stage_sources
from pipeline.config import default_config

STAGES = (
    "ingest",
    "poses",
    "align",
    "depth",
    "fusion",
    "semantics",
    "nerf",
    "project",
    "blueprint",
    "edit",
    "evaluate",
    "export",
    "synth",
)


@pytest.fixture
def tree(tmp_path) -> Path:
    """A project root holding a copy of stages/."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(PROJECT_ROOT / "stages", tmp_path / "stages", ignore=ignore)
    return tmp_path


def _touch(path: Path) -> None:
    with open(path, "a") as f:
        f.write("# touched\n")


def _versions(root: Path) -> dict[str, str]:
    code_version.cache_clear()  # the memo would hide the edit
    return {s: code_version(s, root) for s in STAGES}


def test_touching_a_shared_module_rekeys_exactly_its_importers(tree):
    before = _versions(tree)
    assert before == {s: code_version(s) for s in STAGES}  # same files, same version
    points = tree / "stages" / "common" / "points.py"  # the project stage's files' readers
    users = {s for s in STAGES if points in stage_sources(s, tree)}
    # evaluate reads the points for metrics.observation (stages/evaluate/observation.py)
    assert {"project", "blueprint", "evaluate"} <= users
    assert users.isdisjoint({"ingest", "poses", "align", "fusion", "semantics"})
    _touch(points)
    after = _versions(tree)
    assert {s for s in STAGES if after[s] != before[s]} == users


def test_touching_a_stage_module_rekeys_that_stage_only(tree):
    before = _versions(tree)
    _touch(tree / "stages" / "export" / "vector.py")
    after = _versions(tree)
    assert {s for s in STAGES if after[s] != before[s]} == {"export"}


@pytest.mark.parametrize(
    "code",
    [
        "\nfrom stages.export.vector import write_svg\n",
        "\n\ndef _late():\n    import stages.export.vector\n",
        "\nfrom ..export import vector\n",
        '\n_LAZY = {"svg": "stages.export.vector:write_svg"}\n',
    ],
    ids=["module-level", "in-function", "relative", "lazy-registry"],
)
def test_a_smuggled_import_makes_the_stage_depend_on_what_it_imports(tree, code):
    vector = tree / "stages" / "export" / "vector.py"
    assert vector not in stage_sources("blueprint", tree)
    with open(tree / "stages" / "blueprint" / "mvr.py", "a") as f:
        f.write(code)
    sources = stage_sources("blueprint", tree)
    assert vector in sources
    assert tree / "stages" / "export" / "__init__.py" in sources  # run by importing it
    assert tree / "stages" / "export" / "files.py" in sources  # ... which imports files
    before = _versions(tree)
    _touch(vector)
    after = _versions(tree)
    assert after["blueprint"] != before["blueprint"]
    assert after["project"] == before["project"]  # upstream stays cached


def test_the_depth_stage_is_keyed_by_its_parts_and_the_shared_field(tree):
    # the sweep, the check and the field fill rekey the depth stage alone; the field's
    # training (stages/common/radiance) rekeys both stages that train one
    before = _versions(tree)
    for part in ("sweep.py", "consistency.py", "field.py", "render.py", "stage.py"):
        assert tree / "stages" / "depth" / part in stage_sources("depth", tree)
    _touch(tree / "stages" / "depth" / "sweep.py")
    after = _versions(tree)
    assert {s for s in STAGES if after[s] != before[s]} == {"depth"}
    train = tree / "stages" / "common" / "radiance" / "train.py"
    assert train in stage_sources("depth", tree) and train in stage_sources("nerf", tree)
    _touch(train)
    again = _versions(tree)
    changed = {s for s in STAGES if again[s] != after[s]}
    assert {"depth", "nerf"} <= changed and changed.isdisjoint({"poses", "fusion", "project"})


def _reads(stage: str, root: Path = PROJECT_ROOT) -> set[str]:
    """Names the stage's code reads as attributes (`cfg.select.pad`: select, pad) or names as
    strings (`getattr(cfg, "pad")`), over every module its key follows but the config
    modules (whose checks read every field); a config property the stage reads
    (`cfg.region_blocks`) reads what its body reads of `self`."""
    names: set[str] = set()
    props: dict[str, set[str]] = {}  # a config property: the fields of self it reads
    for path in stage_sources(stage, root):
        tree = ast.parse(path.read_bytes())
        if path.name == "config.py":
            for node in ast.walk(tree):
                if isinstance(node, ast.FunctionDef) and any(
                    isinstance(d, ast.Name) and d.id == "property" for d in node.decorator_list
                ):
                    props[node.name] = {
                        a.attr
                        for a in ast.walk(node)
                        if isinstance(a, ast.Attribute)
                        and isinstance(a.value, ast.Name)
                        and a.value.id == "self"
                    }
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute):
                names.add(node.attr)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                names.add(node.value)
    for name in names & props.keys():
        names |= props[name]
    return names


def _fields(obj, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out = []
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        out += _fields(v, (*path, f.name)) if dataclasses.is_dataclass(v) else [(*path, f.name)]
    return out


def unread_fields(stage: str, cfg) -> list[str]:
    """The config's fields no code of the stage reads: a field is read when its name is read
    as an attribute (`x.pad`, or named in a getattr) and so is each section over it (a section
    is often handed down: `sweep(cfg.stereo)` reads `s.window`). `impl` is the runner's."""
    reads = _reads(stage)
    return [".".join(f) for f in _fields(cfg) if f != ("impl",) and not set(f) <= reads]


@pytest.mark.parametrize("stage", [s for s in STAGES if s != "synth"])
def test_the_stage_reads_every_field_of_its_config(stage):
    # a setting in the cache key that no code reads would rerun a stage for nothing, and
    # tell the user that it does something
    cfg = default_config()[stage]
    assert unread_fields(stage, cfg) == []


def test_a_field_no_code_reads_is_found():
    from stages.edit.config import EditConfig, RenderConfig

    @dataclasses.dataclass(frozen=True)
    class Render(RenderConfig):
        never_read_knob: int = 0

    @dataclasses.dataclass(frozen=True)
    class Edit(EditConfig):
        render: RenderConfig = dataclasses.field(default_factory=Render)
        forgotten: float = 1.0

    assert unread_fields("edit", Edit()) == ["render.never_read_knob", "forgotten"]

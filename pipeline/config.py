"""Typed run configuration: stage dataclass defaults, overridden by one YAML file and --set.

Every stage's config is a frozen dataclass owned by the stage (`stages/<stage>/config.py`);
this module only assembles them and applies overrides. An unknown key is an error naming the
key and where it came from.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from stages.common.errors import BlunfError
from stages.common.io import read_yaml


@dataclass(frozen=True)
class RunSection:
    """What the pipeline itself decides (not any one stage)."""

    # Blueprint methods to run, each reported under its name; the first is the product's plan.
    methods: tuple[str, ...] = ("blunf", "mvr")
    # CPU threads for torch and Open3D; 0 = the cores this process may use.
    threads: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.threads <= 1024:
            raise BlunfError(f"run.threads: must be 0 (all cores) or 1..1024, got {self.threads}")
        if not self.methods:
            raise BlunfError("run.methods: give at least one blueprint method, e.g. [blunf, mvr]")
        if len(set(self.methods)) != len(self.methods):
            raise BlunfError(f"run.methods: a method is named twice in {list(self.methods)}")


# Settings a stage takes from another stage's section, passed when the config is built, so
# that each is set in one place: the depth sweep's finest useful cell is the plan's.
PASSED: dict[str, str] = {"depth.stereo.cell": "project.cell"}


def stage_configs() -> dict[str, type]:
    """Stage name -> its config dataclass, in pipeline order (the one place that lists them)."""
    from stages.align.config import AlignConfig
    from stages.blueprint.config import BlueprintConfig
    from stages.depth.config import DepthConfig
    from stages.edit.config import EditConfig
    from stages.evaluate.config import EvaluateConfig
    from stages.export.config import ExportConfig
    from stages.fusion.config import FusionConfig
    from stages.ingest.config import IngestConfig
    from stages.layout.config import LayoutConfig
    from stages.nerf.config import NerfConfig
    from stages.poses.config import PosesConfig
    from stages.project.config import ProjectConfig
    from stages.semantics.config import SemanticsConfig

    return {
        "ingest": IngestConfig,
        "poses": PosesConfig,
        "align": AlignConfig,
        "depth": DepthConfig,
        "fusion": FusionConfig,
        "semantics": SemanticsConfig,
        "nerf": NerfConfig,
        "project": ProjectConfig,
        "blueprint": BlueprintConfig,
        "layout": LayoutConfig,
        "edit": EditConfig,
        "evaluate": EvaluateConfig,
        "export": ExportConfig,
    }


@dataclass(frozen=True)
class Config:
    """The resolved configuration of a run: one section per stage plus `run`."""

    run: RunSection = field(default_factory=RunSection)
    stages: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, stage: str) -> Any:
        return self.stages[stage]

    def to_dict(self) -> dict:
        d = {"run": dataclasses.asdict(self.run)}
        d.update({k: dataclasses.asdict(v) for k, v in self.stages.items()})
        return d


def default_config() -> Config:
    return _passed(Config(RunSection(), {name: cls() for name, cls in stage_configs().items()}))


def load_config(path: Path | None = None, sets: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then the YAML file at `path`, then each `stage.key=value` of `sets`.

    Each source's keys and types are checked on their own (errors name the source); the
    merged overrides are applied at once, so cross-field checks of a stage config (e.g.
    depth_min < depth_max) see the final values whatever the order of the --set options.
    """
    cfg = default_config()
    layers = []
    if path is not None:
        path = Path(path)
        data = read_yaml(path, "config file") or {}
        if not isinstance(data, dict):
            raise BlunfError(f"{path}: a config must be a mapping of stage names to settings")
        layers.append(_checked(cfg, data, str(path)))
    for s in sets:
        key, sep, raw = s.partition("=")
        if not sep or not key.strip():
            raise BlunfError(f"--set {s!r}: expected stage.key=value")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
        nested: Any = value
        for part in reversed(key.strip().split(".")):
            nested = {part: nested}
        layers.append(_checked(cfg, nested, f"--set {s}"))
    merged: dict = {}
    for layer in layers:
        merge(merged, layer)
    return _build(cfg, merged)


def _checked(cfg: Config, data: dict, where: str) -> dict:
    """`data` with every key known and every value coerced to its field's type."""
    out: dict = {}
    for to, frm in PASSED.items():
        at: Any = data
        for part in to.split("."):
            at = at.get(part) if isinstance(at, dict) else None
        if at is not None:
            raise BlunfError(f"{where}: {to}: set from {frm} (one place for it); set {frm}")
    for name, value in data.items():
        if name == "run":
            out[name] = _check_section(cfg.run, value, f"{where}: run", "run")
        elif name in cfg.stages:
            out[name] = _check_section(cfg.stages[name], value, where, name)
        else:
            known = ", ".join(["run", *cfg.stages])
            raise BlunfError(f"{where}: unknown section {name!r} (known: {known})")
    return out


def _check_section(obj: Any, value: Any, where: str, prefix: str) -> dict:
    if not isinstance(value, dict):
        raise BlunfError(f"{where}: {prefix} must be a mapping, got {value!r}")
    hints = typing.get_type_hints(type(obj))
    names = {f.name for f in fields(obj)}
    renamed: dict[str, str] = getattr(type(obj), "RENAMED", {})  # old flat key -> new path
    moved: dict[str, str] = getattr(type(obj), "MOVED", {})  # key -> its place in another stage
    out = {}
    for k, v in value.items():
        if k in moved and k not in names:
            sub = next(iter(v), None) if isinstance(v, dict) and v else None
            old = f"{k}.{sub}" if sub is not None else k
            new = moved.get(old, f"{moved[k]}.{sub}" if sub is not None else moved[k])
            raise BlunfError(f"{where}: {prefix}.{old}: moved to {new}")
        if k in renamed and (k not in names or not isinstance(v, dict)):
            raise BlunfError(f"{where}: {prefix}.{k}: renamed to {prefix}.{renamed[k]}")
        if k not in names:
            raise BlunfError(
                f"{where}: unknown key {prefix}.{k} (known: {', '.join(sorted(names))})"
            )
        cur = getattr(obj, k)
        if is_dataclass(cur):
            out[k] = _check_section(cur, v, where, f"{prefix}.{k}")
        else:
            out[k] = _coerce(v, hints[k], f"{where}: {prefix}.{k}")
    return out


def recorded(cls: type, d: dict, where: str, prefix: str) -> Any:
    """A stage's config from the settings a run recorded (report.json's `config.<stage>`),
    read by this version: a flat key of an earlier version goes to its new place (the
    config's RENAMED), a key this version does not know is dropped, the rest is checked."""
    obj = cls()
    return _replace(obj, _check_section(obj, _known(obj, d), where, prefix))


def recorded_sections(d: dict) -> dict:
    """A whole recorded config (report.json's `config`) as this version reads it, section by
    section as `recorded` does (unknown sections dropped, the PASSED settings left to their
    source), to be loaded as a YAML layer."""
    cfg = default_config()
    out = {"run": _known(cfg.run, d["run"])} if isinstance(d.get("run"), dict) else {}
    for name, obj in cfg.stages.items():
        if isinstance(d.get(name), dict):
            out[name] = _known(obj, d[name])
    for to in PASSED:
        *path, last = to.split(".")
        at: Any = out
        for part in path:
            at = at.get(part) if isinstance(at, dict) else None
        if isinstance(at, dict):
            at.pop(last, None)
    return out


def _known(obj: Any, d: dict) -> dict:
    names = {f.name for f in fields(obj)}
    renamed: dict[str, str] = getattr(type(obj), "RENAMED", {})
    out: dict = {}
    for k, v in d.items():
        if k in renamed and (k not in names or not isinstance(v, dict)):
            *path, last = renamed[k].split(".")
            at = out
            for part in path:
                at = at.setdefault(part, {})
            at.setdefault(last, v)
        elif k in names:
            cur = getattr(obj, k)
            if is_dataclass(cur) and isinstance(v, dict):
                merge(out.setdefault(k, {}), _known(cur, v))
            elif not is_dataclass(cur):
                out[k] = v
    return out


def merge(into: dict, layer: dict) -> None:
    """Deep-merge checked overrides; a later layer wins (sections are dicts, values are not)."""
    for k, v in layer.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            merge(into[k], v)
        else:
            into[k] = v


def _build(cfg: Config, changes: dict) -> Config:
    stages_ = dict(cfg.stages)
    run = _replace(cfg.run, changes.get("run", {}))
    for name, ch in changes.items():
        if name != "run":
            stages_[name] = _replace(stages_[name], ch)
    return _passed(Config(run, stages_))


def _passed(cfg: Config) -> Config:
    """`cfg` with each PASSED setting taken from its source."""
    stages_ = dict(cfg.stages)
    for to, frm in PASSED.items():
        src = stages_
        for part in frm.split("."):
            src = src[part] if isinstance(src, dict) else getattr(src, part)
        stage, *path = to.split(".")
        change: Any = src
        for part in reversed(path):
            change = {part: change}
        stages_[stage] = _replace(stages_[stage], change)
    return Config(cfg.run, stages_)


def _replace(obj: Any, changes: dict) -> Any:
    """A copy of a (nested) config dataclass with checked changes; its __post_init__ runs once."""
    if not changes:
        return obj
    kw = {
        k: _replace(getattr(obj, k), v) if is_dataclass(getattr(obj, k)) else v
        for k, v in changes.items()
    }
    return replace(obj, **kw)


def _coerce(v: Any, tp: Any, where: str) -> Any:
    """Check/convert a YAML value to a dataclass field type (int, float, str, bool, tuple...)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if v is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(v, a, where)
            except BlunfError:
                continue
        raise BlunfError(f"{where}: {v!r} is not a {tp}")
    if origin is typing.Literal:
        if v not in typing.get_args(tp):
            raise BlunfError(f"{where}: {v!r} is not one of {typing.get_args(tp)}")
        return v
    if origin in (tuple, list):
        if isinstance(v, str):
            v = [x.strip() for x in v.split(",") if x.strip()]
        if not isinstance(v, list | tuple):
            raise BlunfError(f"{where}: expected a list, got {v!r}")
        item_types = [a for a in typing.get_args(tp) if a is not Ellipsis]
        item = item_types[0] if item_types else Any
        out = [_coerce(x, item, where) if item is not Any else x for x in v]
        return tuple(out) if origin is tuple else out
    if tp is bool:
        if isinstance(v, bool):
            return v
        raise BlunfError(f"{where}: expected true or false, got {v!r}")
    if tp is int:
        if isinstance(v, int) and not isinstance(v, bool):
            return v
        raise BlunfError(f"{where}: expected an integer, got {v!r}")
    if tp is float:
        x = None
        if isinstance(v, int | float) and not isinstance(v, bool):
            x = float(v)
        elif isinstance(v, str):
            try:
                x = float(v)
            except ValueError:
                pass
        if x is None:
            raise BlunfError(f"{where}: expected a number, got {v!r}")
        if not math.isfinite(x):  # `> 0` checks downstream would let inf through
            raise BlunfError(f"{where}: must be a finite number, got {v!r}")
        return x
    if tp is str:
        if isinstance(v, str):
            return v
        raise BlunfError(f"{where}: expected a string, got {v!r}")
    return v


def stage_view(stage_cfg: Any, impl: str) -> dict:
    """The part of a stage config that an implementation depends on, for its cache key.

    Nested sections named after other implementations (e.g. `blueprint.mvr` while running
    `blunf`) are left out, so changing one method's settings does not rerun the others; those
    the config lists in SHARED (read by every implementation) stay.
    """
    d = dataclasses.asdict(stage_cfg)
    for f in fields(stage_cfg):
        if (
            is_dataclass(getattr(stage_cfg, f.name))
            and f.name != impl
            and f.name in _impl_names(stage_cfg)
            and f.name not in getattr(stage_cfg, "SHARED", ())
        ):
            d.pop(f.name)
    d["impl"] = impl
    return d


def _impl_names(stage_cfg: Any) -> set[str]:
    module = type(stage_cfg).__module__.rsplit(".", 1)[0]
    import importlib

    reg = getattr(importlib.import_module(module), "IMPLS", {})
    return set(reg)

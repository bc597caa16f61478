"""Content-hash cache of stage outputs: `runs/<scene>/<stage>/<key>/`.

key = hash(stage, implementation, the config it depends on, the keys of its inputs, the code
version of the stage). A stage writes into a temp folder that is renamed into place once
`meta.json` is written, so a killed run never leaves a half-written entry under a key.

The code version hashes every project file the stage runs: the modules of its package and,
transitively, every project module they import (at module level or inside a function, or
named "package.module:attr" in a lazy registry), with the package __init__ files that
importing them executes. A stage that imports another stage's module is therefore still
keyed on that module's code.
"""

from __future__ import annotations

import ast
import dataclasses
import fcntl
import hashlib
import json
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache, lru_cache
from pathlib import Path
from typing import Any

import stages
from stages.common.errors import BlunfError

KEY_LEN = 16
STAGES_ROOT = Path(stages.__file__).parent
PROJECT_ROOT = STAGES_ROOT.parent
# A string naming a module, as lazy registries do: "stages.fusion.tsdf:run".
_MODULE_NAME = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+(?::[\w.]+)?")
_QUOTED_NAME = re.compile(r"""["'][A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+(?::[\w.]+)?["']""")


def _h(data: bytes | str) -> str:
    b = data.encode() if isinstance(data, str) else data
    return hashlib.blake2b(b, digest_size=16).hexdigest()


@cache
def code_version(stage: str, root: Path = PROJECT_ROOT) -> str:
    """Hash of every project file the stage runs (`stage_sources`), names and bytes."""
    h = hashlib.blake2b(digest_size=16)
    for p in stage_sources(stage, root):
        data = p.read_bytes()
        h.update(f"{p.relative_to(root).as_posix()}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()


def stage_sources(stage: str, root: Path = PROJECT_ROOT) -> list[Path]:
    """The modules of `root/stages/<stage>/` and every project module they import, directly
    or not, with the package __init__ files on the way. Sorted paths under `root`."""
    root = Path(root)
    todo = sorted((root / "stages" / stage).rglob("*.py"))
    if not todo:
        raise ValueError(f"no stage package {root / 'stages' / stage}")
    todo += _module_files(root, ("stages", stage))
    seen: set[Path] = set()
    names: set[tuple[str, ...]] = set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        for name in imported_names(p, root) - names:
            names.add(name)
            todo += [f for f in _module_files(root, name) if f not in seen]
    return sorted(seen)


def imported_names(path: Path, root: Path) -> frozenset[tuple[str, ...]]:
    """Dotted names the module at `path` (under `root`) may import: every `import` and
    `from ... import` anywhere in it (relative ones resolved; `from m import n` gives m and
    m.n, n being a module or not) and every string literal that is a module name or
    "module:attr" (lazy registries)."""
    package = path.relative_to(root).parts[:-1]  # where relative imports start (__init__ too)
    return _names_in(path.read_bytes(), package)


@lru_cache(maxsize=4096)
def _names_in(source: bytes, package: tuple[str, ...]) -> frozenset[tuple[str, ...]]:
    names: set[tuple[str, ...]] = set()
    tree = ast.parse(source)
    todo: list[ast.AST] = [tree]
    while todo:  # statements only (imports are statements): far fewer nodes than ast.walk
        node = todo.pop()
        if isinstance(node, ast.Import):
            names.update(tuple(a.name.split(".")) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else ()
            mod = base + (tuple(node.module.split(".")) if node.module else ())
            names.add(mod)
            names.update(mod + (a.name,) for a in node.names if a.name != "*")
        for value in vars(node).values():
            if isinstance(value, list):
                todo += [v for v in value if isinstance(v, ast.stmt | ast.excepthandler)]
                todo += [c for v in value if isinstance(v, ast.match_case) for c in v.body]
    if _QUOTED_NAME.search(source.decode()):  # then only string constants (not a docstring)
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                if _MODULE_NAME.fullmatch(node.value):
                    names.add(tuple(node.value.partition(":")[0].split(".")))
    return frozenset(names)


def _module_files(root: Path, name: tuple[str, ...]) -> list[Path]:
    """The files under `root` that importing module `name` executes: each package's
    __init__.py down to it and the module itself. Empty when `name` is not under root
    (a third-party module, or an attribute)."""
    out = []
    for i in range(1, len(name) + 1):
        base = root.joinpath(*name[:i])
        if (base / "__init__.py").is_file():
            out.append(base / "__init__.py")
        elif i == len(name) and base.with_suffix(".py").is_file():
            out.append(base.with_suffix(".py"))
        elif not base.is_dir():  # a folder without __init__.py is a namespace package
            return []
    return out


def content_hash(path: Path) -> str:
    """Hash of a file, or of every file under a folder (names and bytes), ignoring dotfiles."""
    path = Path(path)
    h = hashlib.blake2b(digest_size=16)
    files = (
        [path]
        if path.is_file()
        else sorted(
            p
            for p in path.rglob("*")
            if p.is_file() and not any(s.startswith(".") for s in p.relative_to(path).parts)
        )
    )
    for p in files:
        h.update(str(p.relative_to(path) if p != path else p.name).encode())
        try:
            with open(p, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
        except OSError as e:  # e.g. a photo without read permission
            raise BlunfError(f"{p}: cannot read ({e.strerror})") from None
    return h.hexdigest()


def stage_key(stage: str, impl: str, cfg_view: dict, input_keys: dict[str, str]) -> str:
    blob = json.dumps(
        {
            "stage": stage,
            "impl": impl,
            "config": cfg_view,
            "inputs": input_keys,
            "code": code_version(stage),
        },
        sort_keys=True,
        default=str,
    )
    return _h(blob)[:KEY_LEN]


class Cache:
    """The stage folders of one run directory."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def folder(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def is_done(self, stage: str, key: str) -> bool:
        return (self.folder(stage, key) / "meta.json").is_file()

    def key_of(self, path: Path) -> str | None:
        """The cache key of a path inside one of this run's stage folders, else None."""
        try:
            rel = Path(path).resolve().relative_to(self.root.resolve())
        except ValueError:
            return None
        return rel.parts[1] if len(rel.parts) >= 2 else None

    def input_keys(self, inputs: Any) -> dict[str, str]:
        """Keys of a stage's inputs: a stage folder's key, or the content hash of outside files."""
        keys = {}
        for f in dataclasses.fields(inputs):
            v = getattr(inputs, f.name)
            if isinstance(v, Path):
                keys[f.name] = self.path_key(v)
            elif isinstance(v, tuple | list) and all(isinstance(x, Path) for x in v):
                keys[f.name] = ",".join(self.path_key(x) for x in v)
            else:
                keys[f.name] = json.dumps(v, sort_keys=True, default=str)
        return keys

    def path_key(self, p: Path) -> str:
        k = self.key_of(p)
        return k if k is not None else f"{Path(p).resolve()}:{content_hash(p)}"

    @contextmanager
    def lock(self, stage: str, key: str) -> Iterator[None]:
        """Exclusive lock on one entry, so concurrent runs never build it twice at once."""
        d = self.root / stage
        d.mkdir(parents=True, exist_ok=True)
        with open(d / f".{key}.lock", "w") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def temp(self, stage: str, key: str) -> Path:
        t = self.root / stage / f".tmp-{key}-{os.getpid()}"
        shutil.rmtree(t, ignore_errors=True)
        t.mkdir(parents=True)
        return t

    def commit(self, tmp: Path, stage: str, key: str, meta: dict) -> Path:
        with open(tmp / "meta.json", "w") as f:
            json.dump(meta, f, indent=1, default=str)
        final = self.folder(stage, key)
        if final.exists():  # under the entry's lock and not done: an entry without meta.json
            shutil.rmtree(final)  # (deleted by hand, or a half-copied run folder); replace it
        os.rename(tmp, final)
        return final

    def sweep(self) -> None:
        """Remove temp folders left by killed runs (their process is gone)."""
        for t in self.root.glob("*/.tmp-*"):
            pid = t.name.rsplit("-", 1)[-1]
            if pid.isdigit() and not alive(int(pid)):
                shutil.rmtree(t, ignore_errors=True)


def alive(pid: int) -> bool:
    """Whether a process of that id exists (a killed run's is gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True

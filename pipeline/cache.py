"""Content-hash cache of stage outputs: `runs/<scene>/<stage>/<key>/`.

key = hash(stage, implementation, the config it depends on, the keys of its inputs, the code
version of the stage). A stage writes into a temp folder that is renamed into place once
`meta.json` is written, so a killed run never leaves a half-written entry under a key.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from typing import Any

import stages

KEY_LEN = 16
STAGES_ROOT = Path(stages.__file__).parent


def _h(data: bytes | str) -> str:
    b = data.encode() if isinstance(data, str) else data
    return hashlib.blake2b(b, digest_size=16).hexdigest()


@cache
def code_version(stage: str) -> str:
    """Hash of the stage package's sources and of stages/common (what the stage runs)."""
    h = hashlib.blake2b(digest_size=16)
    for folder in (STAGES_ROOT / stage, STAGES_ROOT / "common"):
        for p in sorted(folder.rglob("*.py")):
            h.update(str(p.relative_to(STAGES_ROOT)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


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
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
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
            if pid.isdigit() and not _alive(int(pid)):
                shutil.rmtree(t, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True

"""Implementation registries whose modules load on first use.

`LazyImpls({"tsdf": "stages.fusion.tsdf:run"})` lists every implementation by name (greppable,
checked without importing anything) and imports its module only when a stage actually runs,
so a fully cached `blunf run` does not pay for importing torch or Open3D.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any


class LazyImpls(Mapping[str, Callable[..., Any]]):
    """name -> "package.module:function", imported when looked up."""

    def __init__(self, table: dict[str, str]):
        self._table = dict(table)

    def __getitem__(self, name: str) -> Callable[..., Any]:
        module, _, fn = self._table[name].partition(":")
        return getattr(importlib.import_module(module), fn)

    def __contains__(self, name: object) -> bool:  # Mapping's default would import
        return name in self._table

    def __iter__(self) -> Iterator[str]:
        return iter(self._table)

    def __len__(self) -> int:
        return len(self._table)

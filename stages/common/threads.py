"""How many threads torch computes with, set for a block of code and put back after it."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with `n` torch threads (n <= 0: the count as it is), then restore it.

    Does nothing when torch is not imported yet: a block that imports it starts with torch's
    own default, and this module never loads torch itself (a cached run does not pay for it).
    """
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    old = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)

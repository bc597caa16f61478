"""Shared fixtures: one tiny procedural room per test session (exact ground truth)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

os.environ.setdefault("BLUNF_THREADS", "1")


def shared_capture(name: str) -> Path:
    """A real capture in ../shared/data, or a clean skip when this checkout does not have it."""
    p = SHARED_DATA / name
    if not p.is_dir():
        pytest.skip(f"real capture {p} not present (it lives beside the project, not in it)")
    return p


@pytest.fixture(scope="session")
def tiny_room(tmp_path_factory) -> Path:
    """A 16-view 96x72 procedural room: small enough for the default suite."""
    from stages.synth import make_room

    return make_room(tmp_path_factory.mktemp("room") / "capture", views=16, seed=3, size=(96, 72))


# A small radiance field (2^14 x 8 hash entries, up to 128 cells across; a 64-cell occupancy
# grid) and small batches, no held-out evaluation: ~0.05 CPU-s a step on one thread. For
# tune() on any config holding the field's sections (NerfConfig, FieldFillConfig).
SMALL_FIELD = dict(
    train__time_budget=0.0,
    train__eval_every=0,
    field__hash_log2_size=14,
    field__hash_max_res=128,
    occupancy__res=64,
    train__batch_rays=128,
    losses__surface_rays=512,
    losses__geo_rays=512,
    losses__edge_rays=512,
)


def tune(cfg, **changes):
    """A copy of a (nested) config dataclass with `section__field=value` changes applied,
    e.g. tune(NerfConfig(), train__max_steps=10, seed=1)."""
    top: dict = {}
    sub: dict[str, dict] = {}
    for key, value in changes.items():
        head, _, rest = key.partition("__")
        if rest:
            sub.setdefault(head, {})[rest] = value
        else:
            top[head] = value
    for head, ch in sub.items():
        top[head] = tune(getattr(cfg, head), **ch)
    return dataclasses.replace(cfg, **top)


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups into node ids
def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (`--dist loadgroup`, as the Makefile runs the suites), keep the tests
    that share a module- or class-scoped fixture on one worker, so that the fixture (often a
    whole pipeline run) is built once; every other test is dealt out one by one."""
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None or item.get_closest_marker("xdist_group"):
            continue
        shared = any(
            d.scope in ("module", "class") for defs in info.name2fixturedefs.values() for d in defs
        )
        if shared:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))


def pytest_configure(config):
    """pytest 9.2 builds node ids from a structure that pytest-xdist 3.8 cannot tag with their
    group, so `--dist loadgroup` groups nothing: each worker would rebuild every module's shared
    fixture (the batch module's Dask run twice, 41 + 33 s). Refuse that pair at once."""
    if config.getoption("dist", "no") != "loadgroup":
        return
    import xdist

    xdist_v = tuple(int(x) for x in xdist.__version__.split(".")[:2])
    if pytest.version_tuple[:2] >= (9, 2) and xdist_v <= (3, 8):
        raise pytest.UsageError(
            f"pytest {pytest.__version__} with pytest-xdist {xdist.__version__} breaks "
            "--dist loadgroup: make setup installs the pair pinned in constraints.txt"
        )

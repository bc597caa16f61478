"""`blunf synth --rooms N`: a procedural home of 2-5 rooms as one capture, with exact GT.

The plan (stages/synth/home_plan.py), the camera's walk through it (home_path.py) and its
meshes and layout (home_scene.py) are drawn from the seed; views are rendered and written
as for a single room (make.write_views). gt/ holds what a room's gt/ holds: poses,
instances, the mesh, the top-down blueprint (same cell, margin and rays) and layout.json,
with every room's polygon, its walls (`room`) and the openings (`rooms`), and room.json
with the home's figures (the rooms' polygons and the walk's points among them).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from stages.common.errors import BlunfError
from stages.common.io import write_json
from stages.synth.files import (
    PLAN_CELL,
    PLAN_MARGIN,
    checked,
    write_instances,
    write_views,
    written_whole,
)
from stages.synth.home_path import home_path, keyframes, route
from stages.synth.home_plan import TEMPLATES, draw_plan
from stages.synth.home_scene import home_layout, home_parts, home_room
from stages.synth.realism import Realism
from stages.synth.render import Tracer, intrinsics_for, top_down
from stages.synth.room import scene_mesh

log = logging.getLogger(__name__)

ROOMS = (min(TEMPLATES), max(TEMPLATES))  # rooms a home may have


def check_rooms(rooms: object) -> int:
    """`rooms` as an int in 1..5, or a one-line error."""
    ok = isinstance(rooms, int | np.integer) and not isinstance(rooms, bool)
    if not ok or not 1 <= int(rooms) <= ROOMS[1]:  # type: ignore[call-overload]
        raise BlunfError(f"--rooms must be a whole number in 1..{ROOMS[1]}, got {rooms!r}")
    return int(rooms)  # type: ignore[call-overload]


def make_home(
    out: Path,
    rooms: int,
    views: int,
    seed: int,
    size: tuple[int, int],
    photos_only: bool = False,
    realism: Realism | None = None,
    ceiling: bool = True,
) -> Path:
    """Render a home of `rooms` (2..5) rooms to a capture at `out`. Returns `out`.

    Same arguments -> byte-identical files; writes into a temp sibling folder renamed into
    place at the end, so a failure leaves nothing behind (as make_room)."""
    out = Path(out)
    rooms = check_rooms(rooms)
    if rooms < ROOMS[0]:
        raise BlunfError(f"--rooms must be in {ROOMS[0]}..{ROOMS[1]} for a home, got {rooms}")
    views, seed, size = checked(out, views, seed, size)
    return written_whole(
        out,
        lambda tmp: _write(
            tmp, rooms, views, seed, size, photos_only, realism or Realism(), ceiling
        ),
    )


def _write(
    root: Path,
    n: int,
    views: int,
    seed: int,
    size: tuple[int, int],
    photos_only: bool,
    realism: Realism,
    ceiling: bool,
) -> None:
    t0 = time.perf_counter()
    subs = ("images", "gt/instances") + (() if photos_only else ("depth", "labels"))
    for sub in subs:
        (root / sub).mkdir(parents=True)
    plan = draw_plan(seed, n)
    walk = keyframes(route(plan))
    parts = home_parts(plan, seed, walk[:, :2], ceiling)
    home = home_room(plan, parts)
    poses = home_path(plan, views, seed)
    drawn = write_views(
        root, Tracer(parts), poses, intrinsics_for(*size), seed, realism, photos_only
    )
    write_instances(root, home)
    layout = home_layout(plan)
    write_json(
        root / "gt" / "room.json",
        {
            "seed": seed,
            "views": views,
            "size": list(size),
            "ceiling": ceiling,
            "rooms": n,
            "interior": [0.0, 0.0, *plan.size],
            "height": plan.height,
            "wall": plan.wall,
            "cells": [list(r) for r in plan.cells],
            "walk": [[round(float(v), 6) for v in k] for k in walk],
            "plan_cell": PLAN_CELL,
            "plan_rays": "one vertical ray through each cell centre, ceiling excluded",
        },
    )
    if not realism.default:
        write_json(root / "gt" / "realism.json", {"options": realism.to_json(), "views": drawn})
    scene_mesh(home).export(root / "gt" / "mesh.ply")
    write_json(root / "gt" / "layout.json", layout)
    top_down(home, PLAN_CELL, PLAN_MARGIN).save(root / "gt" / "blueprint.npz")
    log.info(
        "synth home seed %d: %d rooms %.2f x %.2f m, %d views, %d objects, %.1f s",
        seed,
        n,
        *plan.size,
        views,
        len(home.furniture),
        time.perf_counter() - t0,
    )

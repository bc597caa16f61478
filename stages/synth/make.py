"""`blunf synth`: write a procedural room as a capture in the project layout, with exact GT."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from stages.common.errors import BlunfError
from stages.common.io import write_json
from stages.synth.files import (
    PLAN_CELL,
    PLAN_MARGIN,
    checked,
    is_int,
    write_instances,
    write_views,
    written_whole,
)
from stages.synth.home import check_rooms, make_home
from stages.synth.layout import room_layout
from stages.synth.realism import Realism
from stages.synth.render import Tracer, camera_paths, intrinsics_for, top_down
from stages.synth.room import scene_mesh
from stages.synth.shape import build_shaped_room

log = logging.getLogger(__name__)


def make_room(
    out: Path,
    views: int = 60,
    seed: int = 0,
    size: tuple[int, int] = (320, 240),
    ceiling: bool = True,
    photos_only: bool = False,
    doors: int = 0,
    shape: str = "rect",
    realism: Realism | None = None,
    passages: int = 0,
    rooms: int = 1,
) -> Path:
    """Render a procedural room to a capture at `out`. Returns `out`.

    photos_only: the capture holds what a phone gives (images and intrinsics): no depth,
    labels, poses or gravity; the ground truth in gt/ is written all the same.
    doors: that many door gaps in distinct walls (0..4); gt/layout.json holds them.
    passages: that many passages (wider gaps, some under a lintel) in other walls (0..4).
    shape: "rect", or "L" for an L-shaped room (stages/synth/shape.py).
    realism: plain surfaces, exposure changes, blur and noise (stages/synth/realism.py);
    None = the textured room and a perfect camera (gt/realism.json holds what each view drew).

    rooms: 1 is this room; 2..5 a home of that many rooms (stages/synth/home.py), where
    doors, passages and shape do not apply.

    Same (views, seed, size, ceiling) -> byte-identical files. Writes into a temp sibling
    folder renamed into place at the end, so a failure leaves nothing behind.
    """
    if check_rooms(rooms) > 1:
        if doors or passages or shape != "rect":
            raise BlunfError("--doors, --passages and --shape apply to one room, not --rooms > 1")
        return make_home(out, rooms, views, seed, size, photos_only, realism, ceiling)
    out = Path(out)
    views, seed, (w, h) = checked(out, views, seed, size)
    if not is_int(doors) or not 0 <= doors <= 4:
        raise BlunfError(f"doors must be a whole number in 0..4, got {doors!r}")
    if not is_int(passages) or not 0 <= passages <= 4:
        raise BlunfError(f"passages must be a whole number in 0..4, got {passages!r}")
    if shape not in ("rect", "L"):
        raise BlunfError(f"--shape must be rect or L, got {shape!r}")
    gaps = (doors, passages)
    return written_whole(
        out,
        lambda tmp: _write(
            tmp, views, seed, (w, h), ceiling, photos_only, gaps, shape, realism or Realism()
        ),
    )


def _write(
    root: Path,
    views: int,
    seed: int,
    size: tuple[int, int],
    ceiling: bool,
    photos_only: bool,
    gaps: tuple[int, int] = (0, 0),
    shape: str = "rect",
    realism: Realism | None = None,
) -> None:
    """The capture's files; photos_only: without what a phone capture lacks (depth, labels,
    poses and gravity), the ground truth in gt/ all the same. gaps: (doors, passages)."""
    t0 = time.perf_counter()
    subs = (
        ("images", "gt/instances") if photos_only else ("images", "depth", "labels", "gt/instances")
    )
    for sub in subs:
        (root / sub).mkdir(parents=True)
    try:
        room = build_shaped_room(seed, ceiling, gaps[0], shape, gaps[1])
    except ValueError as e:  # more gaps than the room has walls for
        raise BlunfError(f"--doors {gaps[0]} --passages {gaps[1]}: {e}") from None
    poses = camera_paths(room, views, seed)
    realism = realism or Realism()
    drawn = write_views(
        root, Tracer(room.parts), poses, intrinsics_for(*size), seed, realism, photos_only
    )
    write_instances(root, room)
    write_json(
        root / "gt" / "room.json",
        {
            "seed": seed,
            "views": views,
            "size": list(size),
            "ceiling": ceiling,
            "interior": [0.0, 0.0, *room.size],
            "height": room.height,
            "wall": room.wall,
            "loop": list(room.loop),
            "plan_cell": PLAN_CELL,
            "plan_rays": "one vertical ray through each cell centre, ceiling excluded",
            **({"outline": room.outline, "loops": room.loops} if room.outline else {}),
        },
    )
    if not realism.default:
        write_json(root / "gt" / "realism.json", {"options": realism.to_json(), "views": drawn})
    scene_mesh(room).export(root / "gt" / "mesh.ply")
    write_json(root / "gt" / "layout.json", room_layout(room))
    plan = root / "gt" / "blueprint.npz"
    top_down(room, PLAN_CELL, PLAN_MARGIN).save(plan)
    log.info(
        "synth room seed %d: %d views, %d objects, %.1f s",
        seed,
        views,
        len(room.furniture),
        time.perf_counter() - t0,
    )

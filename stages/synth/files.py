"""The files every procedural capture writes, a room or a home: each view's images, depth,
labels and instances, cameras.json, labels.json, gt/poses.json and gt/instances.json."""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics
from stages.common.errors import BlunfError
from stages.common.io import write_depth_png, write_image, write_json, write_label_png
from stages.synth.realism import Realism
from stages.synth.render import Tracer, render
from stages.synth.room import CLASSES, IGNORE, Room

log = logging.getLogger(__name__)

PLAN_CELL = 0.02  # ground-truth blueprint cell (metres)
PLAN_MARGIN = 0.1  # the plan covers the room with its walls plus this margin (metres)


def is_int(x: object) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool)


def checked(
    out: Path, views: object, seed: object, size: tuple
) -> tuple[int, int, tuple[int, int]]:
    """The capture's folder, views, seed and size checked as `blunf synth` takes them (a
    one-line error naming the value at fault); returns (views, seed, (w, h)) as ints."""
    if out.exists() and not out.is_dir():
        raise BlunfError(f"{out}: exists and is not a folder")
    if out.exists() and any(out.iterdir()):
        raise BlunfError(f"{out}: output folder exists and is not empty")
    if not is_int(views) or views < 1:  # type: ignore[operator]
        raise BlunfError(f"--views must be a positive integer, got {views!r}")
    if not is_int(seed) or seed < 0:  # type: ignore[operator]
        raise BlunfError(f"--seed must be a non-negative integer, got {seed!r}")
    w, h = size
    if not (is_int(w) and is_int(h) and w >= 8 and h >= 8):
        raise BlunfError(f"--size must be whole pixels, at least 8x8, got {w}x{h}")
    return int(views), int(seed), (int(w), int(h))  # type: ignore[call-overload]


def written_whole(out: Path, write: Callable[[Path], None]) -> Path:
    """Run `write` into a temp sibling of `out` and rename it into place: a failure leaves
    nothing behind. Returns `out`."""
    tmp = out.parent / f".{out.name}.synth-tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        write(tmp)
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def write_views(
    root: Path,
    tracer: Tracer,
    poses: np.ndarray,
    intr: Intrinsics,
    seed: int,
    realism: Realism,
    photos_only: bool,
) -> dict:
    """Render and write each view (images, depth, labels, gt/instances), then cameras.json,
    labels.json and gt/poses.json; returns the camera effects each view drew (realism)."""
    views = len(poses)
    stems = [f"{i:04d}" for i in range(views)]
    t_render = 0.0
    drawn = {}
    for i, (stem, pose) in enumerate(zip(stems, poses, strict=True)):
        t1 = time.perf_counter()
        rng = np.random.default_rng([seed, 5, i])  # the view's exposure, blur and noise
        v = render(tracer, pose, intr, realism=realism, rng=rng)
        if v.camera:
            drawn[stem] = v.camera
        t_render += time.perf_counter() - t1
        write_image(root / "images" / f"{stem}.png", v.rgb)
        if not photos_only:
            write_depth_png(root / "depth" / f"{stem}.png", v.depth)
            write_label_png(root / "labels" / f"{stem}.png", v.label)
        write_label_png(root / "gt" / "instances" / f"{stem}.png", v.instance)
    log.info(
        "rendered %d views of %dx%d in %.2f s (%.3f s/view)",
        views,
        intr.width,
        intr.height,
        t_render,
        t_render / views,
    )
    pose_d = {s: p.tolist() for s, p in zip(stems, poses, strict=True)}
    if photos_only:
        write_json(root / "cameras.json", {"intrinsics": intr.to_json()})
    else:
        write_json(
            root / "cameras.json",
            {
                "intrinsics": intr.to_json(),
                "frames": {s: {"pose": p} for s, p in pose_d.items()},
                "gravity": [0.0, 0.0, -1.0],
                "depth_scale": 1000,
            },
        )
        write_json(
            root / "labels.json",
            {"classes": {str(k): v for k, v in CLASSES.items()}, "ignore": list(IGNORE)},
        )
    write_json(root / "gt" / "poses.json", pose_d)
    return drawn


def write_instances(root: Path, room: Room) -> None:
    """gt/instances.json: each piece of furniture's class, name and bounding box."""
    write_json(
        root / "gt" / "instances.json",
        {
            str(p.instance): {
                "class": p.cls,
                "name": p.name,
                "bbox": [round(float(x), 6) for x in p.mesh.bounds.reshape(-1)],
            }
            for p in room.furniture
        },
    )

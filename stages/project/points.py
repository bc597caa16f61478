"""Π: labelled pixels with depth to world points, and the plan grid that covers them.

Every `stride`-th pixel of every frame with a valid depth reading and a label that is neither
unknown (255) nor in the capture's ignore list becomes a point (x, y, z, label, view, instance:
the object instance id of the pixel when the frame has an instance map, else 0). Without
labels, points are labelled by height (floor / occupied) so a plan exists before semantics.
With occlusion "top" (the default), points a top view would not see are then dropped
(topview.py: floor between a table's legs, under a chair's seat); "none" is the paper's Π.
The plan grid bounds all the points (before that culling), padded by `pad`.

Far from the world origin (a georeferenced capture 10 km out) float32 world coordinates keep
only ~1 mm: points.npz stores them as float32 offsets from a float64 `origin` (the mean camera
centre). The top-view grids are anchored at that origin, not at world multiples of their
cell, so they move and scale with the world; the plan grid keeps world multiples of its cell.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from stages.common.blueprint import Grid
from stages.common.camera import depth_at, pixel_grid, undistort_pixels, unproject
from stages.common.capture import UNKNOWN, Capture, Frame, heldout_views, readings_of
from stages.common.classes import HEIGHT as HEIGHT_CLASSES
from stages.common.errors import BlunfError
from stages.common.io import image_size, read_depth, read_label, save_npz, write_json
from stages.common.points import str_keys, write_grid, write_points
from stages.project.config import ProjectConfig, ProjectInputs, ProjectOutputs
from stages.project.observed import looked_past, observed, past_height, room_inside
from stages.project.topview import top_view_keep

log = logging.getLogger(__name__)

READ_SLACK = 0.1  # _read: a reading this share nearer than the point still reads to it


def run(cfg: ProjectConfig, inputs: ProjectInputs, out: Path) -> ProjectOutputs:
    """Project every labelled pixel with depth of every frame into the world."""
    t0 = time.perf_counter()
    log.debug("project: %s", cfg)  # the full config: meta.json
    cap = Capture.load(inputs.frames)
    if not cap.frames:
        raise BlunfError(f"{inputs.frames}: the capture has no frames")
    labelling = _labelling(cfg, cap)
    ignore = np.asarray([*cap.ignore, UNKNOWN], np.int64)  # label ids never projected
    origin = _local_origin(cap)  # [3] float64; points are kept as float32 offsets from it
    xyz_l, lab_l, view_l, inst_l = [], [], [], []
    # counts, and past_height (metres) among them
    counts: dict[str, int | float] = {
        "sampled": 0,
        "no_depth": 0,
        "dropped_label": 0,
        "dropped_height": 0,
    }
    held_out = labelling == "labels" and inputs.holdout
    held = heldout_views(len(cap.frames), cfg.holdout_every) if held_out else []
    todo = [i for i in range(len(cap.frames)) if i not in held]

    stride = cfg.stride or auto_stride(cap, cfg.cell)

    def one(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
        c = dict.fromkeys(counts, 0)
        f = cap.frames[i]
        xyz, lab, inst = _frame_points(cap, f, cfg, labelling, ignore, origin, c, stride)
        return xyz, lab, inst, c

    # frames in parallel (image decoding and numpy release the GIL), results in frame order
    with ThreadPoolExecutor(_workers(len(todo))) as pool:
        done = list(pool.map(one, todo))
    for i, (xyz, lab, inst, c) in zip(todo, done, strict=True):
        for k, v in c.items():
            counts[k] += v
        xyz_l.append(xyz)
        lab_l.append(lab)
        view_l.append(np.full(len(lab), i, np.int32))
        inst_l.append(inst)
    xyz = np.concatenate(xyz_l)  # [N, 3] float32 offsets from origin
    label = np.concatenate(lab_l).astype(np.uint8)  # [N]
    view = np.concatenate(view_l)  # [N]
    instance = np.concatenate(inst_l).astype(np.int32)  # [N], 0 = none
    if len(label) == 0:
        raise BlunfError(f"no labelled pixel with depth in {cap.root}")
    classes = HEIGHT_CLASSES if labelling == "height" else _label_classes(cap, label)

    lo, hi = plan_bounds(xyz[:, :2], cfg)
    lo, hi = lo + origin[:2], hi + origin[:2]  # [2] world
    grid = Grid.covering(lo, hi, cfg.cell, cfg.pad)
    if cfg.occlusion == "top":
        keep = top_view_keep(  # its grids anchored at the origin: they move with the world
            xyz.astype(np.float64),
            label,
            cfg.occlusion_cell or cfg.cell,
            cfg.top_band,
            cfg.top_min_points,
            cfg.occlusion_shifts,
        )
        counts["dropped_occluded"] = int((~keep).sum())
        xyz, label, view, instance = xyz[keep], label[keep], view[keep], instance[keep]
    if grid.shape[0] * grid.shape[1] > cfg.max_cells:
        raise BlunfError(
            f"{inputs.frames}: the plan would be {grid.shape[1]}x{grid.shape[0]} cells of "
            f"{cfg.cell} m (> project.max_cells = {cfg.max_cells}); check poses and depth units"
        )
    outs = ProjectOutputs.at(out)
    cams = np.array([np.asarray(f.pose, np.float64)[:3, 3] for f in cap.frames])[:, :2]
    world_xy = xyz[:, :2].astype(np.float64) + origin[:2]  # [N, 2]
    # the views' own readings (free_read), read again view by view for `past` below: the
    # rays decide which cells are empty, so the two passes cannot share one, and holding every
    # reading between them would make memory grow with the views
    with_readings = cfg.free_read and inputs.readings is not None
    reading = readings_of(inputs.readings if with_readings else None)
    read = None
    if with_readings:
        read = _read(cap, reading, xyz.astype(np.float64) + origin, view)
        counts["points_read"] = int(read.sum())
    near, free, dist = observed(grid, world_xy, cams, view, cfg.seen_radius, cfg.ray_every, read)
    inside = room_inside(near, free, round(cfg.inside_close / grid.cell))
    labelled = inside & (dist <= max(cfg.fill_radius, cfg.seen_radius))
    row, col, on = grid.cell_of(world_xy)
    empty = free.copy()  # free cells that hold no point: floor no view saw, or an object's
    empty[row[on], col[on]] = False  # inside; `past` tells them apart
    height = past_height(np.array([np.asarray(cap.frames[i].pose)[2, 3] for i in todo]))
    past = looked_past(grid, empty, _views(cap, todo, reading), height)
    save_npz(
        outs.observed,
        near=near.astype(np.uint8),
        free=free.astype(np.uint8),
        inside=inside.astype(np.uint8),
        labelled=labelled.astype(np.uint8),
        past=past,
    )
    counts["cells_near"] = int(near.sum())
    counts["cells_free"] = int((free & ~near).sum())
    counts["cells_inside"] = int(inside.sum())
    counts["cells_labelled"] = int(labelled.sum())
    counts["cells_free_empty"] = int(empty.sum())
    counts["cells_past"] = int((past > 0).sum())
    counts["past_height"] = round(height, 3)
    write_points(outs.points, xyz, origin, label, view, instance, classes)
    write_grid(outs.grid, grid, lo, hi)
    write_json(outs.classes, {"classes": str_keys(classes), "labelling": labelling})
    stems = [cap.frames[i].stem for i in held]
    write_json(outs.heldout, {"every": cfg.holdout_every, "views": held, "stems": stems})
    stats = {
        "frames": len(cap.frames),
        "points": int(len(label)),
        "labelling": labelling,
        "instances": int(len(np.unique(instance[instance > 0]))),
        "heldout_views": len(held),
        "stride": stride,
        **counts,
        "grid_shape": list(grid.shape),
        "cell": grid.cell,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    write_json(Path(out) / "project.json", stats)
    log.info(
        "project: %d points from %d frames, plan %dx%d cells",
        len(label),
        len(cap.frames),
        grid.shape[1],
        grid.shape[0],
    )
    return outs


def auto_stride(cap: Capture, cell: float, frames: int = 8) -> int:
    """The pixel stride whose samples at the capture's median depth (over up to `frames`
    frames spread through it) lie nearest `cell` apart: round(cell * f / depth), at least 1.
    Each view then puts about one sample in each plan cell it sees, and the many views that
    see a cell make its vote."""
    pick = np.unique(np.linspace(0, len(cap.frames) - 1, min(frames, len(cap.frames))).round())
    zs, fs = [], []
    for i in pick.astype(int):
        f = cap.frames[i]
        if f.depth is None:
            continue
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        if (d > 0).any():
            zs.append(float(np.median(d[d > 0])))
            fs.append(f.intrinsics.fx * d.shape[1] / f.intrinsics.width)
    if not zs:
        return 1
    return max(1, round(cell * float(np.median(fs)) / float(np.median(zs))))


def plan_bounds(xy: np.ndarray, cfg: ProjectConfig) -> tuple[np.ndarray, np.ndarray]:
    """(lo [2], hi [2]): the box of points xy [N, 2] without the outer `bounds_pct` % a side."""
    lo = np.percentile(xy, cfg.bounds_pct, axis=0)  # [2]
    hi = np.percentile(xy, 100.0 - cfg.bounds_pct, axis=0)  # [2]
    return lo, hi


def _workers(n: int) -> int:
    """Threads for n frames: the process's thread budget (OMP_NUM_THREADS, which the runtime
    sizes to the free cores), else the cores, at most 4."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    cores = int(env) if env.isdigit() and int(env) > 0 else len(os.sched_getaffinity(0))
    return max(1, min(4, cores, n))


def _frame_points(
    cap: Capture,
    f: Frame,
    cfg: ProjectConfig,
    labelling: str,
    ignore: np.ndarray,
    origin: np.ndarray,
    counts: dict,
    stride: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points [N, 3] (float32 offsets from `origin`), labels [N] (int64; by height without
    labels) and instances [N] (int64; zeros without an instance map) of one frame."""
    use_labels = labelling == "labels"
    if f.pose is None:
        raise BlunfError(f"{f.image}: frame {f.stem!r} has no pose")
    if f.depth is None:
        raise BlunfError(f"{f.image}: frame {f.stem!r} has no depth map")
    w, h = image_size(f.image)
    depth = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)  # [H, W] metres
    if depth.shape != (h, w):
        raise BlunfError(
            f"{f.depth}: depth is {depth.shape[1]}x{depth.shape[0]} but the image "
            f"{f.image.name} is {w}x{h}"
        )
    s = stride
    uv = pixel_grid(w, h, s).reshape(-1, 2)  # [N, 2]
    d = depth[s // 2 :: s, s // 2 :: s].reshape(-1)  # [N]
    keep = d > 0
    counts["sampled"] += len(d)
    counts["no_depth"] += int((~keep).sum())
    if use_labels:
        assert f.label is not None
        lab_img = read_label(f.label)
        if lab_img.shape != (h, w):
            raise BlunfError(
                f"{f.label}: label map is {lab_img.shape[1]}x{lab_img.shape[0]} but "
                f"the image {f.image.name} is {w}x{h}"
            )
        lab = lab_img[s // 2 :: s, s // 2 :: s].reshape(-1).astype(np.int64)  # [N]
        ok = ~np.isin(lab, ignore)
        counts["dropped_label"] += int((keep & ~ok).sum())
        keep &= ok
        if keep.any() and lab[keep].max() > UNKNOWN:
            raise BlunfError(
                f"{f.label}: label id {int(lab[keep].max())} does not fit a plan "
                f"(class ids must be < {UNKNOWN})"
            )
        lab = lab[keep]
    else:
        lab = np.zeros(int(keep.sum()), np.int64)
    if f.instance is not None:
        inst_img = read_label(f.instance)
        if inst_img.shape != (h, w):
            raise BlunfError(
                f"{f.instance}: instance map is {inst_img.shape[1]}x{inst_img.shape[0]} but "
                f"the image {f.image.name} is {w}x{h}"
            )
        inst = inst_img[s // 2 :: s, s // 2 :: s].reshape(-1)[keep].astype(np.int64)  # [N]
        if inst.size and inst.min() < 0:
            raise BlunfError(f"{f.instance}: negative instance ids")
    else:
        inst = np.zeros(len(lab), np.int64)
    intr = f.intrinsics.scaled(w, h)
    uvk = undistort_pixels(uv[keep], intr)  # uv itself without distortion
    xyz = unproject(uvk, d[keep], intr.K, np.asarray(f.pose, np.float64), origin)
    if labelling == "height":
        return _height_labels(xyz, inst, cfg, counts, float(origin[2]))
    return xyz, lab, inst


def _views(cap: Capture, todo: list[int], reading: Callable[[str], np.ndarray | None]):
    """(intrinsics, c2w, depth metres, the view's own reading or None: capture.readings_of)
    of the frames `todo`, one at a time."""
    for i in todo:
        f = cap.frames[i]
        assert f.depth is not None and f.pose is not None  # checked by _frame_points
        depth = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        yield f.intrinsics, np.asarray(f.pose, np.float64), depth, reading(f.stem)


def _read(
    cap: Capture, reading: Callable[[str], np.ndarray | None], xyz: np.ndarray, view: np.ndarray
) -> np.ndarray:
    """Whether each point xyz [N, 3] (world) lies no farther from its view than that view's
    own reading (capture.readings_of; the same camera as the view's frame, at its own
    resolution) at its pixel, within READ_SLACK: the view read that far along the ray. False
    where the view has no reading there (a hole the fused surface closed or ran through) or
    reads something nearer. bool [N]; the points grouped by view, as run() gathers them."""
    out = np.zeros(len(xyz), bool)
    bounds = np.flatnonzero(np.diff(view)) + 1
    for a, b in zip(np.r_[0, bounds], np.r_[bounds, len(view)], strict=True):
        if a == b:
            continue
        f = cap.frames[int(view[a])]
        got = reading(f.stem)
        if got is None:
            continue
        intr = f.intrinsics.scaled(got.shape[1], got.shape[0])
        d, z = depth_at(xyz[a:b], got, intr.K, np.asarray(f.pose, np.float64), intr.dist)
        out[a:b] = (d > 0) & (d >= z * (1 - READ_SLACK))
    return out


def _local_origin(cap: Capture) -> np.ndarray:
    """The mean camera centre [3] (float64), or 0 when a frame has no pose (caught later)."""
    if any(f.pose is None for f in cap.frames):
        return np.zeros(3)
    return np.mean([np.asarray(f.pose, np.float64)[:3, 3] for f in cap.frames], axis=0)


def _height_labels(
    xyz: np.ndarray, inst: np.ndarray, cfg: ProjectConfig, counts: dict, z0: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Floor (0) below floor_band, occupied (1) up to ceiling_cut, higher points dropped
    (heights z + z0: xyz may be offsets from a point at height z0).
    Returns the points kept [N, 3], their labels [N] and their instances inst [N]."""
    z = xyz[:, 2].astype(np.float64) + z0
    keep = z < cfg.ceiling_cut
    counts["dropped_height"] += int((~keep).sum())
    lab = np.where(z[keep] < cfg.floor_band, 0, 1).astype(np.int64)
    return xyz[keep], lab, inst[keep]


def _labelling(cfg: ProjectConfig, cap: Capture) -> str:
    if cfg.labelling == "height":
        return "height"
    if cap.has_labels:
        return "labels"
    if cfg.labelling == "labels":
        stem = next(f.stem for f in cap.frames if f.label is None)
        raise BlunfError(
            f"{cap.root}: project.labelling='labels' but frame {stem!r} has no label map"
        )
    log.info("project: the capture has no labels; labelling points by height")
    return "height"


def _label_classes(cap: Capture, label: np.ndarray) -> dict[int, str]:
    """The capture's class table without ignored ids, plus a name for every unnamed seen id."""
    classes = {k: v for k, v in cap.classes.items() if k not in cap.ignore and 0 <= k < UNKNOWN}
    for c in np.unique(label).tolist():
        classes.setdefault(int(c), f"class {c}")
    return dict(sorted(classes.items()))

"""Semantics from geometry: classes of the fused mesh (segment.py) ray-cast into every view.

Each view's rays are cast against the mesh with Open3D's RaycastingScene (Embree), the same
rays the fusion stage casts for its clean depth (pixel centres at integer (u, v), Open3D's
at +0.5), so a pixel's label is that of the triangle its depth comes from. Pixels whose ray
hits nothing are UNKNOWN. Lens distortion is ignored (pinhole), as in the fusion stage.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d

from stages.common.capture import UNKNOWN, Capture, Frame, readings_of
from stages.common.classes import (
    CEILING_NAME,
    FLOOR,
    FLOOR_NAME,
    OBJECT,
    STRUCTURE,
    UNKNOWN_NAME,
    WALL,
    WALL_NAME,
)
from stages.common.classes import GEOMETRY as CLASSES
from stages.common.classes import GEOMETRY_IGNORE as IGNORE
from stages.common.errors import BlunfError
from stages.common.io import write_depth_npy, write_json, write_label_png
from stages.common.o3d import o3d_extrinsic, o3d_intrinsic
from stages.semantics.config import (
    SemanticsConfig,
    SemanticsInputs,
    SemanticsOutputs,
)
from stages.semantics.floorfill import Footprint, Reach, floor_past, floor_through
from stages.semantics.innerwalls import inner_walls
from stages.semantics.pointwalls import (
    PointWallOptions,
    evidence_readings,
    point_walls,
    room_directions,
)
from stages.semantics.segment import MoreWalls, segment, triangles
from stages.semantics.segmentation import Segmentation
from stages.semantics.wallfill import wall_through

log = logging.getLogger(__name__)

MISS = np.iinfo(np.uint32).max  # Open3D's INVALID_ID: the ray hit nothing


def run(cfg: SemanticsConfig, inputs: SemanticsInputs, out: Path) -> SemanticsOutputs:
    """Segment the fused mesh and write a class map and an instance map for every view."""
    log.debug("semantics geometry: %s", cfg)  # the full config: meta.json
    t0 = time.perf_counter()
    cap = Capture.load(inputs.frames)
    if not cap.frames:
        raise BlunfError(f"semantics: {inputs.frames} has no frames")
    missing = next((f.stem for f in cap.frames if f.pose is None), None)
    if missing is not None:
        raise BlunfError(f"semantics: frame {missing!r} of {inputs.frames} has no pose")
    mesh = _read_mesh(inputs.mesh)
    verts = mesh.vertex.positions.numpy().astype(np.float64)  # [V, 3]
    tris = mesh.triangle.indices.numpy().astype(np.int64)  # [T, 3]
    t_read = time.perf_counter() - t0

    t0 = time.perf_counter()
    seg = segment(verts, tris, cfg, _point_walls(cfg, inputs, cap))
    t_segment = time.perf_counter() - t0

    outs = SemanticsOutputs.at(out)
    outs.labels.mkdir(parents=True, exist_ok=True)
    outs.instances.mkdir(parents=True, exist_ok=True)
    room, reach = _room(verts, tris, seg, cap, cfg) if cfg.floor_fill.enabled else (None, None)
    hull = cfg.floor_fill.hull or not seg.has_floor
    if room is not None and cfg.objects.outside_unknown:
        out_obj = (seg.cls == OBJECT) & ~room.contains(triangles(verts, tris)[0][:, :2])
        seg.cls[out_obj] = UNKNOWN
        seg.instance[out_obj] = 0
        seg.outside_triangles = int(out_obj.sum())
    t0 = time.perf_counter()
    frames, pixels = _render(mesh, seg, cap, outs, (room, reach), cfg, readings_of(inputs.readings))
    t_render = time.perf_counter() - t0
    sem = replace(cap, frames=tuple(frames), classes=dict(CLASSES), ignore=IGNORE)
    sem.save(outs.frames)

    n_obj = int(seg.instance.max(initial=0))
    planes = {k: sum(p["kind"] == k for p in seg.planes) for k in STRUCTURE}
    stats = {
        "triangles": len(tris),
        "planes": planes,
        "point_walls": sum(p.get("source") == "points" for p in seg.planes),
        "plane_list": seg.planes,
        # vertical planes that were not walls: [length, height (5-95 %, m), area (m²)]
        "vertical_rejected": [[*p["span"], p["area_m2"]] for p in seg.rejected],
        "floor_z": round(seg.floor_z, 4),
        "objects": n_obj,
        "noise_clusters": seg.noise_clusters,  # labelled unknown
        "noise_triangles": seg.noise_triangles,  # labelled unknown
        "floating_clusters": seg.floating_clusters,  # labelled unknown
        "resting_clusters": seg.resting_clusters,  # on a standing object: objects
        "hidden_stand_clusters": seg.hidden_stand_clusters,  # nothing seen under: objects
        "hanger_triangles": seg.hanger_triangles,  # by what hangs before a wall: unknown
        "object_base_z": round(seg.object_base_z, 3),  # clusters stand within objects.max_gap of it
        "outside_triangles": seg.outside_triangles,  # objects outside the room: unknown
        # the floor fill's room: the floor and wall triangles' footprint, or without a floor
        # plane the hull of the surface and the cameras, rays bounded by a reach (m²: cells)
        "floor_fill": None
        if room is None
        else {
            "room": "hull of surface and cameras" if hull else "floor and walls",
            "reach": reach is not None,  # rays bounded by floor_fill.min_drop_deg and .reach
            "room_m2": round(float(room.mask.sum()) * room.cell**2, 2),
        },
        "area_m2": {
            name: round(float(seg.area[seg.cls == k].sum()), 3)
            for k, name in [*CLASSES.items(), (UNKNOWN, UNKNOWN_NAME)]
        },
        "pixels": pixels,  # fraction of all pixels per class over every view
        "views": len(frames),
        "seconds": {
            "read": round(t_read, 3),
            "segment": round(t_segment, 3),
            "render": round(t_render, 3),
        },
    }
    write_json(outs.stats, stats)
    log.info(
        "semantics: %d floor, %d wall, %d ceiling planes; %d objects; %d views in %.1f s",
        planes[FLOOR_NAME],
        planes[WALL_NAME],
        planes[CEILING_NAME],
        n_obj,
        len(frames),
        t_segment + t_render,
    )
    return outs


def _read_mesh(path: Path) -> o3d.t.geometry.TriangleMesh:
    if not Path(path).is_file():
        raise BlunfError(f"{path}: mesh file not found")
    mesh = o3d.t.io.read_triangle_mesh(str(path))
    if "indices" not in mesh.triangle or mesh.triangle.indices.shape[0] == 0:
        raise BlunfError(f"{path}: the mesh has no triangles")
    return mesh


def _render(
    mesh: o3d.t.geometry.TriangleMesh,
    seg: Segmentation,
    cap: Capture,
    outs: SemanticsOutputs,
    fill: tuple[Footprint | None, Reach | None],
    cfg: SemanticsConfig,
    reading: Callable[[str], np.ndarray | None] = lambda stem: None,
) -> tuple[list[Frame], dict[str, float]]:
    """Class and instance maps of every view; returns the frames pointing at them and the
    fraction of pixels per class over all views (and of floor seen through the surface).

    With a room (fill: the room and the rays' reach, floorfill.py), the floor seen through
    the surface within it (plane_dist metres beyond the plane) is labelled floor, and each
    view's depth is written with it; with walls.fill, so are the walls seen through it
    (wallfill.py), the nearer crossing winning; and the floor a view's own `reading` lies on
    past the surface (floorfill.floor_past)."""
    room, reach = fill
    margin = cfg.planes.plane_dist
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    cls = np.append(seg.cls, np.uint8(UNKNOWN))  # [T + 1]: the last entry is "no hit"
    inst = np.append(seg.instance, 0)  # [T + 1]
    wide = inst.max(initial=0) > 255
    walls = tuple(p for p in seg.planes if p["kind"] == WALL_NAME)
    # the point walls are plain walls seen through by construction: always filled
    fill_walls = tuple(w for w in walls if cfg.walls.fill or w.get("source") == "points")
    counts = np.zeros(256, np.int64)
    frames, filled, walled = [], 0, 0
    if room is not None:
        outs.depth.mkdir(parents=True, exist_ok=True)
    for f in cap.frames:
        k = f.intrinsics
        rays = scene.create_rays_pinhole(o3d_intrinsic(k), o3d_extrinsic(f), k.width, k.height)
        hit = scene.cast_rays(rays)
        prim = hit["primitive_ids"].numpy().astype(np.int64)  # [H, W]
        prim[prim == MISS] = len(cls) - 1
        label = cls[prim]  # [H, W] uint8
        if room is not None:
            t = hit["t_hit"].numpy()  # [H, W]: the depth (Open3D's rays have camera z = 1)
            r = rays.numpy()
            floor = floor_through(r, t, seg.floor_z, room, margin, walls, reach)  # [H, W]
            got = reading(f.stem) if cfg.floor_fill.past > 0 else None  # past a fattened rim
            if got is not None:
                past = floor_past(r, t, got, seg.floor_z, room, cfg.floor_fill.past, margin)
                floor = np.where((floor > 0) | (label == WALL), floor, past)  # not past a wall
            wall = (
                wall_through(r, t, fill_walls, seg.floor_z, room, margin)[0]
                if fill_walls
                else np.zeros_like(t)
            )
            wall = np.where((wall > 0) & ((floor == 0) | (wall < floor)), wall, 0.0)
            floor = np.where(wall > 0, 0.0, floor)
            seen = floor > 0
            label = np.where(seen, np.uint8(FLOOR), label)
            label = np.where(wall > 0, np.uint8(WALL), label)
            prim[seen | (wall > 0)] = len(cls) - 1  # no instance
            filled += int(seen.sum())
            walled += int((wall > 0).sum())
            dpath = outs.depth / f"{f.stem}.npy"
            write_depth_npy(dpath, np.where(seen, floor, np.where(wall > 0, wall, t)))
            f = replace(f, depth=dpath)
        counts += np.bincount(label.reshape(-1), minlength=256)
        path = outs.labels / f"{f.stem}.png"
        write_label_png(path, label)
        ids = inst[prim].astype(np.uint16 if wide else np.uint8)  # [H, W]
        ipath = outs.instances / f"{f.stem}.png"
        write_label_png(ipath, ids)
        frames.append(replace(f, label=path, instance=ipath))
    total = max(int(counts.sum()), 1)
    names = {**CLASSES, UNKNOWN: UNKNOWN_NAME}
    pixels = {name: round(int(counts[k]) / total, 4) for k, name in names.items()}
    return frames, {
        **pixels,
        "floor_seen_through": round(filled / total, 4),
        "wall_seen_through": round(walled / total, 4),
    }


def _point_walls(cfg: SemanticsConfig, inputs: SemanticsInputs, cap: Capture
                 ) -> MoreWalls | None:  # fmt: skip
    """The segmentation's walls from the views' readings (pointwalls.py), or None when
    point_walls is off or no readings are given."""
    if not (cfg.point_walls.enabled and inputs.evidence):
        return None
    pts, eyes = evidence_readings([Capture.load(p) for p in inputs.evidence])
    cams = np.array([f.pose[:3, 3] for f in cap.frames if f.pose is not None])  # [N, 3]
    opt = PointWallOptions(
        dist=cfg.point_walls.dist,
        min_length=cfg.walls.min_length,
        min_height=cfg.point_walls.min_height,
        min_area=cfg.point_walls.min_area,
        max_beyond=cfg.point_walls.max_beyond,
        beyond_rel=cfg.point_walls.beyond_rel,
        top=cfg.planes.ceiling_min_z,
    )
    log.info("semantics: %d readings for the point walls", len(pts))

    def more(c: np.ndarray, n: np.ndarray, area: np.ndarray, floor_z: float) -> list[dict]:
        if len(pts) == 0:
            return []
        dirs = room_directions(pts, opt.dist)
        walls = point_walls(pts, cams, dirs, floor_z, opt, eyes)
        if cfg.point_walls.inner:
            walls += inner_walls(pts, eyes, dirs, floor_z, opt, cfg.walls.behind, walls)
        return walls

    return more


def _room(
    verts: np.ndarray, tris: np.ndarray, seg: Segmentation, cap: Capture, cfg: SemanticsConfig
) -> tuple[Footprint | None, Reach | None]:
    """Where the floor may be seen through the surface and how far a ray may reach it: the
    footprint of the floor and wall triangles, any reach. Without a floor plane (z = 0, the
    align stage's floor, stands in for it) the convex hull of the surface and the cameras,
    within the config's reach (floorfill.py), or nothing when floor_fill.no_plane is off; with
    floor_fill.hull, that hull at the found floor's height too, within that reach unless
    floor_fill.hull_reach is off."""
    found = seg.has_floor
    if cfg.floor_fill.hull or not found:
        if not (cfg.floor_fill.no_plane or found):
            return None, None
        c = triangles(verts, tris)[0]  # [T, 3] centres
        cams = np.array([f.pose[:3, 3] for f in cap.frames if f.pose is not None])  # [N, 3]
        xy = np.concatenate([c[:, :2], cams[:, :2]])
        bound = not found or cfg.floor_fill.hull_reach
        reach = Reach(cfg.floor_fill.min_drop_deg, cfg.floor_fill.reach) if bound else None
        return Footprint.of(xy, cfg.floor_fill.cell, hull=True), reach
    keep = (seg.cls == FLOOR) | (seg.cls == WALL)
    c = triangles(verts, tris[keep])[0]  # [K, 3] centres
    return Footprint.of(c[:, :2], cfg.floor_fill.cell), None

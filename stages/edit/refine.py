"""Finer outlines round the selected objects: their depth fused again in a small box.

The fused mesh outlines what an edit changes in the fast render path (stages/edit/surface.py)
and, through its ray-cast depth, what the field learnt. At the fusion stage's 2 cm voxels
and 8 cm truncation a thin part is smeared: the TSDF seen from either side of a chair's
3.5 cm leg averages into a surface pushed ~1 cm off, and on the demo room (remove chair_2)
that misplaced outline was most of what the removal missed (per view, 157 / 69 / 88 of its
224 / 187 / 88 missed pixels were chair pixels whose fused surface lay elsewhere; the rest,
leg bottoms below floor_clear and seat edges outside the plan's footprint). Here the depth
the fusion stage read (sensor or stereo, not its ray-cast) is cropped to a box round each
selection and fused again as the fusion stage fuses (Open3D's VoxelBlockGrid, sized by
stages.common.o3d's block probe as the fusion stage sizes its own) at a finer voxel and a
truncation thinner than the parts; the fine surface replaces the coarse one inside the boxes (coarse
faces entirely inside a box go, fine faces whose centroid lies inside one come in: the
seams overlap rather than crack).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stages.common.camera import depth_to_points
from stages.common.capture import Capture, Frame
from stages.common.io import read_depth
from stages.common.o3d import CPU, o3d_extrinsic, o3d_intrinsic, o3d_tensor, touched_blocks
from stages.edit.select import Extent

log = logging.getLogger(__name__)

Box = tuple[np.ndarray, np.ndarray]  # (lo [3], hi [3]) world metres
BLOCK = 16  # voxels along a hashed block's side (the fusion stage's)
DEPTH_MAX = 10.0  # metres: readings beyond are not fused (the boxes crop them first anyway)
WEIGHT_THRESHOLD = 0.5  # a voxel is surface when a frame saw it (the fusion stage's default)


def boxes_of(extents: Sequence[Extent], vertices: np.ndarray, margin: float) -> list[Box]:
    """One box per extent: its footprint's bbox and height range (an open top capped at the
    fused geometry's), grown by `margin` metres on every side."""
    top = float(np.max(vertices[:, 2])) if len(vertices) else 3.0
    out = []
    for e in extents:
        fp = e.footprint
        if not fp.any():
            continue
        x0, y0, x1, y1 = e.bbox()
        z0 = float(np.min(e.zlo[fp]))
        z1 = min(float(np.max(e.zhi[fp])), top)
        out.append((np.array([x0, y0, z0]) - margin, np.array([x1, y1, z1]) + margin))
    return out


def _inside(x: np.ndarray, boxes: Sequence[Box], grow: float = 0.0) -> np.ndarray:
    """Which points x [N, 3] lie inside any of `boxes` grown by `grow` metres. bool [N]."""
    res = np.zeros(len(x), bool)
    for lo, hi in boxes:
        res |= np.all((x >= lo - grow) & (x <= hi + grow), axis=1)
    return res


def refine_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    boxes: Sequence[Box],
    frames: Path,
    voxel: float,
    trunc_voxels: float,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The mesh (vertices [V, 3], faces [F, 3]) with its surface inside `boxes` fused again
    from the depth of `frames` (frames.json) at `voxel` metres and `trunc_voxels`. Returns
    the new vertices, faces and facts (faces swapped, seconds); the mesh unchanged, with
    the reason, when no depth falls in the boxes."""
    t0 = time.perf_counter()
    facts: dict = {"boxes": len(boxes), "voxel": voxel, "trunc_voxels": trunc_voxels}
    if not boxes:
        return vertices, faces, {**facts, "skipped": "no box"}
    cap = Capture.load(frames)
    reach = trunc_voxels * voxel + voxel  # depth a little outside a box still shapes its inside
    crops = []  # (frame, its depth readings near a box [H, W] float32 metres)
    for f in cap.frames:
        if f.depth is None or f.pose is None:
            continue
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid).astype(np.float32)
        pts, idx = depth_to_points(d, f.intrinsics.K, np.asarray(f.pose))
        near = idx[_inside(pts, boxes, reach)]
        if len(near):
            crop = np.zeros(d.size, np.float32)
            crop[near] = d.reshape(-1)[near]
            crops.append((f, crop.reshape(d.shape)))
    n_in = sum(int((c > 0).sum()) for _, c in crops)
    if n_in == 0:
        return vertices, faces, {**facts, "skipped": "no depth reading in the boxes"}
    fv, ff = _fuse(crops, voxel, trunc_voxels)
    ff = ff[_inside(fv[ff].mean(axis=1), boxes)]
    if len(ff) == 0:
        return vertices, faces, {**facts, "skipped": "no surface fused in the boxes"}
    v = np.asarray(vertices, np.float64)
    tri = np.asarray(faces, np.int64)
    inner = _inside(v, boxes)  # [V]
    keep = ~inner[tri].all(axis=1)  # a coarse face goes when all its corners are inside
    facts.update(
        {
            "depth_readings": n_in,
            "coarse_faces_dropped": int((~keep).sum()),
            "fine_faces": int(len(ff)),
            "seconds": round(time.perf_counter() - t0, 3),
        }
    )
    log.info(
        "edit: outlines refined in %d boxes: %d coarse faces -> %d at %.3f m (%.1f s)",
        len(boxes), facts["coarse_faces_dropped"], len(ff), voxel, facts["seconds"],
    )  # fmt: skip
    return np.concatenate([v, fv]), np.concatenate([tri[keep], ff + len(v)]), facts


def _fuse(
    crops: Sequence[tuple[Frame, np.ndarray]], voxel: float, trunc_voxels: float
) -> tuple[np.ndarray, np.ndarray]:
    """The TSDF of the cropped depth maps (Open3D's VoxelBlockGrid, as the fusion stage
    fuses, without colour): mesh vertices [V, 3] and faces [F, 3] (none when nothing fused)."""
    import open3d as o3d  # late: the CLI starts fast
    import open3d.core as o3c

    def image(d: np.ndarray) -> o3d.t.geometry.Image:
        return o3d.t.geometry.Image(o3d_tensor(d[..., None], o3c.float32))

    def grid(blocks: int) -> o3d.t.geometry.VoxelBlockGrid:
        f32, sv = o3c.float32, o3c.SizeVector
        return o3d.t.geometry.VoxelBlockGrid(
            ("tsdf", "weight"), (f32, f32), (sv([1]), sv([1])), voxel, BLOCK, blocks, CPU
        )

    probe, seen = grid(1), set[int]()
    coords: list[o3c.Tensor | None] = []
    for f, d in crops:
        coords.append(
            touched_blocks(
                probe, image(d), o3d_intrinsic(f.intrinsics), o3d_extrinsic(f), DEPTH_MAX,
                trunc_voxels, seen,
            )
        )  # fmt: skip
    if not seen:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    vbg = grid(len(seen))
    for (f, d), got in zip(crops, coords, strict=True):
        if got is not None:
            vbg.integrate(
                got, image(d), o3d_intrinsic(f.intrinsics), o3d_extrinsic(f), 1.0, DEPTH_MAX,
                trunc_voxels,
            )  # fmt: skip
    mesh = vbg.extract_triangle_mesh(WEIGHT_THRESHOLD)
    v = mesh.vertex.positions.numpy().astype(np.float64)
    t = mesh.triangle.indices.numpy().astype(np.int64) if "indices" in mesh.triangle else None
    return v, (np.zeros((0, 3), np.int64) if t is None else t)

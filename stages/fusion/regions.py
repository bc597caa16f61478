"""Fusion of a large scene region by region, so that memory follows the largest region.

One voxel block grid for a whole home holds every block any view touched (80 kB a block at
16³ voxels), and extracting its mesh allocates tables of the same size again. When the
views touch more voxels than `fusion.region_mb` holds, the blocks are split into boxes (a
k-d split along the longest side, at the median block, until each box holds at most that)
and each box is fused on its own grid: every frame integrates only its blocks inside the
box grown by one block on every side, the mesh and cloud are extracted, what lies in the box
itself is kept, and the grid is freed before the next box.

Why the result is the very same surface as one grid's: a voxel's TSDF depends only on the
frames integrated into its block, in their order, and every block in the grown box receives
exactly the frames it receives in one grid, in the same order. Marching cubes and the
normals of a point or vertex inside the box read voxels at most two voxels away, inside the
grown box (a block is 8-16 voxels). What is kept is decided by position (the block a point,
a vertex or a triangle's centroid falls in), the same rule for every box, so each piece of
surface is kept by exactly one box; the vertices a kept triangle shares with the next box's
are kept by both, at the very same position, and `canonical_mesh` merges them.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
import open3d as o3d
import open3d.core as o3c

from stages.common.errors import BlunfError
from stages.common.o3d import CPU, o3d_tensor
from stages.common.rows import unique_rows

log = logging.getLogger(__name__)

Box = tuple[np.ndarray, np.ndarray]  # block coordinates [3] lo (inclusive), hi (exclusive)


def fuse(
    frames: list[tuple], budget: int, block_size: float,
    new_grid: Callable[[int], o3d.t.geometry.VoxelBlockGrid],
    integrate: Callable[[o3d.t.geometry.VoxelBlockGrid, list, str], float],
    extract: Callable[[o3d.t.geometry.VoxelBlockGrid], tuple],
) -> tuple[o3d.t.geometry.TriangleMesh, o3d.t.geometry.PointCloud, dict]:  # fmt: skip
    """The mesh and cloud of (frame, its block coordinates [M, 3] int32) fused box by box.

    Args:
        new_grid: an empty grid of n blocks; integrate: fuses (frame, blocks) pairs into a
            grid and returns Open3D's seconds; extract: a grid's (mesh, cloud).
    Returns the merged mesh and cloud (vertices shared by two boxes twice, the order not yet
    canonical) and facts (blocks held in all, regions, the largest grid's blocks, Open3D's
    integration seconds, extraction seconds).
    """
    blocks = unique_rows(np.concatenate([bc.numpy() for _, bc in frames]))[0]
    boxes = split(blocks, budget)
    mesh_parts, cloud_parts = [], []
    t_o3d = t_extract = 0.0
    largest = held = 0
    index_dtype = None
    for i, box in enumerate(boxes):
        grown = int(inside(blocks, box, 1).sum())
        grid = new_grid(grown)
        mine = []
        for f, bc in frames:
            c = bc.numpy()
            m = inside(c, box, 1)
            if m.any():
                mine.append((f, o3d_tensor(c[m], bc.dtype)))
        t_o3d += integrate(grid, mine, f"fusion region {i + 1}/{len(boxes)}")
        t0 = time.perf_counter()
        mesh, cloud = extract(grid)
        t_extract += time.perf_counter() - t0
        largest, held = max(largest, grown), held + int(grid.hashmap().size())
        del grid  # freed before the next box's grid
        if mesh.vertex.positions.shape[0]:
            mesh_parts.append(keep_mesh(mesh, box, block_size))
            index_dtype = mesh.triangle.indices.dtype
        if cloud.point.positions.shape[0]:
            cloud_parts.append(keep_cloud(cloud, box, block_size))
        del mesh, cloud
    log.info("fusion: %d regions of at most %d blocks (%d blocks in all, %d held)",
             len(boxes), largest, len(blocks), held)  # fmt: skip
    if not mesh_parts or not cloud_parts:
        raise BlunfError(f"fusion: no surface fused from the {len(frames)} frames with depth")
    t0 = time.perf_counter()
    mesh, cloud = merged_mesh(mesh_parts, index_dtype), merged_cloud(cloud_parts)
    t_extract += time.perf_counter() - t0
    facts = {"blocks": held, "regions": len(boxes), "largest_grid": largest}
    return mesh, cloud, {**facts, "integrate_open3d_seconds": t_o3d, "extract_seconds": t_extract}


def split(blocks: np.ndarray, budget: int) -> list[Box]:
    """Boxes of block coordinates covering `blocks` [B, 3], each holding at most `budget`
    of them (a box of blocks all at one coordinate is never split further)."""
    out: list[Box] = []
    todo = [blocks]
    while todo:
        b = todo.pop()
        lo, hi = b.min(axis=0), b.max(axis=0) + 1
        ext = hi - lo
        if len(b) <= budget or ext.max() <= 1:
            out.append((lo, hi))
            continue
        axis = int(np.argmax(ext))
        cut = max(int(np.median(b[:, axis])), int(lo[axis]) + 1)
        below = b[:, axis] < cut
        todo += [b[~below], b[below]]
    return sorted(out, key=lambda box: tuple(box[0]))


def inside(coords: np.ndarray, box: Box, grow: int = 0) -> np.ndarray:
    """Which block coordinates [M, 3] lie in the box grown by `grow` blocks -> [M] bool."""
    lo, hi = box
    return np.all((coords >= lo - grow) & (coords < hi + grow), axis=1)


def owned(points: np.ndarray, box: Box, block_size: float) -> np.ndarray:
    """Which world points [N, 3] fall in a block of the box -> [N] bool."""
    return inside(np.floor(points.astype(np.float64) / block_size).astype(np.int64), box)


def keep_mesh(mesh: o3d.t.geometry.TriangleMesh, box: Box, block_size: float) -> dict:
    """The part of a box's mesh the box keeps, as numpy arrays: its triangles whose centroid
    lies in the box, and its vertices that lie in the box or that those triangles use."""
    pos = mesh.vertex.positions.numpy()
    tri = mesh.triangle.indices.numpy().astype(np.int64)
    t_keep = owned(pos[tri].mean(axis=1), box, block_size) if len(tri) else np.zeros(0, bool)
    v_keep = owned(pos, box, block_size)
    v_keep[tri[t_keep].ravel()] = True
    new_id = np.cumsum(v_keep) - 1
    return {
        "vertex": {k: v.numpy()[v_keep] for k, v in mesh.vertex.items()},
        "triangles": new_id[tri[t_keep]],
    }


def keep_cloud(cloud: o3d.t.geometry.PointCloud, box: Box, block_size: float) -> dict:
    """The box's points (numpy arrays by attribute) that lie in the box."""
    keep = owned(cloud.point.positions.numpy(), box, block_size)
    return {k: v.numpy()[keep] for k, v in cloud.point.items()}


def merged_mesh(parts: list[dict], index_dtype) -> o3d.t.geometry.TriangleMesh:
    """One mesh of the boxes' parts (vertices shared by two boxes appear twice: canonical_mesh
    merges them)."""
    out = o3d.t.geometry.TriangleMesh(CPU)
    offsets = np.cumsum([0] + [len(p["vertex"]["positions"]) for p in parts])
    for key in parts[0]["vertex"]:
        out.vertex[key] = _tensor(np.concatenate([p["vertex"][key] for p in parts]))
    tri = np.concatenate([p["triangles"] + o for p, o in zip(parts, offsets, strict=False)])
    out.triangle.indices = o3d_tensor(tri.reshape(-1, 3), index_dtype)
    return out


def _tensor(a: np.ndarray) -> o3c.Tensor:
    """An Open3D tensor on the CPU of the array's own dtype."""
    # open3d's stub makes dtype required; it defaults to None (the array's dtype)
    return o3c.Tensor(np.ascontiguousarray(a), device=CPU)  # type: ignore[call-overload]


def merged_cloud(parts: list[dict]) -> o3d.t.geometry.PointCloud:
    """One cloud of the boxes' points."""
    out = o3d.t.geometry.PointCloud(CPU)
    for key in parts[0]:
        out.point[key] = _tensor(np.concatenate([p[key] for p in parts]))
    return out

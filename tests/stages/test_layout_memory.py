"""The layout stage's memory: the mesh is read as the float32 vertices and uint32 triangles
its one ray-casting scene needs, nothing more (a home's fused mesh is millions of triangles:
the stage's peak is the mesh's, not the plan's)."""

from __future__ import annotations

import sys
import tracemalloc

import numpy as np
import open3d as o3d
import pytest
import trimesh
from shapely import contains_xy
from shapely.geometry import box

from stages.common import heap
from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN
from stages.layout import LayoutConfig, openings, walls
from stages.layout.meshfile import read_mesh
from stages.layout.walls import build_plan

N = 400  # floor quads a side: 320 000 floor triangles, the bulk of the mesh


def _room(n: int = N) -> tuple[np.ndarray, np.ndarray]:
    """A 4 x 3 m room, 2.5 m walls facing in, its floor a fine grid as fusion leaves it."""
    x, y = np.meshgrid(np.linspace(0, 4, n + 1), np.linspace(0, 3, n + 1))
    verts = [np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)]
    i = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    tris = [
        np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    ]
    k = len(verts[0])
    for p, q in (((0, 0), (4, 0)), ((4, 0), (4, 3)), ((4, 3), (0, 3)), ((0, 3), (0, 0))):
        verts.append(np.array([(*q, 0.0), (*p, 0.0), (*p, 2.5), (*q, 2.5)]))
        tris.append(np.array([[0, 1, 2], [0, 2, 3]]) + k)
        k += 4
    return np.concatenate(verts), np.concatenate(tris)


def _fused_ply(path, verts: np.ndarray, tris: np.ndarray) -> None:  # noqa: ANN001
    """As the fusion stage writes its mesh: Open3D, double vertices, normals, colours."""
    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris)
    )
    m.compute_vertex_normals()
    m.vertex_colors = o3d.utility.Vector3dVector(np.full((len(verts), 3), 0.5))
    o3d.io.write_triangle_mesh(str(path), m)


def _blueprint() -> Blueprint:
    grid = Grid.covering(np.array([-0.3, -0.3]), np.array([4.3, 3.3]), 0.02)
    c = grid.centers()
    labels = np.full(grid.shape, UNKNOWN, np.uint8)
    labels[contains_xy(box(-0.1, -0.1, 4.1, 3.1), c[..., 0], c[..., 1])] = 1
    labels[contains_xy(box(0.0, 0.0, 4.0, 3.0), c[..., 0], c[..., 1])] = 0
    return Blueprint(labels, grid, {0: "floor", 1: "wall"})


def test_the_mesh_is_read_as_a_general_reader_reads_it_in_float32_and_uint32(tmp_path):
    verts, tris = _room(8)
    _fused_ply(tmp_path / "fused.ply", verts, tris)  # the lean reader's: binary, triangles
    trimesh.Trimesh(verts, tris, process=False).export(tmp_path / "mesh.obj")  # trimesh's
    for name in ("fused.ply", "mesh.obj"):
        v, t = read_mesh(tmp_path / name)
        assert v.dtype == np.float32 and t.dtype == np.uint32
        m = trimesh.load(tmp_path / name, process=False, force="mesh")
        np.testing.assert_array_equal(v, np.asarray(m.vertices, np.float32))
        np.testing.assert_array_equal(t, np.asarray(m.faces))
        np.testing.assert_allclose(v, verts, atol=1e-6)


def test_the_plan_of_a_room_holds_little_more_than_its_mesh_at_most(tmp_path, monkeypatch):
    verts, tris = _room()
    _fused_ply(tmp_path / "mesh.ply", verts, tris)
    bp, cfg = _blueprint(), LayoutConfig(face_offset=0.0)
    scenes = []
    for mod in (walls, openings):
        made = mod.scene_of
        monkeypatch.setattr(mod, "scene_of", lambda v, t, made=made: scenes.append(1) or made(v, t))
    build_plan(bp, cfg)  # warm: what the plan alone allocates once (imports, caches)
    tracemalloc.start()
    plain = build_plan(bp, cfg)
    bare = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    plan = build_plan(bp, cfg, tmp_path / "mesh.ply")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert len(plan["rooms"]) == len(plain["rooms"]) == 1
    assert abs(plan["rooms"][0]["area"] - 12.0) < 0.2
    # the float32 vertices and uint32 triangles, and the file's records they are read from:
    # measured 1.6x them; a general reader (float64 vertices, normals, colours, int64 faces,
    # parse buffers) held 14x them
    need = verts.size * 4 + tris.size * 4
    assert peak - bare < 3 * need, (peak - bare) / need
    # one scene for the stage (each holds its own copy of the mesh and its BVH)
    assert len(scenes) == 1


def test_rays_cast_round_many_points_are_cast_a_batch_at_a_time():
    # a home's unseen floor: tens of thousands of points, AROUND rays each
    verts, tris = _room(8)
    scene = openings.scene_of(verts, tris)
    g = np.stack(np.meshgrid(np.linspace(-1, 5, 250), np.linspace(-1, 4, 200)), -1).reshape(-1, 2)
    tracemalloc.start()
    inside = openings.enclosed(scene, g)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    x, y = g.T
    assert inside[(x > 0.01) & (x < 3.99) & (y > 0.01) & (y < 2.99)].all()
    assert not inside[(x < -0.01) | (x > 4.01) | (y < -0.01) | (y > 3.01)].any()
    # measured 10 MB batched; all the rays at once held 78 MB (50 000 points x 16 rays)
    assert peak < 25e6, peak


def _resident_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(x.split()[1]) / 1024 for x in f if x.startswith("VmRSS:"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap, /proc")
def test_the_heaps_free_pages_go_back_before_the_scene_is_built(tmp_path, monkeypatch):
    # what earlier stages freed stays in the heap; Embree's scene does not come from it
    blocks = [bytearray(b"x" * 65536) for _ in range(1600)]  # 100 MB of heap, touched
    keep = bytearray(b"x" * 65536)  # over them: free() alone hands back only the heap's top
    before = _resident_mb()
    del blocks
    freed = _resident_mb()
    heap.heap_returned()
    after = _resident_mb()
    assert before - freed < 20, (before, freed)  # freed, still resident
    assert freed - after > 80, (freed, after)  # handed back
    del keep
    # and the stage hands them back before it reads the mesh and builds its scene
    verts, tris = _room(8)
    _fused_ply(tmp_path / "mesh.ply", verts, tris)
    order = []
    monkeypatch.setattr(walls, "heap_returned", lambda: order.append("heap"))
    read = walls.read_mesh
    monkeypatch.setattr(walls, "read_mesh", lambda p: order.append("read") or read(p))
    build_plan(_blueprint(), LayoutConfig(face_offset=0.0), tmp_path / "mesh.ply")
    assert order == ["heap", "read"]

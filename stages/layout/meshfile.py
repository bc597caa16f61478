"""The layout's mesh in memory.

`read_mesh`: float32 vertices and uint32 triangles straight from a binary PLY (the fusion
stage's mesh.ply), without the float64 vertices, normals, colours and parse buffers a general
loader holds (on a 3-room home's 1.26 M-triangle mesh: 334 MB resident that the process
keeps). Other files go through trimesh. Open3D's own tensor reader
(`o3d.t.io.read_triangle_mesh`, whose mesh `RaycastingScene.add_triangles` takes whole) is
not as lean: on the 5-room home's 2.9 M-triangle mesh (240 views) it peaks 254 MB over the
process while reading against 123 MB here, keeps 119 MB against 59 MB (float32 normals and
colours, int64 triangles), and read then cast into one scene peaks 377 MB against 341 MB.

Before it is read, the heap's free pages go back to the system (stages/common/heap.py):
Embree's scene and BVH do not come from the heap, and were added on top of what earlier
stages freed. On the 5-room home (240 views, sensor depth) the process held 1165 MB as the
layout started, 556 MB once the free pages went back; reading its 2.9 M-triangle mesh and
building the scene takes 352 MB (the stage alone on that run's inputs: 169 MB on the 3-room
home, 90 MB on the demo room)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from stages.common.errors import BlunfError
from stages.common.ply import read_header


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float32 [V, 3], triangles uint32 [T, 3]) of the mesh file at `path`."""
    try:
        lean = _binary_ply(Path(path))
        if lean is not None:
            return lean
        m = trimesh.load(path, process=False, force="mesh")
        return (
            np.asarray(m.vertices, np.float32),  # type: ignore[attr-defined]
            np.asarray(m.faces, np.uint32).reshape(-1, 3),  # type: ignore[attr-defined]
        )
    except (OSError, ValueError, AttributeError, KeyError) as e:
        raise BlunfError(f"{path}: cannot read the mesh ({e})") from None


def _binary_ply(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The arrays of a little-endian binary PLY of a vertex element (x, y, z among scalar
    properties) then a face element of one list property, every face a triangle; None for
    any other file (read elsewhere)."""
    with open(path, "rb") as f:
        header = read_header(f)
        if header is None:
            return None
        fmt, elements = header
        if fmt != "binary_little_endian" or [e[0] for e in elements] != ["vertex", "face"]:
            return None
        (_, nv, vprops), (_, nf, fprops) = elements
        if any(not isinstance(t, str) for _, t in vprops) or len(fprops) != 1:
            return None
        names = [p for p, _ in vprops]
        if not {"x", "y", "z"} <= set(names):
            return None
        count_t, index_t = fprops[0][1]
        if count_t is None or index_t is None:
            return None
        vdt = np.dtype([(p, "<" + t) for p, t in vprops])
        v = np.fromfile(f, vdt, nv)
        if len(v) != nv:
            return None
        verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
        del v  # the vertex records (normals, colours) go before the faces are read
        fdt = np.dtype([("n", "<" + count_t), ("i", "<" + index_t, (3,))])
        faces = np.fromfile(f, fdt, nf)
    if len(faces) != nf or (nf and (faces["n"] != 3).any()):
        return None  # short, or faces other than triangles: the general reader's
    tris = faces["i"].astype(np.uint32)
    if nf and (tris.max() >= nv or (faces["i"] < 0).any()):
        raise ValueError(f"a face indexes a vertex beyond the {nv} there are")
    return verts, tris

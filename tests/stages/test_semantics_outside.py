"""Objects outside the room's footprint (semantics.objects.outside_unknown): the exact room of
test_semantics with a box standing on the floor's level 0.3 m beyond its east wall."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import trimesh

from stages.common.camera import Intrinsics
from stages.semantics import IMPLS, SemanticsConfig, SemanticsInputs
from stages.semantics.config import ObjectsConfig
from tests.stages.test_semantics import _look, _views_capture, exact_room


def test_an_object_behind_a_wall_is_unknown_only_when_asked(tmp_path):
    verts, tris, _, _ = exact_room()
    box = trimesh.creation.box(bounds=[(4.3, 1.0, 0.0), (4.8, 1.5, 0.5)])
    box_v, box_f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.05)
    tris = np.concatenate([tris, box_f + len(verts)])
    verts = np.concatenate([verts, box_v])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris.astype(np.int32))
    )
    o3d.io.write_triangle_mesh(tmp_path / "mesh.ply", mesh)
    _views_capture(tmp_path, [_look((2.0, 1.5, 1.5), (3.0, 1.5, 0.0))],
                   Intrinsics(20.0, 20.0, 15.5, 11.5, 32, 24))  # fmt: skip
    inputs = SemanticsInputs(tmp_path / "frames.json", tmp_path / "mesh.ply")
    stats = {}
    for flag in (False, True):
        out = tmp_path / f"out{int(flag)}"
        out.mkdir()
        outs = IMPLS["geometry"](
            SemanticsConfig(objects=ObjectsConfig(outside_unknown=flag)), inputs, out
        )
        stats[flag] = json.loads(outs.stats.read_text())
    assert stats[False]["objects"] == stats[True]["objects"] + 1
    assert stats[False]["outside_triangles"] == 0
    assert stats[True]["outside_triangles"] == len(box_f)
    lost = stats[False]["area_m2"]["object"] - stats[True]["area_m2"]["object"]
    assert abs(lost - 6 * 0.5 * 0.5) < 1e-3  # the whole box, its six faces

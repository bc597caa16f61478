"""A written PLY is checked against the size its header declares (stages/common/ply.py):
Open3D's writers cut a file short on a full disk without an error."""

from __future__ import annotations

import open3d as o3d
import pytest

from stages.common.errors import BlunfError
from stages.common.ply import check_written
from stages.layout.meshfile import read_mesh


def test_a_whole_ply_passes_a_cut_one_names_the_file(tmp_path):
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_sphere())
    mesh.vertex.colors = mesh.vertex.positions.abs().clip(0.0, 1.0)
    cloud = o3d.t.geometry.PointCloud(mesh.vertex.positions)
    m, c = tmp_path / "mesh.ply", tmp_path / "cloud.ply"
    o3d.t.io.write_triangle_mesh(str(m), mesh)
    o3d.t.io.write_point_cloud(str(c), cloud)
    check_written(m)
    check_written(c)
    assert read_mesh(m)[1].shape == (mesh.triangle.indices.shape[0], 3)
    data = m.read_bytes()
    m.write_bytes(data[:-1])  # one byte short
    with pytest.raises(BlunfError, match=rf"{m}: cannot write \(\d+ of \d+ bytes"):
        check_written(m)
    m.write_bytes(data[:40])  # inside the header
    with pytest.raises(BlunfError, match=rf"{m}: cannot write \(its header is cut"):
        check_written(m)
    o3d.io.write_triangle_mesh(str(m), mesh.to_legacy(), write_ascii=True)
    check_written(m)  # ASCII: not checked

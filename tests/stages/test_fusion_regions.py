"""Fusion region by region (stages/fusion/regions.py) gives the surface of one grid."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from stages.common.errors import BlunfError
from stages.fusion import FusionConfig
from stages.fusion.regions import split
from tests.stages.exact_room import fuse, room_capture


def test_split_boxes_cover_every_block_once_and_hold_at_most_the_budget():
    rng = np.random.default_rng(0)
    blocks = np.unique(rng.integers(0, 30, size=(3000, 3)), axis=0)
    boxes = split(blocks, 200)
    counts = np.zeros(len(blocks), int)
    for lo, hi in boxes:
        m = np.all((blocks >= lo) & (blocks < hi), axis=1)
        assert 0 < m.sum() <= 200
        counts += m
    assert (counts == 1).all()
    assert len(split(blocks, len(blocks))) == 1


def test_tiled_fusion_gives_the_surface_of_one_grid(tmp_path):
    """The exact room (4 x 3 m, 8 cm blocks) fused on one grid and in regions of at most
    1.5 MB of voxels (153 blocks of 8^3, of ~700): the same vertices, triangles and points,
    to the bit."""
    frames = room_capture(tmp_path / "cap")
    whole = fuse(frames, tmp_path / "whole", region_mb=0)
    tiled = fuse(frames, tmp_path / "tiled", region_mb=1.5)
    s_whole = json.loads(whole.stats.read_text())
    s_tiled = json.loads(tiled.stats.read_text())
    assert s_whole["regions"] == 1 and s_tiled["regions"] >= 4, s_tiled
    assert s_tiled["voxel_memory_mb"] < 0.5 * s_whole["voxel_memory_mb"]
    m_whole = o3d.t.io.read_triangle_mesh(str(whole.mesh))
    m_tiled = o3d.t.io.read_triangle_mesh(str(tiled.mesh))
    assert m_whole.triangle.indices.shape[0] > 1000
    for key in ("positions", "normals", "colors"):
        np.testing.assert_array_equal(m_tiled.vertex[key].numpy(), m_whole.vertex[key].numpy())
    np.testing.assert_array_equal(
        m_tiled.triangle.indices.numpy(), m_whole.triangle.indices.numpy()
    )
    c_whole = o3d.t.io.read_point_cloud(str(whole.cloud))
    c_tiled = o3d.t.io.read_point_cloud(str(tiled.cloud))
    for key in ("positions", "normals", "colors"):
        np.testing.assert_array_equal(c_tiled.point[key].numpy(), c_whole.point[key].numpy())
    assert whole.mesh.read_bytes() == tiled.mesh.read_bytes()
    # the clean depth ray-cast from it is the same too
    for d in sorted(whole.depth.iterdir()):
        assert np.array_equal(np.load(d), np.load(tiled.depth / d.name))


def test_region_mb_is_checked_and_sizes_regions_by_the_block_size():
    with pytest.raises(BlunfError, match="fusion.region_mb"):
        FusionConfig(region_mb=-1.0)
    assert FusionConfig().region_blocks == 2560  # 200 MB of 16^3 blocks
    assert FusionConfig(block_resolution=8).region_blocks == 20480  # configs/phone.yaml's
    assert FusionConfig(region_mb=0).region_blocks == 0

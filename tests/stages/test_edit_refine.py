"""The selections' outlines fused again (stages/edit/refine.py), on the exact room of the
fusion tests: 8 views at 64x48 with depth ray-cast from the true triangles."""

from __future__ import annotations

import numpy as np
import open3d.core as o3c
import trimesh

from stages.edit.refine import refine_mesh
from tests.stages.exact_room import VOXEL, fuse, make_scene, room_capture

BOX = (np.array([2.35, 0.75, -0.05]), np.array([3.05, 1.35, 0.75]))  # round the floor's box


def _inside(x: np.ndarray) -> np.ndarray:
    return np.all((x >= BOX[0]) & (x <= BOX[1]), axis=1)


def test_refined_surface_replaces_the_coarse_one_inside_the_box_only(tmp_path):
    frames = room_capture(tmp_path / "cap")
    mesh = trimesh.load(fuse(frames, tmp_path / "coarse").mesh, process=False)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    nv, nf, facts = refine_mesh(v, f, [BOX], frames, VOXEL / 2, 2.0)
    assert facts["fine_faces"] > 0 and facts["coarse_faces_dropped"] > 0, facts
    # the coarse mesh's vertices come first, unchanged; every coarse face with a corner
    # outside the box is kept as it was (the seam overlaps), none inside it
    np.testing.assert_array_equal(nv[: len(v)], v)
    coarse, fine = nf[nf.max(axis=1) < len(v)], nf[nf.min(axis=1) >= len(v)]
    assert len(coarse) + len(fine) == len(nf)
    outside = ~_inside(v)[f].all(axis=1)
    np.testing.assert_array_equal(coarse, f[outside])
    assert _inside(nv[fine].mean(axis=1)).all()
    # nearer the true surfaces than the coarse mesh was there. Measured, in coarse voxels
    # (4 cm): coarse 90th percentile 1.0, max 1.41; refined (2 cm, 2-voxel truncation) 0.11
    # and 0.30
    scene = make_scene()

    def dist(x: np.ndarray) -> np.ndarray:
        return scene.compute_distance(o3c.Tensor(x.astype(np.float32))).numpy() / VOXEL

    before, after = dist(v[_inside(v)]), dist(nv[np.unique(fine)])
    assert np.percentile(after, 90) < 0.3 < np.percentile(before, 90), (before, after)
    assert after.max() < 0.6 < before.max()


def test_a_box_without_depth_leaves_the_mesh(tmp_path):
    frames = room_capture(tmp_path / "cap")
    mesh = trimesh.load(fuse(frames, tmp_path / "coarse").mesh, process=False)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    above = (np.array([1.0, 1.0, 5.0]), np.array([1.5, 1.5, 6.0]))  # over the walls' top
    nv, nf, facts = refine_mesh(v, f, [above], frames, VOXEL / 2, 2.0)
    assert nv is v and nf is f and facts["skipped"] == "no depth reading in the boxes"
    assert refine_mesh(v, f, [], frames, VOXEL / 2, 2.0)[2]["skipped"] == "no box"

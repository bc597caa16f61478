"""The floor seen past a fattened rim (floorfill.floor_past): the fused surface of a stool is
5 cm wider each way than the stool; the views' own readings reach the floor past it."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.classes import FLOOR, OBJECT
from stages.common.io import read_label, write_image
from stages.semantics import IMPLS, SemanticsConfig, SemanticsInputs
from stages.semantics.config import FloorFillConfig
from tests.stages.test_semantics import EDGE, _look, exact_room

STOOL = ((1.8, 1.3, 0.0), (2.2, 1.7, 0.45))  # the stool's box; its fused surface: RIM wider
RIM = 0.05


def _with_box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    verts, tris, _, _ = exact_room()
    box = trimesh.creation.box(bounds=[lo, hi])
    box = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, EDGE))
    return (
        np.concatenate([verts, box.vertices]),
        np.concatenate([tris, np.asarray(box.faces) + len(verts)]),
    )


def _scene(verts: np.ndarray, tris: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(verts.astype(np.float32), tris.astype(np.uint32))
    return scene


def test_the_floor_past_a_fattened_rim_is_floor(tmp_path):
    lo, hi = np.asarray(STOOL[0]), np.asarray(STOOL[1])
    fat = _with_box(lo - [RIM, RIM, 0], hi + [RIM, RIM, RIM])  # what the fusion made
    true = _with_box(lo, hi)  # what the views read
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(fat[0]), o3d.utility.Vector3iVector(fat[1].astype(np.int32))
    )
    o3d.io.write_triangle_mesh(str(tmp_path / "mesh.ply"), mesh)
    intr = Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)
    poses = [_look((2.0, 0.3, 1.6), (2.0, 1.5, 0.2)), _look((0.8, 1.5, 1.5), (2.0, 1.5, 0.2))]
    (tmp_path / "images").mkdir()
    (tmp_path / "depth").mkdir()
    views, read = [], []
    for i, pose in enumerate(poses):
        img = tmp_path / "images" / f"v{i}.png"
        write_image(img, np.zeros((intr.height, intr.width, 3), np.uint8))
        ext = np.linalg.inv(pose)
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(intr.K), o3d.core.Tensor(ext), intr.width, intr.height
        )
        t = _scene(*true).cast_rays(rays)["t_hit"].numpy()  # the depth (camera z = 1)
        d = tmp_path / "depth" / f"v{i}.npy"
        np.save(d, np.where(np.isfinite(t), t, 0.0).astype(np.float32))
        views.append(Frame(f"v{i}", img, intr, None, None, pose))
        read.append(Frame(f"v{i}", img, intr, d, None, pose))
    Capture(tmp_path, tuple(views)).save(tmp_path / "frames.json")
    Capture(tmp_path, tuple(read)).save(tmp_path / "readings.json")
    inputs = SemanticsInputs(tmp_path / "frames.json", tmp_path / "mesh.ply", (), None)
    labels = {}
    for past, given in ((0.1, True), (0.1, False), (0.0, True)):
        cfg = SemanticsConfig(floor_fill=FloorFillConfig(past=past))
        ins = SemanticsInputs(
            inputs.frames, inputs.mesh, (), tmp_path / "readings.json" if given else None
        )
        out = tmp_path / f"out-{past}-{given}"
        outs = IMPLS["geometry"](cfg, ins, out)
        cap = Capture.load(outs.frames)
        labels[past, given] = [read_label(f.label) for f in cap.frames]
    rim = stool = 0
    for i, pose in enumerate(poses):
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(intr.K), o3d.core.Tensor(np.linalg.inv(pose)), intr.width, intr.height
        )
        hit_fat = _scene(*fat).cast_rays(rays)
        hit_true = _scene(*true).cast_rays(rays)
        on_fat = hit_fat["primitive_ids"].numpy() >= len(exact_room()[1])  # the fat box's
        on_true = hit_true["primitive_ids"].numpy() >= len(exact_room()[1])
        r = rays.numpy()
        z = r[..., 2] + hit_true["t_hit"].numpy() * r[..., 5]  # height the reading lies at
        z_fat = r[..., 2] + hit_fat["t_hit"].numpy() * r[..., 5]  # ... the fused surface's hit
        # the rim over the floor the view saw, hit 15 cm or more above it (more than `past`
        # before the floor along the ray)
        m_rim = on_fat & ~on_true & (np.abs(z) < 0.01) & (z_fat > 0.15)
        rim += int(m_rim.sum())
        stool += int(on_true.sum())
        # with the readings the rim is floor, without them (or with past 0) the stool's
        assert (labels[0.1, True][i][m_rim] == FLOOR).all()
        assert (labels[0.1, False][i][m_rim] == OBJECT).mean() > 0.8
        assert (labels[0.0, True][i][m_rim] == OBJECT).mean() > 0.8
        # the stool itself stays the stool (its top and sides)
        assert (labels[0.1, True][i][on_true & on_fat] == OBJECT).mean() > 0.95
    assert rim > 20 and stool > 100

"""Fusion stage: TSDF of a synthetic room rendered exactly, and of the 7-Scenes kitchen.

The room (tests/stages/exact_room.py, z up, floor at z = 0): floor 4 x 3 m, four walls 2.5 m
high, a counter against the north wall and a box on the floor, seen by 8 cameras at 64x48 whose
depth is ray-cast from the exact triangles. Every check compares with that exact geometry.
"""

from __future__ import annotations

import json
import resource
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
import pytest
from PIL import Image

from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import read_depth, write_depth_png
from stages.fusion import IMPLS, FusionConfig, FusionInputs
from stages.fusion.carve import view_votes
from stages.fusion.tsdf import canonical_cloud, canonical_mesh
from tests.conftest import shared_capture
from tests.stages.exact_room import (
    INTR,
    VOXEL,
    H,
    W,
    fuse,
    look_at,
    make_scene,
    render,
    room_capture,
    room_poses,
)


def test_mesh_and_raycast_depth_match_the_true_room(tmp_path):
    frames = room_capture(tmp_path / "cap")
    outs = fuse(frames, tmp_path / "out")
    mesh = o3d.io.read_triangle_mesh(str(outs.mesh))
    v = np.asarray(mesh.vertices, np.float32)  # [N, 3]
    assert len(mesh.triangles) > 1000
    # Distance of each fused vertex to the true surfaces: marching cubes puts vertices on the
    # zero crossing interpolated between voxel centres, so with exact depth they sit within a
    # voxel. The exception is a thin fringe along occluding edges (the box top seen at 4 cm
    # pixels): the projective SDF there is wrong by up to the truncation distance (4 voxels).
    dist = make_scene().compute_distance(o3c.Tensor(v)).numpy() / VOXEL  # [N] in voxels
    assert np.percentile(dist, 99) < 1.0, np.percentile(dist, [50, 99, 100])
    assert (dist < 1.5).mean() > 0.99
    assert dist.max() < 4.0

    cap = Capture.load(outs.frames)
    scene = make_scene()
    errs, hits, seen_px = [], 0, 0
    for f, pose in zip(cap.frames, room_poses(), strict=True):
        assert f.depth == outs.depth / f"{f.stem}.npy"
        truth, _ = render(scene, pose)
        got = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        both = (truth > 0) & (got > 0)
        errs.append(np.abs(got - truth)[both])
        hits += int(both.sum())
        seen_px += int((truth > 0).sum())
    err = np.concatenate(errs)
    # Exact depth, and pixel centres agreeing between our rays, Open3D's integration and its
    # ray casting: millimetres (half a pixel off would give ~1 cm here, at 4 cm pixels).
    assert np.median(err) < 0.005, np.median(err)
    assert (err < 0.03).mean() > 0.98
    # Misses: surfaces seen by one view only at its frustum edge, where marching cubes lacks
    # the neighbouring observed voxel (one or two border pixels of a 64x48 view: ~5 %).
    assert hits / seen_px > 0.9, hits / seen_px

    stats = json.loads(outs.stats.read_text())
    assert stats["frames"] == 8 and stats["triangles"] == len(mesh.triangles)
    # block_count is the exact number of blocks the depth touches: none missing, none spare
    assert stats["block_count"] == stats["blocks"]
    assert (tmp_path / "out" / "cloud.ply").is_file()
    assert len(o3d.io.read_point_cloud(str(outs.cloud)).points) > 1000


def test_fused_files_are_in_a_canonical_order(tmp_path):
    """The voxel block grid lists blocks in an order that changes between runs: the mesh and
    cloud are written sorted, so a shuffled copy of them orders to the very same arrays."""
    outs = fuse(room_capture(tmp_path / "cap"), tmp_path / "out")
    mesh = o3d.t.io.read_triangle_mesh(str(outs.mesh))
    pos, tri = mesh.vertex.positions.numpy(), mesh.triangle.indices.numpy()
    assert (np.diff(pos[:, 0]) >= 0).all()  # written sorted by x first
    assert (tri.argmin(axis=1) == 0).all() and (np.diff(tri[:, 0]) >= 0).all()
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(pos))  # new -> old
    back = np.argsort(perm)  # old -> new
    shuffled = o3d.t.geometry.TriangleMesh()
    for key, value in mesh.vertex.items():
        shuffled.vertex[key] = o3c.Tensor(value.numpy()[perm])
    rolled = np.roll(back[tri][rng.permutation(len(tri))], 1, axis=1)  # same winding
    shuffled.triangle.indices = o3c.Tensor(rolled)
    again = canonical_mesh(shuffled)
    for key in ("positions", "colors", "normals"):
        np.testing.assert_array_equal(again.vertex[key].numpy(), mesh.vertex[key].numpy())
    np.testing.assert_array_equal(again.triangle.indices.numpy(), tri)
    cloud = o3d.t.io.read_point_cloud(str(outs.cloud))
    shuffled_cloud = o3d.t.geometry.PointCloud(o3c.Tensor(np.zeros((1, 3), np.float32)))
    perm = rng.permutation(cloud.point.positions.shape[0])
    for key, value in cloud.point.items():
        shuffled_cloud.point[key] = o3c.Tensor(value.numpy()[perm])
    again = canonical_cloud(shuffled_cloud)
    for key, value in cloud.point.items():
        np.testing.assert_array_equal(again.point[key].numpy(), value.numpy())


def test_canonical_mesh_merges_twin_vertices_and_drops_what_collapses():
    """Two vertices at one position become one; a triangle left with a repeated vertex goes."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0]], np.float32)
    tri = np.array([[0, 1, 2], [1, 4, 2], [1, 3, 4]])  # the last: vertices 1 and 3 coincide
    mesh = o3d.t.geometry.TriangleMesh(o3c.Tensor(pos), o3c.Tensor(tri))
    out = canonical_mesh(mesh)
    got = out.vertex.positions.numpy()
    np.testing.assert_array_equal(got, [[0, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0]])
    # triangles (0, 1, 2) and (1, 4, 2) of the input, renumbered, lowest id first, same winding
    assert out.triangle.indices.numpy().tolist() == [[0, 2, 1], [1, 2, 3]]


def test_invalid_depth_is_never_fused(tmp_path):
    """Patches of invalid readings must give exactly the mesh and depth of the same patches
    left empty (0). The PNG frames use 1/5000 m units (as TUM RGB-D does), so the invalid
    code 65535 would read as 13.1 m, inside depth_max = 15 m, if it were not dropped; the
    float frames hold NaN, inf, 50 m (beyond any sensor) and 17 m (beyond depth_max)."""
    clean = Capture.load(room_capture(tmp_path / "cap"))
    bad_values = [np.nan, np.inf, 50.0, 17.0]
    patch = np.s_[10:30, 20:50]

    def variant(name: str, fill_bad: bool) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        frames = []
        for i, f in enumerate(clean.frames):
            d = read_depth(f.depth)  # [H, W] metres
            d[patch] = 0.0
            if i < 4:
                raw = np.round(d * 5000).astype(np.uint16)
                raw[patch] = 65535 if fill_bad else 0
                path = folder / f"{f.stem}.png"
                Image.fromarray(raw).save(path)
            else:
                d[patch] = bad_values[i - 4] if fill_bad else 0.0
                path = folder / f"{f.stem}.npy"
                np.save(path, d)
            frames.append(Frame(f.stem, f.image, f.intrinsics, depth=path, pose=f.pose))
        cap = replace(clean.with_frames(frames), depth_scale=5000.0, depth_invalid=(65535,))
        cap.save(folder / "frames.json")
        return folder / "frames.json"

    a = fuse(variant("bad", True), tmp_path / "out_bad", depth_max=15.0)
    b = fuse(variant("empty", False), tmp_path / "out_empty", depth_max=15.0)
    va = np.asarray(o3d.io.read_triangle_mesh(str(a.mesh)).vertices)
    vb = np.asarray(o3d.io.read_triangle_mesh(str(b.mesh)).vertices)
    assert va.shape == vb.shape
    # same vertices up to order (the hash map's block order may differ between runs)
    np.testing.assert_allclose(va[np.lexsort(va.T)], vb[np.lexsort(vb.T)], atol=1e-5)
    for f in clean.frames:
        da = np.load(a.depth / f"{f.stem}.npy")
        db = np.load(b.depth / f"{f.stem}.npy")
        assert np.array_equal(da, db)


def test_raycast_off_keeps_input_depth(tmp_path):
    frames = room_capture(tmp_path / "cap")
    outs = fuse(frames, tmp_path / "out", raycast=False)
    cap = Capture.load(outs.frames)
    assert [f.depth for f in cap.frames] == [f.depth for f in Capture.load(frames).frames]
    assert not any(outs.depth.iterdir())


def test_frame_without_depth_or_with_bad_pose_is_named(tmp_path):
    frames = room_capture(tmp_path / "cap")
    cap = Capture.load(frames)
    fs = list(cap.frames)
    fs[3] = Frame(fs[3].stem, fs[3].image, fs[3].intrinsics, depth=None, pose=fs[3].pose)
    cap.with_frames(fs).save(tmp_path / "nodepth.json")
    with pytest.raises(BlunfError, match="frame 'v03'.*no depth"):
        fuse(tmp_path / "nodepth.json", tmp_path / "o1")
    fs = list(cap.frames)
    bad = fs[5].pose.copy()
    bad[0, 3] = np.nan
    fs[5] = Frame(fs[5].stem, fs[5].image, fs[5].intrinsics, depth=fs[5].depth, pose=bad)
    cap.with_frames(fs).save(tmp_path / "nanpose.json")
    with pytest.raises(BlunfError, match="frame 'v05'.*finite"):
        fuse(tmp_path / "nanpose.json", tmp_path / "o2")


def test_a_frame_whose_few_readings_touch_no_block_is_skipped(tmp_path):
    """Open3D's block probe reads every 4th pixel and aborts the whole fusion when a frame
    touches no block: a rendered photos-only frame with a handful of readings off that grid
    (seen in a loaded run whose field trained 35 steps) is skipped and named, as a frame
    without depth is."""
    frames = room_capture(tmp_path / "cap")
    cap = Capture.load(frames)
    fs = list(cap.frames)
    d = read_depth(fs[2].depth, cap.depth_scale)
    few = np.zeros_like(d)
    few[13, 21], few[22, 17] = d[13, 21], d[22, 17]  # off the probe's 4-pixel grid
    assert (few > 0).sum() == 2
    write_depth_png(tmp_path / "few.png", few)  # millimetres, as the room's other frames
    fs[2] = replace(fs[2], depth=tmp_path / "few.png")
    cap.with_frames(fs).save(tmp_path / "few.json")
    outs = fuse(tmp_path / "few.json", tmp_path / "out")
    facts = json.loads(outs.stats.read_text())
    assert facts["frames_fused"] == len(fs) - 1 and "'v02'" in facts["notes"], facts


def test_all_depth_invalid_is_an_error(tmp_path):
    frames = room_capture(tmp_path / "cap")
    # every reading beyond depth_max: nothing to fuse
    with pytest.raises(BlunfError, match="no surface fused"):
        fuse(frames, tmp_path / "out", depth_max=0.5, far_share=0.0)


def test_view_votes_support_counts_readings_near_a_point():
    """A point 2 m in front of a camera: supported by a reading within dist of 2 m at its
    pixel, not by one farther, nor by a view it lies behind or outside of."""
    pose = look_at((0.0, 0.0, 1.0), (0.0, 5.0, 1.0))  # looks along +y
    p = np.array([[0.0, 2.0, 1.0]])  # on the optical axis, 2 m out
    K = INTR.K

    def views(*depths, c2w=pose):
        return [(np.full((H, W), d, np.float32), K, c2w) for d in depths]

    assert view_votes(p, views(2.03), 0.05)[0].tolist() == [1]
    assert view_votes(p, views(2.03, 1.97, 2.0), 0.05)[0].tolist() == [3]
    assert view_votes(p, views(2.03), 0.02)[0].tolist() == [0]
    assert view_votes(p, views(3.0, 0.0), 0.05)[0].tolist() == [0]  # far; no reading
    behind = look_at((0.0, 4.0, 1.0), (0.0, 9.0, 1.0))  # the point is 2 m behind it
    assert view_votes(p, views(2.0, c2w=behind), 0.05)[0].tolist() == [0]
    aside = look_at((0.0, 0.0, 1.0), (5.0, 0.0, 1.0))  # the point is 90 deg off its axis
    assert view_votes(p, views(2.0, c2w=aside), 0.05)[0].tolist() == [0]


def test_min_support_removes_the_surface_only_one_view_saw(tmp_path):
    """One view's depth holds a floater: a patch read at 1 m where the room is ~3 m away
    (a stereo mismatch). The TSDF keeps it (no other view's readings come near those
    voxels); with min_support = 2 it is gone and the room is left as it was. Each of the 8
    views has a twin 15 cm to its side, so that every surface is seen twice."""
    twins = [p.copy() for p in room_poses()]
    for p in twins:
        p[:3, 3] += 0.15 * p[:3, 0]
    clean = Capture.load(room_capture(tmp_path / "cap", poses=room_poses() + twins))
    frames = list(clean.frames)
    d = read_depth(frames[2].depth)
    d[15:30, 20:40] = 1.0
    path = tmp_path / "floater.png"
    write_depth_png(path, d)
    frames[2] = replace(frames[2], depth=path)
    clean.with_frames(frames).save(tmp_path / "floater.json")

    def far_and_near(outs) -> tuple[int, int]:
        v = np.asarray(o3d.io.read_triangle_mesh(str(outs.mesh)).vertices, np.float32)
        dist = make_scene().compute_distance(o3c.Tensor(v)).numpy()  # [N] metres
        return int((dist > 0.3).sum()), int((dist < 1.5 * VOXEL).sum())

    plain = fuse(tmp_path / "floater.json", tmp_path / "plain")
    carved = fuse(tmp_path / "floater.json", tmp_path / "carved", min_support=2)
    clean_run = fuse(tmp_path / "cap" / "frames.json", tmp_path / "clean", min_support=2)
    far_plain, near_plain = far_and_near(plain)
    far_carved, near_carved = far_and_near(carved)
    assert far_plain > 20, far_plain  # the floater is fused without the check
    assert far_carved == 0
    # the true room loses only the odd vertex at the frustum edges, seen by a single view
    assert near_carved > 0.95 * near_plain, (near_carved, near_plain)
    stats = json.loads(carved.stats.read_text())
    assert stats["carved_vertices"] >= far_plain and stats["carved_points"] > 0
    assert json.loads(plain.stats.read_text())["carved_vertices"] == 0
    # exact depth: every vertex lies on readings of two views but the frustum-edge few
    clean_stats = json.loads(clean_run.stats.read_text())
    assert clean_stats["carved_vertices"] < 0.05 * clean_stats["vertices"], clean_stats


def test_view_votes_count_readings_on_and_beyond_a_point():
    """A point 2 m out on a view's axis: a reading within dist of it supports it, one more
    than dist beyond it saw through it (free space there), one nearer hides it (neither)."""
    pose = look_at((0.0, 0.0, 1.0), (0.0, 5.0, 1.0))
    p = np.array([[0.0, 2.0, 1.0]])
    views = [(np.full((H, W), d, np.float32), INTR.K, pose) for d in (2.03, 3.0, 2.2, 1.0, 0.0)]
    support, through = view_votes(p, views, 0.05)
    assert support.tolist() == [1] and through.tolist() == [2]


def test_a_surface_more_views_see_through_than_lie_on_is_removed(tmp_path):
    """A box 20 cm across floating 1.3 m before view 2, in the depth of view 2 and its twin
    only (a surface two views' stereo agree on and nothing holds): min_support 2 keeps it;
    the views whose readings lie beyond it (three or four per vertex) outnumber the two it
    lies on, and fusion.max_through 1 removes it. The true room keeps its surface (the views'
    readings lie on it, none beyond)."""
    twins = [p.copy() for p in room_poses()]
    for p in twins:
        p[:3, 3] += 0.15 * p[:3, 0]
    poses = room_poses() + twins
    clean = Capture.load(room_capture(tmp_path / "cap", poses=poses))
    c = poses[2][:3, 3] + 1.3 * poses[2][:3, 2]
    box = o3d.t.geometry.TriangleMesh.from_legacy(
        o3d.geometry.TriangleMesh.create_box(0.2, 0.2, 0.2).translate(c - 0.1)
    )
    ghost = make_scene()
    ghost.add_triangles(box.vertex.positions.to(o3c.float32), box.triangle.indices.to(o3c.uint32))
    frames = list(clean.frames)
    for i in (2, 10):
        path = tmp_path / f"ghost{i}.png"
        write_depth_png(path, render(ghost, poses[i])[0])
        frames[i] = replace(frames[i], depth=path)
    clean.with_frames(frames).save(tmp_path / "ghost.json")

    def far_and_near(outs) -> tuple[int, int]:
        v = np.asarray(o3d.io.read_triangle_mesh(str(outs.mesh)).vertices, np.float32)
        dist = make_scene().compute_distance(o3c.Tensor(v)).numpy()  # [N] metres
        return int((dist > 0.3).sum()), int((dist < 1.5 * VOXEL).sum())

    outs = fuse(tmp_path / "ghost.json", tmp_path / "kept", min_support=2)
    kept = far_and_near(outs)
    assert json.loads(outs.stats.read_text())["seen_through_vertices"] == 0
    outs = fuse(tmp_path / "ghost.json", tmp_path / "gone", min_support=2, max_through=1)
    gone = far_and_near(outs)
    assert kept[0] > 20, kept  # the box is fused and two views' readings lie on it
    assert gone[0] == 0, gone
    assert gone[1] > 0.97 * kept[1], (gone, kept)
    assert json.loads(outs.stats.read_text())["seen_through_vertices"] >= kept[0]
    # the rule runs without the support check too
    outs = fuse(tmp_path / "ghost.json", tmp_path / "alone", max_through=1)
    assert far_and_near(outs)[0] == 0
    assert json.loads(outs.stats.read_text())["seen_through_vertices"] >= kept[0]


def test_min_support_that_removes_everything_says_so(tmp_path):
    frames = room_capture(tmp_path / "cap")  # each surface seen by one or two of 8 views
    with pytest.raises(BlunfError, match="min_support = 20 removes the whole surface"):
        fuse(frames, tmp_path / "out", min_support=20)
    assert not (tmp_path / "out" / "mesh.ply").exists()


def test_min_support_settings_are_checked():
    with pytest.raises(BlunfError, match="fusion.min_support"):
        FusionConfig(min_support=-1)
    with pytest.raises(BlunfError, match="fusion.support_voxels"):
        FusionConfig(support_voxels=0.0)
    with pytest.raises(BlunfError, match="fusion.max_through"):
        FusionConfig(max_through=-1.0)


@pytest.mark.slow
def test_kitchen_fusion(tmp_path):
    """7-Scenes redkitchen, 100 frames at 2 cm: a real mesh, and ray-cast depth that agrees
    with the sensor (Kinect v1 noise is ~1 cm at 2 m)."""
    src = shared_capture("7scenes-redkitchen")
    from stages.ingest import load

    cap = load(src, tmp_path / "work", "7scenes")
    cap.save(tmp_path / "frames.json")
    t0 = time.perf_counter()
    outs = IMPLS["tsdf"](FusionConfig(), FusionInputs(tmp_path / "frames.json"), tmp_path / "out")
    secs = time.perf_counter() - t0
    stats = json.loads(outs.stats.read_text())
    mesh = o3d.io.read_triangle_mesh(str(outs.mesh))
    v = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 50_000
    # every vertex lies within depth_max of some camera: the box around the cameras +- 5 m
    c = cap.poses()[:, :3, 3]
    assert (v.min(0) > c.min(0) - 5.0).all() and (v.max(0) < c.max(0) + 5.0).all()
    fused = Capture.load(outs.frames)
    errs = []
    for f0, f1 in list(zip(cap.frames, fused.frames, strict=True))[::10]:
        a = read_depth(f0.depth, cap.depth_scale, cap.depth_invalid)
        b = read_depth(f1.depth, fused.depth_scale, fused.depth_invalid)
        ok = (a > 0) & (b > 0)
        errs.append(np.median(np.abs(a - b)[ok]))
    assert np.median(errs) < 0.02, errs
    assert stats["depth_valid_out"] > stats["depth_valid_in"]  # holes filled
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"\nkitchen fusion: {stats['frames']} frames, {stats['integrate_fps']} frames/s "
        f"integration, block_count {stats['block_count']} ({stats['voxel_memory_mb']} MB), "
        f"raycast {stats['raycast_seconds']} s, total {secs:.1f} s, peak RSS {peak:.0f} MB, "
        f"median |raycast - sensor| {np.median(errs) * 100:.1f} cm"
    )


def test_far_share_fuses_a_far_wall_that_a_good_share_of_a_view_sees(tmp_path):
    """The 4 x 3 m room with depth_max 1.5 m stands for a room longer than the far limit: its
    walls beyond 1.5 m are not fused. With far_share the limit grows to the farthest view's
    (1 - far_share) quantile of its readings, and the far walls are fused; a stray far
    reading in every view (1 % of its pixels at 40 m) does not move it."""
    frames = room_capture(tmp_path / "cap")
    cap = Capture.load(frames)
    fs, want = [], 0.0
    for f in cap.frames:
        d = read_depth(f.depth, cap.depth_scale)
        want = max(want, float(np.quantile(d[d > 0], 0.75)))
        d.reshape(-1)[::100] = 40.0
        np.save(tmp_path / f"{f.stem}.npy", d.astype(np.float32))
        fs.append(replace(f, depth=tmp_path / f"{f.stem}.npy"))
    cap.with_frames(fs).save(tmp_path / "stray.json")
    near = fuse(tmp_path / "stray.json", tmp_path / "near", depth_max=1.5, far_share=0.0)
    far = fuse(tmp_path / "stray.json", tmp_path / "far", depth_max=1.5, far_share=0.25)
    limit = json.loads(far.stats.read_text())["depth_max_m"]
    assert json.loads(near.stats.read_text())["depth_max_m"] == 1.5
    assert limit == pytest.approx(want, abs=0.01) and limit > 1.8, limit  # not 40 m
    v_near = np.asarray(o3d.io.read_triangle_mesh(str(near.mesh)).vertices)
    v_far = np.asarray(o3d.io.read_triangle_mesh(str(far.mesh)).vertices)
    assert len(v_far) > 1.2 * len(v_near)
    # the walls' surface the 1.5 m limit left out: vertices up against the far walls
    dist = make_scene().compute_distance(o3c.Tensor(v_far.astype(np.float32))).numpy()
    assert np.percentile(dist, 99) < 2 * VOXEL
    # far_max bounds it
    capped = fuse(
        tmp_path / "stray.json", tmp_path / "cap", depth_max=1.5, far_share=0.25, far_max=1.7
    )
    assert json.loads(capped.stats.read_text())["depth_max_m"] == 1.7
    with pytest.raises(BlunfError, match="far_share"):
        FusionConfig(far_share=0.5)

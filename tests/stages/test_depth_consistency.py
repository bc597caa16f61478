"""Multi-view consistency check of rendered depth (stages/depth/consistency.py), on the exact
depth of the procedural room: true readings survive, floaters pasted into one view do not."""

from __future__ import annotations

import numpy as np
import pytest

from stages.common.camera import depth_at, depth_to_points
from stages.common.capture import read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth
from stages.depth import consistency
from stages.depth.consistency import HIDDEN, consistent_depth, overlap_order

ARGS = {"tol": 0.03, "min_agree": 1, "max_through": 0, "neighbours": 8}


@pytest.fixture(scope="module")
def views(tiny_room):
    cap = read_layout(tiny_room)
    depths = [read_depth(f.depth).astype(np.float32) for f in cap.frames]
    return depths, [f.intrinsics.K for f in cap.frames], [np.asarray(f.pose) for f in cap.frames]


def test_true_depth_is_kept_and_floaters_dropped(views):
    depths, ks, poses = views
    out, kept = consistent_depth(depths, ks, poses, **ARGS)
    # exact depth: a reading is dropped only where no other view sees its point, or where a
    # neighbour's nearest pixel reads across a depth edge
    assert kept > 0.85
    for d, o in zip(depths, out, strict=True):
        assert o.dtype == np.float32 and o.shape == d.shape
        assert np.all((o == 0) | (o == d))  # kept readings are unchanged
    # a floater: a patch of view 3 read at 60 % of its depth (density hanging in free space)
    bad = [d.copy() for d in depths]
    bad[3][20:40, 30:60] *= 0.6
    out_bad, _ = consistent_depth(bad, ks, poses, **ARGS)
    patch = out_bad[3][20:40, 30:60]
    assert np.count_nonzero(patch) <= 0.02 * patch.size
    # the rest of view 3 and the other views are judged as before, bar the readings that
    # leaned on the patch
    rest = np.ones(depths[3].shape, bool)
    rest[20:40, 30:60] = False
    assert np.mean(out_bad[3][rest] == out[3][rest]) > 0.97
    same = [np.mean(a == b) for i, (a, b) in enumerate(zip(out, out_bad, strict=True)) if i != 3]
    assert min(same) > 0.95


def test_readings_checked_against_reference_maps(views):
    # candidates (e.g. rendered depth) judged by other maps (e.g. stereo) alone: view 0's
    # exact depth against the other views' exact depth, with a floater pasted into view 0
    # and the references blanked over one half of the room
    depths, ks, poses = views
    cand = depths[0].copy()
    cand[20:40, 30:60] *= 0.6
    refs = (depths[1:], ks[1:], poses[1:])
    (out,), kept = consistent_depth([cand], ks[:1], poses[:1], **ARGS, refs=refs)
    alone, _ = consistent_depth(depths, ks, poses, **ARGS)
    assert 0 < kept < 1
    patch = out[20:40, 30:60]
    assert np.count_nonzero(patch) <= 0.02 * patch.size  # the references see through it
    rest = np.ones(cand.shape, bool)
    rest[20:40, 30:60] = False
    # elsewhere the same verdicts as checking all maps together, whose neighbours of view 0
    # are these same references
    assert np.mean(out[rest] == alone[0][rest]) > 0.97
    # a reading no reference sees is not confirmed (min_agree 1): nothing is kept when the
    # references hold no readings at all
    empty = ([np.zeros_like(d) for d in depths[1:]], ks[1:], poses[1:])
    (none,), kept0 = consistent_depth([cand], ks[:1], poses[:1], **ARGS, refs=empty)
    assert kept0 == 0 and not none.any()


@pytest.mark.parametrize(("scale", "offset"), [(1e-3, 0.0), (1e3, 0.0), (1.0, 1e5)])
def test_same_verdicts_at_any_scale_and_offset(views, scale, offset):
    # the tolerance is relative and points are float64: a scene in millimetres, kilometres
    # or far from the origin is judged alike
    depths, ks, poses = views
    ref, _ = consistent_depth(depths, ks, poses, **ARGS)
    moved = []
    for p in poses:
        q = p.copy()
        q[:3, 3] = q[:3, 3] * scale + offset
        moved.append(q)
    out, _ = consistent_depth([d * np.float32(scale) for d in depths], ks, moved, **ARGS)
    for a, b in zip(ref, out, strict=True):
        assert np.all(np.isfinite(b))
        assert np.mean((a > 0) == (b > 0)) > 0.995


def test_bad_settings_are_refused(views):
    depths, ks, poses = views
    with pytest.raises(BlunfError, match=r"depth\.check\.tol"):
        consistent_depth(depths, ks, poses, **{**ARGS, "tol": 0.0})
    with pytest.raises(BlunfError, match=r"depth\.check\.views"):
        consistent_depth(depths, ks, poses, **{**ARGS, "neighbours": 0})


def test_view_selection_by_angle_passes_over_a_near_duplicate_view(views):
    """overlap_order(angle=...): a copy of view 0 moved 1 cm sees every one of its points
    (the most overlap of all) but at a fraction of a degree; by overlap alone it ranks first
    among view 0's neighbours, by angle (5 degrees) below every neighbour that sees the same
    points from a few degrees away."""
    depths, ks, poses = views
    twin = poses[0].copy()
    twin[:3, 3] += twin[:3, 0] * 0.01  # 1 cm along the camera's x axis
    d, k, p = [*depths, depths[0]], [*ks, ks[0]], [*poses, twin]
    by_overlap = overlap_order(d, k, p, stride=4)
    by_angle = overlap_order(d, k, p, stride=4, angle=5.0)
    twin_at = len(d) - 1
    assert by_overlap[0][0] == twin_at
    assert twin_at in by_angle[0] and by_angle[0].index(twin_at) > 0
    assert set(by_angle[0]) == set(by_overlap[0])  # the same neighbours, in another order


def _overlap_by_pairs(depths, ks, poses, stride, refs=None, angle=0.0, hidden=HIDDEN):
    """overlap_order as its definition reads, one `depth_at` call per pair of views."""
    r_depths, r_ks, r_poses = refs if refs is not None else (depths, ks, poses)
    order = []
    for i, d in enumerate(depths):
        s = max(1, min(stride, min(d.shape) // 8))
        pts, _ = depth_to_points(d, ks[i], poses[i], s)
        counts = np.zeros(len(r_depths))
        for j in range(len(r_depths)):
            if refs is None and j == i:
                counts[j] = -1
                continue
            dj, z = depth_at(pts, r_depths[j], r_ks[j], r_poses[j])
            seen = (dj > 0) & ((hidden <= 0) | (dj >= z * (1 - hidden)))
            a, b = pts[seen] - poses[i][:3, 3], pts[seen] - r_poses[j][:3, 3]
            cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
            t = np.degrees(np.arccos(np.clip(cos, -1, 1)))
            w = np.exp(-((t - angle) ** 2) / (2 * np.where(t <= angle, 1.0, 10.0) ** 2))
            counts[j] = seen.sum() if angle <= 0 else w.sum()
        order.append([j for j in np.argsort(-counts, kind="stable") if counts[j] > 0])
    return order


def test_overlap_order_projects_into_all_views_at_once_as_pair_by_pair(views, monkeypatch):
    """The batched projection (all views at once, in blocks) ranks the neighbours as the
    pair-by-pair definition does: with and without the angle, against other maps (`refs`),
    with maps of other sizes among them, and with blocks of a few views."""
    depths, ks, poses = views
    small = [d[::2, ::2].copy() for d in depths]
    k2 = [np.diag([0.5, 0.5, 1.0]) @ k for k in ks]
    mixed = ([*depths[:4], *small[4:]], [*ks[:4], *k2[4:]], poses)
    for chunk in (1 << 20, 1000):
        monkeypatch.setattr(consistency._Maps, "CHUNK", chunk)
        for angle, hidden in ((0.0, HIDDEN), (5.0, 0.1), (0.0, 0.0)):
            got = overlap_order(*mixed, stride=4, angle=angle, hidden=hidden)
            want = _overlap_by_pairs(*mixed, stride=4, angle=angle, hidden=hidden)
            assert got == want, (chunk, angle, hidden)
        got = overlap_order(small, k2, poses, stride=2, refs=views)
        assert got == _overlap_by_pairs(small, k2, poses, stride=2, refs=views)
    assert all(len(o) >= 3 for o in got)  # the room's views do overlap


def test_a_view_behind_a_wall_does_not_count_as_overlap():
    """View 0 reads a wall 3 m ahead. View 1 stands 2 m behind it, looking the same way
    through a partition 1 m ahead of itself: every one of view 0's points projects inside
    view 1 onto a reading, but a nearer one (the partition hides them). View 2 stands 0.3 m
    beside view 0 and reads the same wall, losing some points past its image's edge. By
    readings alone view 1 ranks first; by what each view can see, view 2 does and view 1
    not at all."""
    k = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    poses = [np.eye(4) for _ in range(3)]
    poses[1][2, 3] = -2.0
    poses[2][0, 3] = 0.3
    depths = [np.full((48, 64), d, np.float32) for d in (3.0, 1.0, 3.0)]
    assert overlap_order(depths, [k] * 3, poses, hidden=0.0)[0] == [1, 2]
    assert overlap_order(depths, [k] * 3, poses)[0] == [2]
    # the partition view 1 reads lies behind views 0 and 2: nobody overlaps it
    assert overlap_order(depths, [k] * 3, poses)[1] == []

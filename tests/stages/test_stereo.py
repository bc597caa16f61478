"""Plane-sweep stereo (stages/depth/sweep.py) against the procedural room's exact depth: the
photos-only path's dense depth. Sparse 'tracks' are 2 % of the true readings, as SfM gives."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from stages.common.capture import read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label
from stages.depth.config import StereoConfig
from stages.depth.sweep import (
    _box,
    _window_inside,
    _window_stats,
    costs_for,
    near_edge,
    plane_count,
    smallest_mean,
    sweep_depths,
)


@pytest.fixture(scope="module")
def room(tiny_room):
    cap = read_layout(tiny_room)
    gt = [read_depth(f.depth).astype(np.float32) for f in cap.frames]
    rng = np.random.default_rng(0)
    tracks = [np.where(rng.random(g.shape) < 0.02, g, 0).astype(np.float32) for g in gt]
    images = [read_image(f.image).astype(np.float32) / 255 for f in cap.frames]
    ks = [f.intrinsics.K for f in cap.frames]
    poses = [np.asarray(f.pose, np.float64) for f in cap.frames]
    return images, ks, poses, tracks, gt


@pytest.fixture(scope="module")
def swept(room):
    images, ks, poses, tracks, _ = room
    return sweep_depths(images, ks, poses, tracks, StereoConfig())


def _errors(depths: list[np.ndarray], gt: list[np.ndarray]) -> np.ndarray:
    pairs = zip(depths, gt, strict=True)
    return np.concatenate([np.abs(d[d > 0] - g[d > 0]) / g[d > 0] for d, g in pairs])


def test_depth_matches_the_exact_depth(room, swept):
    images, _, _, _, gt = room
    depths, facts = swept
    assert len(depths) == len(images)
    for d, g in zip(depths, gt, strict=True):
        assert d.dtype == np.float32 and d.shape == g.shape
        assert np.isfinite(d).all() and (d >= 0).all()
    # Measured on this 16-view 96x72 room: a fifth of the pixels kept (the low resolution
    # leaves few windows with texture and overlap), median error 0.75 % (0.83 % without the
    # per-pixel refinement), 2 % of the readings off by more than 5 %. Readings the sweep
    # made up would be off by tens of %.
    cover = np.mean([(d > 0).mean() for d in depths])
    e = _errors(depths, gt)
    assert cover > 0.15, cover
    assert np.median(e) < 0.015 and (e > 0.05).mean() < 0.06, (np.median(e), (e > 0.05).mean())
    assert facts["kept"] == pytest.approx(cover, abs=1e-3) and facts["matched"] >= facts["kept"]


def test_wrong_poses_give_no_depth(room, swept):
    # every camera moved 0.3 m: windows no longer match along the true epipolar lines, so
    # few readings pass the cost and cross-view checks
    images, ks, poses, tracks, _ = room
    moved = [p.copy() for p in poses]
    for i, p in enumerate(moved):
        p[:3, 3] += 0.3 * np.array([np.cos(i), np.sin(i), 0.0])
    _, facts = sweep_depths(images, ks, moved, tracks, StereoConfig())
    assert facts["kept"] < 0.25 * swept[1]["kept"], (facts, swept[1])


def test_flat_images_give_no_depth(room):
    # no texture, nothing to match: every reading is refused rather than guessed
    images, ks, poses, tracks, _ = room
    flat = [np.full_like(im, 0.5) for im in images]
    depths, facts = sweep_depths(flat, ks, poses, tracks, StereoConfig())
    assert facts["matched"] == 0 and all(not d.any() for d in depths)


@pytest.mark.parametrize(("scale", "offset"), [(1e-3, 0.0), (1e3, 0.0), (1.0, 1e5)])
def test_same_depth_at_any_scale_and_offset(room, swept, scale, offset):
    # a scene in millimetres, in kilometres or far from the origin: the same readings, scaled
    images, ks, poses, tracks, _ = room
    ref, _ = swept
    moved = []
    for p in poses:
        q = p.copy()
        q[:3, 3] = q[:3, 3] * scale + offset
        moved.append(q)
    scaled = [t * np.float32(scale) for t in tracks]
    out, _ = sweep_depths(images, ks, moved, scaled, StereoConfig())
    for a, b in zip(ref, out, strict=True):
        assert np.isfinite(b).all()
        both = (a > 0) & (b > 0)
        assert both.sum() >= 0.97 * max((a > 0).sum(), (b > 0).sum())
        np.testing.assert_allclose(b[both], a[both] * scale, rtol=2e-3)


def test_box_mean_matches_a_direct_sum():
    # the windowed mean at a corner, an edge and inside, by hand
    x = torch.arange(30, dtype=torch.float32).view(1, 1, 5, 6)
    m = _box(x, 3)[0, 0]
    v = x[0, 0]
    assert float(m[0, 0]) == pytest.approx(float(v[:2, :2].mean()))
    assert float(m[0, 3]) == pytest.approx(float(v[:2, 2:5].mean()))
    assert float(m[2, 2]) == pytest.approx(float(v[1:4, 1:4].mean()))


def test_matching_cost_is_one_minus_the_windows_zncc():
    # the neighbour is the reference shifted 2 px right: depth d lands ref pixel (u, v) at
    # ((d u + 2 d) / d, v) in it, so every depth is the true one; a direct ZNCC of the two
    # 5x5 windows, the cost of a window leaving the neighbour, and a negated image
    rng = np.random.default_rng(0)
    h, w, win = 12, 16, 5
    ref = torch.from_numpy(rng.random((h, w), dtype=np.float32))
    nbr = torch.roll(ref, 2, dims=1)  # nbr[v, u + 2] = ref[v, u]
    v, u = np.mgrid[0:h, 0:w]
    ka = torch.from_numpy(np.stack([u + 2.0, v, np.ones_like(u)], -1).reshape(-1, 3)).float()
    kb = torch.zeros(3)
    r_mean, r_std = _window_stats(ref[None, None], win)
    cost = costs_for(nbr, ka, kb, torch.tensor([1.0, 3.0]), ref, r_mean, r_std, win)
    assert cost.shape == (2, h, w)
    np.testing.assert_allclose(cost[:, 2:-2, 2:-4].numpy(), 0.0, atol=1e-4)  # same windows
    assert (cost[:, :, -4:] == 2.0).all()  # windows reaching past the neighbour's edge
    # another neighbour: not the same texture; the cost against a direct ZNCC at a pixel
    other = torch.from_numpy(rng.random((h, w), dtype=np.float32))
    c = costs_for(other, ka, kb, torch.tensor([1.0]), ref, r_mean, r_std, win)[0]
    a = ref[3:8, 4:9].numpy().ravel()
    b = other[3:8, 6:11].numpy().ravel()
    zncc = ((a - a.mean()) * (b - b.mean())).mean() / (a.std() * b.std())
    assert float(c[5, 6]) == pytest.approx(1.0 - zncc, abs=1e-4)
    flipped = costs_for(1.0 - nbr, ka, kb, torch.tensor([1.0]), ref, r_mean, r_std, win)
    np.testing.assert_allclose(flipped[0, 2:-2, 2:-4].numpy(), 2.0, atol=1e-4)  # ZNCC -1


@pytest.mark.parametrize(
    "kw",
    [
        {"planes": 2},
        {"views": 0},
        {"refine": 2},
        {"refine": -1},
        {"window": 4},
        {"window": 1},
        {"max_cost": 0.0},
        {"plane_px": -1.0},
        {"edge_px": -1},
    ],
)
def test_bad_settings_are_refused(kw):
    with pytest.raises(BlunfError, match=r"depth\.stereo\."):
        StereoConfig(**kw)


def test_refinement_sharpens_the_coarse_planes(room):
    # 16 coarse planes alone leave the depth between planes to the parabola; the per-pixel
    # refinement across a plane step either side lowers the error and confirms more readings
    # (measured: median 1.43 % -> 1.09 %, 6.1 % -> 9.0 % of the pixels kept)
    images, ks, poses, tracks, gt = room
    coarse, fc = sweep_depths(images, ks, poses, tracks, StereoConfig(planes=16, refine=0))
    fine, ff = sweep_depths(images, ks, poses, tracks, StereoConfig(planes=16, refine=16))
    e_coarse, e_fine = np.median(_errors(coarse, gt)), np.median(_errors(fine, gt))
    assert e_fine < 0.85 * e_coarse and ff["kept"] > fc["kept"], (e_fine, e_coarse, ff, fc)


def test_auto_scale_follows_the_plan_cell():
    # one pixel at the median track depth spans at most `cell` metres at the chosen scale
    from stages.depth.sweep import stereo_scale

    ks = [np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])]
    z = np.full(10, 2.0)  # a pixel spans 4 mm at 2 m
    assert stereo_scale(StereoConfig(scale=0, cell=0.02), ks, z) == 5
    assert stereo_scale(StereoConfig(scale=0, cell=0.001), ks, z) == 1
    assert stereo_scale(StereoConfig(scale=3), ks, z) == 3


def test_coarse_to_fine_at_half_resolution(room, swept):
    # planes at 1/4, the refinement at 1/2: half-resolution maps (each pixel a 2 x 2 block)
    images, ks, poses, tracks, gt = room
    cfg = StereoConfig(scale=2, coarse=2)
    depths, facts = sweep_depths(images, ks, poses, tracks, cfg)
    assert facts["scale"] == 2 and facts["coarse"] == 2
    for d, g in zip(depths, gt, strict=True):
        h, w = g.shape[0] // 2, g.shape[1] // 2
        assert d.shape == (h, w) and d.dtype == np.float32 and np.isfinite(d).all()
    # Measured on this 16-view 96x72 room: 2.6 % of the (48x36) pixels kept against 22 % at
    # full resolution: a 7-pixel window at half resolution finds little texture here
    assert 0 < facts["kept"] < swept[1]["kept"], (facts, swept[1])


def test_coarse_needs_the_refinement():
    with pytest.raises(BlunfError, match=r"depth\.stereo\.coarse"):
        StereoConfig(coarse=2, refine=0)


def _tracks_frames(capture, tracks, tmp_path) -> None:
    """tmp_path/frames.json: the capture with the SfM-like track depths as its depth."""
    from dataclasses import replace

    from stages.common.io import write_depth_npy

    cap = read_layout(capture)
    (tmp_path / "tracks").mkdir()
    frames = []
    for f, t in zip(cap.frames, tracks, strict=True):
        write_depth_npy(tmp_path / "tracks" / f"{f.stem}.npy", t)
        frames.append(replace(f, depth=tmp_path / "tracks" / f"{f.stem}.npy"))
    replace(cap.with_frames(frames), depth_scale=1.0, depth_invalid=()).save(
        tmp_path / "frames.json"
    )


def test_stereo_stage_writes_depth_for_fusion_without_a_field(tiny_room, tmp_path, room):
    # the depth stage's `stereo` implementation: every view swept, frames.json pointing at the
    # checked maps (metres), sources/ saying stereo where there is depth, no field trained

    from stages.common.capture import Capture
    from stages.common.io import read_json
    from stages.depth import DepthConfig, DepthInputs
    from stages.depth.config import FieldFillConfig
    from stages.depth.planes import PlanesConfig
    from stages.depth.stage import run_stereo

    _, _, _, tracks, gt = room
    _tracks_frames(tiny_room, tracks, tmp_path)
    (tmp_path / "out").mkdir()
    # fill off: at 96x72 stereo covers ~15-20 %, and the default (auto) would train a field;
    # the plane fill off too (it is tested below)
    cfg = DepthConfig(field=FieldFillConfig(fill=False), planes=PlanesConfig(enabled=False))
    outs = run_stereo(cfg, DepthInputs(tmp_path / "frames.json"), tmp_path / "out")
    assert not outs.field.exists()
    got = Capture.load(outs.frames)
    depths = [read_depth(f.depth) for f in got.frames]
    assert all(f.depth.parent == outs.depth for f in got.frames)
    facts = read_json(outs.stats)
    assert facts["kept"] > 0.15
    assert np.median(_errors(depths, gt)) < 0.015
    # sources: stereo exactly where there is depth, the same size as the depth maps
    for f, d in zip(got.frames, depths, strict=True):
        src = read_label(outs.sources / f"{f.stem}.png")
        assert src.shape == d.shape and set(np.unique(src)) <= {0, 1}
        assert np.array_equal(src == 1, d > 0)
    # the report's facts: coverage after each part (the plane fill off leaves it as it is)
    cov = facts["coverage"]
    assert cov["sweep"] == cov["planes"] == facts["by_source"]["stereo"]
    assert abs(cov["sweep"] - facts["kept"]) < 0.02 and "field" not in cov
    assert facts["parts"]["sweep"]["cpu_seconds"] > 0 and facts["cpu_seconds"] > 0


def test_stereo_stage_runs_the_plane_fill_where_stereo_covers_too_little(tiny_room, tmp_path, room):
    # depth.planes on: under `below` the room's planes fill stereo's holes (sources 2, more
    # coverage than the sweep, every stereo reading kept where no plane overrode it); at or
    # over it the fill is skipped and says why

    from stages.common.capture import Capture
    from stages.common.io import read_json
    from stages.depth import DepthConfig, DepthInputs
    from stages.depth.config import FieldFillConfig
    from stages.depth.planes import PlanesConfig
    from stages.depth.stage import run_stereo

    _, _, _, tracks, gt = room
    _tracks_frames(tiny_room, tracks, tmp_path)
    facts = {}
    for below, most in ((1.0, 1.0), (0.0, 1.0), (1.0, 0.0)):
        out = tmp_path / f"out{below}-{most}"
        out.mkdir()
        pc = PlanesConfig(below=below, max_dropped=most, width=96, superpixels=150)
        cfg = DepthConfig(field=FieldFillConfig(fill=False), planes=pc)
        outs = run_stereo(cfg, DepthInputs(tmp_path / "frames.json"), out)
        facts[below, most] = read_json(outs.stats)
        srcs = [
            read_label(outs.sources / f"{f.stem}.png") for f in Capture.load(outs.frames).frames
        ]
        if (below, most) == (1.0, 1.0):
            assert any((s == 2).any() for s in srcs)
        else:
            assert all(set(np.unique(s)) <= {0, 1} for s in srcs)
    ran, skipped, undone = facts[1.0, 1.0], facts[0.0, 1.0], facts[1.0, 0.0]
    # some fills fail the check, so with max_dropped 0 the fill is undone, and says why
    assert ran["plane_fill"]["fills_dropped_by_check"] > 0
    assert not undone["parts"]["planes"]["ran"] and not undone["plane_fill"]["ran"]
    assert undone["coverage"]["planes"] == undone["coverage"]["sweep"]
    assert undone["plane_fill_reason"].startswith("no plane fill: the multi-view check dropped")
    assert ran["parts"]["planes"]["ran"] and not skipped["parts"]["planes"]["ran"]
    assert ran["coverage"]["planes"] > ran["coverage"]["sweep"]
    assert skipped["coverage"]["planes"] == skipped["coverage"]["sweep"]
    assert ran["plane_fill_reason"].startswith("plane fill: stereo covers")
    assert skipped["plane_fill_reason"].startswith("no plane fill")
    assert "plane_fill" in ran and "plane_fill" not in skipped


def test_smallest_mean_is_the_mean_of_the_k_lowest():
    # the neighbours' costs are merged as they come; the result is topk's, ties included
    g = torch.Generator().manual_seed(0)
    costs = [torch.randint(0, 4, (3, 5, 6), generator=g).float() for _ in range(5)]
    for k in (1, 2, 3, 5):
        want = torch.topk(torch.stack(costs), k, dim=0, largest=False).values.mean(0)
        torch.testing.assert_close(smallest_mean(iter(costs), k), want)


def test_window_inside_matches_the_windowed_sum():
    # pixels warped inside a neighbour form a convex region: its corners decide the window,
    # as the windowed sum of the inside mask did (edges clip the window)
    h, w = 20, 24
    v, u = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    masks = [
        (u - 3 * v / 4 > 2) & (u + v < 30),  # a wedge
        (u > 5) & (v < 11) & (u - v < 15),  # clipped by the image's edges
        torch.ones(h, w, dtype=torch.bool),
        torch.zeros(h, w, dtype=torch.bool),
    ]
    inside = torch.stack(masks)  # [4, H, W]
    for window in (3, 7):
        want = _box(inside[:, None].float(), window)[:, 0] > 0.999
        assert torch.equal(_window_inside(inside, window), want)


def test_plane_count_follows_the_widest_neighbours_disparity():
    from dataclasses import replace

    # focal 200 px, neighbours 0.1 m and 0.2 m away, depths 1 .. 4 m: the far neighbour sees
    # a point move 200 x 0.2 x (1 - 1/4) = 30 px over the range
    K = np.array([[200.0, 0, 100], [0, 200.0, 80], [0, 0, 1]])
    poses = [np.eye(4) for _ in range(3)]
    poses[1][0, 3], poses[2][0, 3] = 0.1, 0.2
    cfg = StereoConfig(planes=64)
    assert plane_count(cfg, K, poses, 0, [1, 2], 1.0, 4.0) == 64  # off: `planes`
    assert plane_count(replace(cfg, plane_px=2.0), K, poses, 0, [1, 2], 1.0, 4.0) == 16
    assert plane_count(replace(cfg, plane_px=2.0), K, poses, 0, [1], 1.0, 4.0) == 9
    assert plane_count(replace(cfg, plane_px=0.1), K, poses, 0, [1, 2], 1.0, 4.0) == 64
    assert plane_count(replace(cfg, plane_px=20.0), K, poses, 0, [1, 2], 1.0, 4.0) == 8


def test_fewer_planes_from_the_disparity_still_match_the_exact_depth(room, swept):
    images, ks, poses, tracks, gt = room
    depths, facts = sweep_depths(images, ks, poses, tracks, StereoConfig(plane_px=6.0))
    assert 8 <= facts["planes_mean"] < 48, facts
    assert swept[1]["planes_mean"] == StereoConfig().planes
    # measured on this 96x72 room: 32.7 planes on average, 19.2 % of the pixels kept against
    # 24.2 % with 64, median error 0.89 %
    e = _errors(depths, gt)
    assert np.median(e) < 0.015 and facts["kept"] > 0.7 * swept[1]["kept"], (facts, swept[1])


def _dropped(d: np.ndarray, px: int) -> np.ndarray:
    """d without its near_edge readings (0 there), in d's dtype."""
    return np.where(near_edge(d, px), 0.0, d)


def test_near_edge_takes_the_fattened_rim_and_keeps_a_gentle_slope():
    # A box 1 m away before a wall 2 m away, read 2 px too wide all round (a correlation
    # window over the box's edge matched the box); below it a floor whose depth grows 2 % a
    # pixel, and below that one seen at a grazing angle, 8 % a pixel. The near side of the
    # edge goes, 2 px of it, and the grazing floor; the box's inside, the wall round it and
    # the gentle floor stay.
    d = np.full((50, 60), 2.0, np.float32)
    d[30:40] = 2.0 * 1.02 ** np.arange(10)[:, None]  # the gentle floor
    d[40:] = 3.0 * 1.08 ** np.arange(10)[:, None]  # the grazing floor
    d[10:20, 20:40] = 1.0  # the box as stereo read it, true extent [12:18, 22:38]
    out = _dropped(d, 2)
    assert out.dtype == d.dtype
    assert (out[10:20, 20:40][[0, 1, -2, -1]] == 0).all()  # its rim rows
    assert (out[10:20, 20:40][:, [0, 1, -2, -1]] == 0).all()  # its rim columns
    assert (out[12:18, 22:38] == 1.0).all()  # the box's inside
    box = np.zeros(d.shape, bool)
    box[10:20, 20:40] = True
    box[28:] = True  # the floors: the gentle one's last rows see the grazing one behind
    assert (out[~box] == d[~box]).all()  # the wall round the box
    assert (out[30:36] == d[30:36]).all()  # the gentle floor
    assert (out[40:48] == 0).all()  # the grazing floor (its last 2 rows: no pixel beyond)
    assert (_dropped(np.where(box, 0, d), 2) == np.where(box, 0, d)).all()  # a hole


def test_dropping_the_near_side_of_edges_leaves_fewer_fattened_readings(room, swept):
    # The tiny room's chairs and table before its walls: readings within 3 px of an edge of
    # the exact depth that read the nearer side's depth on the farther side (off by > 10 %)
    # are stereo's fattening. edge_px = 2 drops a share of them (those with a reading of the
    # farther surface beside them), and away from the edges leaves nearly every reading.
    *_, gt = room
    plain, _ = swept
    cut = [_dropped(d, 2) for d in plain]
    fat_plain = fat_cut = kept_calm = calm_n = 0
    for a, b, g in zip(plain, cut, gt, strict=True):
        far = ndimage.maximum_filter(g, size=7)
        near = ndimage.minimum_filter(g, size=7)
        edge = far > 1.1 * near  # within 3 px of a depth edge
        fat_plain += int(((a > 0) & edge & (a < g / 1.1)).sum())  # nearer than the truth
        fat_cut += int(((b > 0) & edge & (b < g / 1.1)).sum())
        calm = ~ndimage.binary_dilation(edge, iterations=4) & (a > 0)
        kept_calm += int((b[calm] == a[calm]).sum())
        calm_n += int(calm.sum())
    # measured: 120 fattened readings, 80 after (105 with edge_px 1, 68 with 3); 6383 of the
    # 6401 readings away from the edges kept (the rest beside a reading stereo put too far)
    assert fat_plain > 0 and fat_cut < 0.75 * fat_plain, (fat_plain, fat_cut)
    assert kept_calm >= 0.99 * calm_n, (kept_calm, calm_n)


def test_the_stage_drops_stereo_beside_edges_after_the_plane_fill(tiny_room, tmp_path, room):
    # depth.stereo.edge_px with the plane fill on: the fill reads every checked reading, so
    # its fills are those of the run without edge_px; then stereo's readings beside an edge
    # go (a subset of the run's readings, the share reported), the plane fills all stay
    from stages.common.capture import Capture
    from stages.common.io import read_json
    from stages.depth import DepthConfig, DepthInputs
    from stages.depth.config import FieldFillConfig
    from stages.depth.planes import PlanesConfig
    from stages.depth.stage import run_stereo

    _tracks_frames(tiny_room, room[3], tmp_path)
    got = {}
    for px in (0, 2):
        out = tmp_path / f"out{px}"
        out.mkdir()
        cfg = DepthConfig(
            stereo=StereoConfig(edge_px=px),
            field=FieldFillConfig(fill=False),
            planes=PlanesConfig(below=1.0, max_dropped=1.0, width=96, superpixels=150),
        )
        outs = run_stereo(cfg, DepthInputs(tmp_path / "frames.json"), out)
        frames = Capture.load(outs.frames).frames
        got[px] = (
            read_json(outs.stats),
            [read_label(outs.sources / f"{f.stem}.png") for f in frames],
            [np.load(f.depth) for f in frames],
        )
    (plain, s0, d0), (cut, s2, d2) = got[0], got[2]
    assert "edge_dropped" not in plain and cut["edge_dropped"] > 0
    assert cut["plane_fill"]["planes"] == plain["plane_fill"]["planes"]
    stereo0 = sum(int((s == 1).sum()) for s in s0)
    stereo2 = sum(int((s == 1).sum()) for s in s2)
    assert 0 < stereo2 < stereo0
    for a, b, da, db in zip(s0, s2, d0, d2, strict=True):
        assert ((b == 1) <= (a == 1)).all()  # stereo only ever removed
        assert ((a == 2) == (b == 2)).all() and (da[a == 2] == db[b == 2]).all()  # fills kept
    n = sum(s.size for s in s0)
    assert cut["edge_dropped"] == pytest.approx((stereo0 - stereo2) / n, abs=1e-4)
    assert cut["parts"]["edges"]["coverage"] == cut["coverage"]["edges"]

"""The depth stage's field fill (stages/depth/field.py) on small procedural rooms: what it
writes for fusion, at what resolution, and how far stereo helps it. The fields are small and
trained for a fixed number of steps (reproducible)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stages.common.capture import Capture, heldout_views, read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_json, read_label
from stages.common.radiance.evaluate import depth_absrel
from stages.common.radiance.field import load_field
from stages.depth import DepthConfig, DepthInputs
from stages.depth.config import FIELD, STEREO, FieldFillConfig
from stages.depth.render import ray_spread, render_depth, upsample_depth
from stages.depth.stage import run_field, run_stereo
from stages.synth import make_room
from tests.conftest import SMALL_FIELD, tune

# the small field of tests/stages/test_nerf.py: ~0.05 CPU-s a step on one thread
FAST = DepthConfig(
    threads=1,
    field=tune(FieldFillConfig(), **SMALL_FIELD),
)
DENSE_STEPS = 80


def _sparse(room: Path, folder: Path, keep: float, seed: int = 0) -> Path:
    """The room's capture with each depth map thinned to a random `keep` fraction of its
    pixels (what the poses stage writes from SfM tracks); returns its frames.json."""
    cap = read_layout(room)
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    frames = []
    for f in cap.frames:
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        d = np.where(rng.random(d.shape) < keep, d, 0.0).astype(np.float32)
        np.save(folder / f"{f.stem}.npy", d)
        frames.append(replace(f, depth=folder / f"{f.stem}.npy"))
    replace(cap.with_frames(frames), depth_scale=1.0).save(folder / "frames.json")
    return folder / "frames.json"


def _run(fn, cfg: DepthConfig, frames: Path, out: Path):
    out.mkdir(parents=True)
    return fn(cfg, DepthInputs(frames), out)


def test_field_alone_renders_every_view(tmp_path):
    # no sweep (the `field` implementation): 5 views at 48 x 36 (view 4 held out), 1 % of
    # the depth pixels kept. Ten steps do not fit the room: this checks what is written.
    room = make_room(tmp_path / "room", views=5, seed=3, size=(48, 36))
    frames = _sparse(room, tmp_path / "sparse", keep=0.01)
    cfg = tune(FAST, field__train__max_steps=10)
    outs = _run(run_field, cfg, frames, tmp_path / "out")
    facts = read_json(outs.stats)
    stats = facts["field"]
    assert not stats["depth_dense"] and stats["depth_supervised"]
    assert 0.005 < stats["depth_coverage"] < 0.02
    assert stats["depth_absrel"] is None  # sparse input depth is no reference
    assert list(facts["coverage"]) == ["field"]  # no sweep, no plane fill
    got = Capture.load(outs.frames)
    assert got.depth_scale == 1.0
    k = cfg.field.render_scale
    for f in got.frames:
        assert f.depth == outs.depth / f"{f.stem}.npy" and f.depth.is_file()
        raw = np.load(f.depth)
        assert raw.dtype == np.float32 and raw.shape == (36 // k, 48 // k)
        assert np.isfinite(raw).all() and (raw >= 0).all() and raw.max() < 8.0
        src = read_label(outs.sources / f"{f.stem}.png")
        assert np.array_equal(src == FIELD, raw > 0) and set(np.unique(src)) <= {0, FIELD}
    assert not load_field(outs.field / "model.pt").surface_color
    # with the multi-view check: the same (seeded) renders, minus the unconfirmed readings
    runs = {}
    for check in (False, True):
        c = tune(cfg, check__enabled=check, field__sampling__acc_threshold=0.0)
        runs[check] = _run(run_field, c, frames, tmp_path / f"check_{check}")
    kept = read_json(runs[True].stats)["field"]["depth_check_kept"]
    assert read_json(runs[False].stats)["field"]["depth_check_kept"] is None and 0 <= kept < 1
    n_raw = n_chk = 0
    plain, checked = (Capture.load(runs[c].frames).frames for c in (False, True))
    for f, g in zip(plain, checked, strict=True):
        raw, chk = np.load(f.depth), np.load(g.depth)
        assert np.all((chk == 0) | (chk == raw))
        n_raw, n_chk = n_raw + np.count_nonzero(raw), n_chk + np.count_nonzero(chk)
    assert n_raw > 0 and n_chk == pytest.approx(kept * n_raw, abs=1)


def test_the_fill_is_no_finer_than_the_sweep(tmp_path):
    # stereo swept at half resolution (depth.stereo.scale 2): the field's fill is rendered
    # at 1/2 too although render_scale asks for full resolution, every view's depth (its
    # readings and the fill) at the sweep's resolution
    room = make_room(tmp_path / "room", views=5, seed=3, size=(48, 36))
    frames = _sparse(room, tmp_path / "sparse", keep=0.01)
    shapes, scales = {}, {}
    for scale in (1, 2):
        cfg = tune(
            FAST,
            field__train__max_steps=10,
            field__render_scale=1,
            field__fill=True,
            stereo__scale=scale,
        )
        outs = _run(run_stereo, cfg, frames, tmp_path / f"out{scale}")
        scales[scale] = read_json(outs.stats)["field"]["depth_render_scale"]
        shapes[scale] = {np.load(f.depth).shape for f in Capture.load(outs.frames).frames}
    assert scales == {1: 1, 2: 2}
    assert shapes == {1: {(36, 48)}, 2: {(18, 24)}}


@pytest.mark.slow
def test_field_alone_accuracy(tmp_path):
    # 1 % of the depth pixels (uniformly at random): the field fills in the rest. Measured
    # after 300 steps: AbsRel 0.04-0.08 on the training views, 0.11-0.12 on the held-out
    # view 4, mean 0.06-0.065.
    room = make_room(tmp_path / "room", views=8, seed=3, size=(96, 72))
    frames = _sparse(room, tmp_path / "sparse", keep=0.01)
    cfg = tune(
        FAST,
        field__train__max_steps=300,
        field__train__batch_rays=256,
        field__losses__surface_rays=1024,
        field__losses__geo_rays=1024,
        field__render_scale=1,
    )
    outs = _run(run_field, cfg, frames, tmp_path / "out")
    got = Capture.load(outs.frames)
    rels = [
        depth_absrel(read_depth(f.depth, got.depth_scale), read_depth(g.depth))
        for f, g in zip(got.frames, read_layout(room).frames, strict=True)
    ]
    assert float(np.mean(rels)) < 0.12, rels
    assert rels[4] < 0.25, rels


@pytest.mark.slow  # 51 s on the idle machine: two field fills rendered at full size (the
# untrained field without stereo marches every sample); the default suite keeps the
# other two fill tests
def test_stereo_gives_the_field_dense_depth(tiny_room, tmp_path):
    # photos + 1 % of the readings (SfM tracks): the sweep fills in dense depth before the
    # field trains, so a short run already renders the room's depth; without it the same
    # steps leave a field that has barely started. Measured: mean AbsRel 0.155 with stereo,
    # 0.253 without (80 steps of the small field; the sweep keeps 14 % of the pixels)
    cap = read_layout(tiny_room)
    frames = _sparse(tiny_room, tmp_path / "sparse", keep=0.01)
    # the field's own render is scored: no check of the rendered readings
    cfg = tune(
        FAST,
        field__train__max_steps=DENSE_STEPS,
        field__render_scale=1,
        field__fill=True,
        field__check=0,
        planes__enabled=False,  # the sweep's readings alone before the field
    )
    rels, facts = {}, {}
    for stereo, fn in ((True, run_stereo), (False, run_field)):
        outs = _run(fn, cfg, frames, tmp_path / f"stereo_{stereo}")
        facts[stereo] = read_json(outs.stats)
        got = Capture.load(outs.frames)
        rels[stereo] = [
            depth_absrel(read_depth(f.depth, got.depth_scale), read_depth(g.depth))
            for f, g in zip(got.frames, cap.frames, strict=True)
        ]
    st = facts[True]
    assert "kept" not in facts[False] and 0.1 < st["kept"] <= st["matched"] <= 1
    assert not st["field"]["depth_dense"] and st["field"]["depth_absrel"] is None
    assert np.mean(rels[True]) < 0.8 * np.mean(rels[False]), rels
    # fusion's depth: every view's stereo readings (the held-out views' too), the render
    # elsewhere; the sources say which
    assert st["field"]["stereo_check_kept"] is None  # check 0
    got = Capture.load(tmp_path / "stereo_True" / "frames.json")
    n_stereo = 0
    for f in got.frames:
        d = np.load(f.depth)
        src = read_label(tmp_path / "stereo_True" / "sources" / f"{f.stem}.png")
        assert d.shape == src.shape == (72, 96)
        assert np.array_equal(src > 0, d > 0)
        n_stereo += int((src == STEREO).sum())
    assert n_stereo > 0
    cov, by = st["coverage"], st["by_source"]
    assert cov["sweep"] == cov["planes"] < cov["field"]
    assert by["stereo"] == pytest.approx(cov["sweep"], abs=1e-3)
    assert by["stereo"] + by["field"] == pytest.approx(cov["field"], abs=1e-3)


def test_the_field_trains_only_when_the_readings_cover_too_little(tiny_room, tmp_path):
    # the photos-only default (depth.field.fill auto): at 96x72 the sweep keeps ~14 % of the
    # pixels: under depth.field.below 50 % the field trains, under 10 % not (the plane fill
    # off: on, it covers 50 % of this room, and the field's decision reads its coverage)
    frames = _sparse(tiny_room, tmp_path / "sparse", keep=0.01)
    cfg = tune(
        FAST, field__train__max_steps=DENSE_STEPS, field__render_scale=1, planes__enabled=False
    )
    got = {}
    for below in (0.5, 0.1):
        c = tune(cfg, field__fill="auto", field__below=below)
        outs = _run(run_stereo, c, frames, tmp_path / f"below_{below}")
        got[below] = (read_json(outs.stats), Capture.load(outs.frames), outs)
    st, cap, outs = got[0.5]
    assert 0.1 < st["kept"] < 0.5
    assert st["field_fill"].startswith("field trained") and "under" in st["field_fill"]
    assert (outs.field / "model.pt").is_file() and st["field"]["steps"] == DENSE_STEPS
    filled = swept = 0
    for f in cap.frames:
        assert Path(f.depth).parent == outs.depth
        src = read_label(outs.sources / f"{f.stem}.png")
        filled += int((np.load(f.depth) > 0).sum())
        swept += int((src == STEREO).sum())
    assert filled > 2 * swept, (filled, swept)
    st, cap, outs = got[0.1]
    assert st["field_fill"].startswith("no field trained") and "field" not in st
    assert not outs.field.exists() and "field" not in st["coverage"]
    assert all(Path(f.depth).parent == outs.depth for f in cap.frames)


def test_the_fill_field_trains_and_renders_at_the_sweeps_resolution(tiny_room, tmp_path):
    # stereo swept at 1/2: the field that fills its holes trains on the views binned 2 x 2
    # and writes every view's depth at 1/2; a held-out view's rendered depth is the room's at
    # that resolution, which a wrong principal point or focal length of the binned views
    # would miss (AbsRel 0.011 and 0.016 after 240 steps)
    cap = read_layout(tiny_room)
    frames = _sparse(tiny_room, tmp_path / "sparse", keep=0.01)
    c = tune(
        FAST,
        field__train__max_steps=3 * DENSE_STEPS,
        field__render_scale=1,
        field__fill=True,
        field__check=0,
        field__sampling__samples_across=200,
        stereo__scale=2,
        planes__enabled=False,  # the field alone fills the holes
    )
    outs = _run(run_stereo, c, frames, tmp_path / "out")
    st = read_json(outs.stats)
    assert st["scale"] == 2 and st["field"]["train_scale"] == 2
    assert st["field"]["depth_render_scale"] == 2
    # ... and marches at its own step (depth.field.sampling), not the nerf stage's
    diag = float(np.linalg.norm(np.subtract(*st["field"]["box"][::-1])))
    assert st["field"]["step_m"] == pytest.approx(diag / 200, rel=1e-3)
    got = Capture.load(outs.frames)
    assert [f.intrinsics for f in got.frames] == [f.intrinsics for f in cap.frames]
    held = heldout_views(len(cap.frames), c.field.train.holdout_every)
    assert held
    for i in held:
        f, g = got.frames[i], cap.frames[i]
        d = np.load(f.depth)
        src = read_label(outs.sources / f"{f.stem}.png")
        assert d.shape == (36, 48)
        gt = read_depth(g.depth)[::2, ::2]  # a binned pixel's centre: between four
        gt = np.minimum(gt, read_depth(g.depth)[1::2, 1::2])
        ok = (src == FIELD) & (gt > 0)
        assert ok.mean() > 0.3
        assert np.median(np.abs(d[ok] - gt[ok]) / gt[ok]) < 0.05


def test_upsample_depth_repeats_blocks_and_edges():
    d = np.array([[1.0, 2.0], [3.0, 0.0]], np.float32)
    got = upsample_depth(d, (5, 5))  # 2 x 2 blocks, the fifth row and column repeat the fourth
    np.testing.assert_array_equal(got[:4, :4], np.kron(d, np.ones((2, 2), np.float32)))
    np.testing.assert_array_equal(got[4], got[3])
    np.testing.assert_array_equal(got[:, 4], got[:, 3])
    assert got.dtype == np.float32
    with pytest.raises(BlunfError, match="whole blocks"):
        upsample_depth(d, (4, 6))


def barely_trained_field(tmp_path):
    """A field trained 20 steps on 1 % of the depth of a 5-view room (48 x 36): its config,
    model, the sparse capture and the room's true layout (for the fill's spread tests)."""
    room = make_room(tmp_path / "room", views=5, seed=3, size=(48, 36))
    frames = _sparse(room, tmp_path / "sparse", keep=0.01)
    cfg = tune(
        FAST, field__train__max_steps=20, field__render_scale=1, field__sampling__acc_threshold=0.0
    )
    outs = _run(run_field, cfg, frames, tmp_path / "out")
    return cfg, load_field(outs.field / "model.pt"), Capture.load(frames), read_layout(room)


def test_renders_whose_weights_spread_along_the_ray_are_dropped(tmp_path):
    # depth.field.max_spread: a reading whose compositing weights spread along its ray by
    # more than that share of its depth is 0 (fog the photos do not pin down, which reads
    # short); the others are the plain render's. On a field barely trained (20 steps, 1 %
    # of the depth) the dropped readings are the worse ones against the room's true depth.
    cfg, model, cap, truth = barely_trained_field(tmp_path)
    plain = [render_depth(model, f, cfg.field) for f in cap.frames]
    spread = [ray_spread(model, np.asarray(f.pose), f.intrinsics)[2] for f in cap.frames]
    hit = np.concatenate([(d > 0).reshape(-1) for d in plain])
    limit = float(np.median(np.concatenate([s.reshape(-1) for s in spread])[hit]))
    narrow = replace(cfg.field, max_spread=limit)
    err_kept, err_dropped = [], []
    for f, g, d, s in zip(cap.frames, truth.frames, plain, spread, strict=True):
        got = render_depth(model, f, narrow)
        assert np.array_equal(got, np.where(s <= limit, d, 0.0))
        true = read_depth(g.depth, truth.depth_scale)
        rel = np.abs(d - true) / np.where(true > 0, true, 1.0)
        err_kept.append(rel[(got > 0) & (true > 0)])
        err_dropped.append(rel[(d > 0) & (got == 0) & (true > 0)])
    kept, dropped = np.concatenate(err_kept), np.concatenate(err_dropped)
    assert len(kept) > 100 and len(dropped) > 100
    assert np.median(dropped) > 1.5 * np.median(kept), (np.median(dropped), np.median(kept))
    with pytest.raises(BlunfError, match="max_spread"):
        FieldFillConfig(max_spread=-0.1)

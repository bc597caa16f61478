"""The NeRF stage on a tiny procedural room (exact images, depth, labels and plan)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.common.blueprint import Blueprint
from stages.common.capture import Capture, read_layout
from stages.common.io import read_depth, read_image, read_json, read_label
from stages.nerf import IMPLS, NerfConfig, NerfInputs, NerfOutputs, load_model, top_view_labels
from stages.nerf.render import render_view
from stages.nerf.train import (
    build_model,
    depth_points,
    gather_rays,
    load_views,
    scene_box,
    split,
    train,
)
from stages.synth.room import FLOOR

# Training runs take 40-50 CPU-s on this machine: they run in the slow target.
pytestmark = pytest.mark.slow

torch.set_num_threads(1)

# ~25 s of CPU on one thread: enough for the geometry (depth-supervised) and the flat colours;
# max_steps makes the run reproducible (a time budget would not be).
TINY = NerfConfig(
    threads=1,
    max_steps=200,
    time_budget=0.0,
    batch_rays=1024,
    eval_every=0,
    holdout_every=8,
)


def _frames(room: Path, tmp: Path) -> Path:
    path = tmp / "frames.json"
    read_layout(room).save(path)
    return path


@pytest.fixture(scope="module")
def trained(tiny_room, tmp_path_factory) -> tuple[Path, NerfOutputs]:
    tmp = tmp_path_factory.mktemp("nerf")
    out = tmp / "out"
    out.mkdir()
    return tiny_room, IMPLS["grid"](TINY, NerfInputs(_frames(tiny_room, tmp)), out)


def test_outputs_and_photos_only_depth(trained):
    room, outs = trained
    assert outs == NerfOutputs.at(outs.model.parent)
    stats = read_json(outs.stats)
    assert stats["steps"] == 200 and stats["stop_reason"] == "steps"
    assert stats["depth_supervised"] and stats["semantics"]
    cap = Capture.load(outs.frames)
    src = read_layout(room)
    assert [f.stem for f in cap.frames] == [f.stem for f in src.frames]
    rels = []
    for f, g in zip(cap.frames, src.frames, strict=True):
        assert f.depth == outs.depth / f"{f.stem}.png" and f.depth.exists()
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        gt = read_depth(g.depth)
        assert d.shape == gt.shape
        ok = gt > 0
        rels.append(np.median(np.abs(d[ok] - gt[ok]) / gt[ok]))
    # Depth is supervised on the training views; surfaces settle within about one marching
    # step (box diagonal / 512 ~ 1.5 cm) of the truth at 1-5 m, i.e. ~1 %: 5 % leaves room
    # for the short run and for the two held-out views, which no ray was trained on.
    assert float(np.mean(rels)) < 0.05, rels
    assert stats["depth_absrel"] < 0.05


def test_psnr_beats_mean_colour(trained):
    room, outs = trained
    stats = read_json(outs.stats)
    cap = read_layout(room)
    # the mean-colour baseline: every pixel predicted by the mean training colour. At 96 x 72
    # the rooms' 4 cm noise texture is at the pixel scale, so a flat colour already scores
    # ~18 dB; the field must clearly beat it on the views it was trained on (it reaches
    # ~20.5 dB in 200 steps), and on the two held-out views it must not be far worse.
    train = [i for i in range(len(cap.frames)) if i % 8 != 4]
    mean = np.mean([read_image(cap.frames[i].image).reshape(-1, 3).mean(0) for i in train], 0)
    mse = np.mean([((read_image(cap.frames[i].image) - mean) / 255.0) ** 2 for i in train])
    baseline = 10 * np.log10(1.0 / mse)
    assert stats["psnr_train"] > baseline + 2.0, (stats["psnr_train"], baseline)
    assert stats["psnr_heldout"] > baseline - 1.5, (stats["psnr_heldout"], baseline)


def test_model_round_trip_and_views(trained):
    room, outs = trained
    model = load_model(outs.model)
    f = read_layout(room).frames[4]
    v = render_view(model, np.asarray(f.pose), f.intrinsics)
    h, w = f.intrinsics.height, f.intrinsics.width
    assert v["rgb"].shape == (h, w, 3) and v["depth"].shape == (h, w)
    assert np.isfinite(v["rgb"]).all() and np.isfinite(v["depth"]).all()
    # rendered z-depth against the exact depth of the synthetic camera
    gt = read_depth(f.depth)
    ok = (gt > 0) & (v["acc"] >= 0.5)
    assert ok.mean() > 0.9
    assert np.median(np.abs(v["depth"][ok] - gt[ok]) / gt[ok]) < 0.05
    # semantics: most pixels get the ground-truth class
    assert (v["semantics"] == read_label(f.label)).mean() > 0.7


def test_top_view_labels_find_the_floor(trained):
    room, outs = trained
    model = load_model(outs.model)
    plan = Blueprint.load(room / "gt" / "blueprint.npz")
    got = top_view_labels(model, plan.grid, [1.0])
    assert list(got) == [1.0]
    lab = got[1.0]
    assert lab.shape == plan.labels.shape and lab.dtype == np.uint8
    floor = plan.labels == FLOOR
    # from 1 m down, the first surface over a GT floor cell is the floor (furniture taller
    # than 1 m is in the GT plan as furniture): most such cells must read floor
    assert (lab[floor] == FLOOR).mean() > 0.6


def test_same_seed_same_weights(tiny_room):
    # the whole training (init, batches, jitter, occupancy updates) is seeded: two runs give
    # bit-identical weights and occupancy grids
    cfg = replace(TINY, max_steps=8, batch_rays=256, occ_every=4)
    cap = read_layout(tiny_room)
    views = load_views(cap, cfg.semantics)
    tr, held = split(len(cap.frames), cfg.holdout_every)
    pts = depth_points(cap, views, tr, cfg.depth_stride)
    lo, hi = scene_box(cap.poses()[:, :3, 3], pts, cfg)
    rays = gather_rays(cap, views, tr)
    sds = []
    for _ in range(2):
        torch.manual_seed(cfg.seed)
        model = build_model(cfg, lo, hi, views.class_ids, [pts])
        train(cfg, model, rays, None)
        sds.append(model.state_dict())
    for key in sds[0]:
        assert torch.equal(sds[0][key], sds[1][key]), key
    # and another seed gives other weights
    torch.manual_seed(1)
    other = build_model(replace(cfg, seed=1), lo, hi, views.class_ids, [pts])
    train(replace(cfg, seed=1), other, rays, None)
    assert not torch.equal(other.state_dict()["encoding.table"], sds[0]["encoding.table"])

"""The field fill's spread limit set by the field's own readings (stages/depth/spread.py,
depth.field.max_spread_agreeing): a multiple of the median spread of the renders that agree
with stereo, so a well-trained and a briefly trained field each keep their tight readings
and drop their wide ones, where one fixed share fits only one of them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stages.common.errors import BlunfError
from stages.common.io import read_depth
from stages.depth.config import FieldFillConfig
from stages.depth.render import ray_spread, write_depths
from stages.depth.spread import MIN_AGREEING, at_blocks, sample_blocks, spread_limit
from tests.stages.test_depth_field import barely_trained_field


def _field(rng: np.random.Generator, tight: float, wide: float):
    """(spreads of 500 renders agreeing with stereo around `tight`, of 300 hole renders
    round `tight` (surfaces the field learnt), of 300 round `wide` (fog))."""
    around = lambda c, n: c * rng.uniform(0.8, 1.25, n)  # noqa: E731
    return around(tight, 500), around(tight, 300), around(wide, 300)


@pytest.mark.parametrize("tight, wide", [(0.015, 0.08), (0.07, 0.4)])
def test_the_limit_follows_the_fields_own_agreeing_readings(tight, wide):
    # a well-trained field (tight 1.5 %, fog 8 % of the depth, as on the 7-Scenes kitchen
    # from 100 views) and a briefly trained one (tight 7 %, fog 40 %, as from 20 views and
    # 50 steps): 3 x the agreeing readings' median keeps the first kind, drops the second
    agree, good, fog = _field(np.random.default_rng(0), tight, wide)
    limit, facts = spread_limit(agree, 3.0, 0.0)
    assert np.all(good <= limit) and np.all(fog > limit), (limit, tight, wide)
    assert facts["limit"] == pytest.approx(3.0 * np.median(agree), abs=1e-4)
    assert facts["agreeing_readings"] == 500
    # no limit without the rule; a fixed 0.05 fits the well-trained field only
    assert spread_limit(agree, 0.0, 0.0)[0] == float("inf")
    assert np.all(good <= 0.05) == (tight < 0.05)
    # the fixed share is a floor under the rule
    assert spread_limit(agree, 3.0, 0.5)[0] == 0.5


def test_too_few_agreeing_readings_set_no_limit():
    few = np.full(MIN_AGREEING - 1, 0.01)
    assert spread_limit(few, 3.0, 0.0)[0] == float("inf")
    assert spread_limit(few, 3.0, 0.05)[0] == 0.05
    assert "too few" in spread_limit(few, 3.0, 0.0)[1]["rule"]
    with pytest.raises(BlunfError, match="max_spread_agreeing"):
        FieldFillConfig(max_spread_agreeing=-1.0)


def test_blocks_and_samples():
    prior = np.arange(36.0).reshape(6, 6)
    assert np.array_equal(at_blocks(prior, (3, 3)), prior[1::2, 1::2])  # block centres
    need = np.zeros((4, 4), bool)
    need[0, 0] = True
    got = sample_blocks(need)
    assert not got[0, 0] and got[2, 2] and got[0, 2] and not got[1, 1]


def test_the_fill_drops_what_spreads_past_the_agreeing_readings(tmp_path):
    # a small field barely trained (20 steps) on a room from 1 % of its depth; "stereo"
    # reads the true depth on the left half of each view, the field fills the right half.
    # The limit is 3 x the median spread of its renders that agree with that stereo (a
    # sample of the left half); the fill keeps exactly the readings under it, and those
    # it drops lie farther from the room's true depth than those it keeps.
    cfg, model, cap, truth = barely_trained_field(tmp_path)
    true = [read_depth(g.depth, truth.depth_scale) for g in truth.frames]
    prior = {}
    for i, t in enumerate(true):
        p = t.copy()
        p[:, t.shape[1] // 2 :] = 0.0
        prior[i] = p.astype(np.float32)
    fc = replace(cfg.field, max_spread_agreeing=3.0)
    (tmp_path / "d").mkdir()
    _, facts, depths = write_depths(model, list(cap.frames), fc, tmp_path / "d", prior, 0, 0.05)
    rendered = [ray_spread(model, np.asarray(f.pose), f.intrinsics) for f in cap.frames]
    agree = np.concatenate(
        [
            s[sample_blocks(p <= 0) & (np.abs(d - p) <= 0.05 * p) & (p > 0)]
            for (d, _, s), p in zip(rendered, prior.values(), strict=True)
        ]
    )
    sp = facts["spread"]
    assert sp["agreeing_readings"] == len(agree) >= MIN_AGREEING
    limit = 3.0 * float(np.median(agree))
    assert sp["limit"] == pytest.approx(limit, abs=1e-4)
    err_kept, err_dropped, dropped = [], [], 0
    for (d, _, s), p, t, got in zip(rendered, prior.values(), true, depths, strict=True):
        hole = p <= 0
        assert np.array_equal(got[hole] > 0, s[hole] <= limit)  # wide renders dropped
        assert np.array_equal(got[~hole], p[~hole])  # stereo untouched
        rel = np.abs(d - t) / np.where(t > 0, t, 1.0)
        err_kept.append(rel[hole & (got > 0) & (t > 0)])
        err_dropped.append(rel[hole & (got == 0) & (t > 0)])
        dropped += int((hole & (got == 0)).sum())
    assert dropped == pytest.approx(
        sp["dropped"] * sum(int((p <= 0).sum()) for p in prior.values()), abs=1
    )
    kept, lost = np.concatenate(err_kept), np.concatenate(err_dropped)
    assert len(kept) > 100 and len(lost) > 20, (len(kept), len(lost))
    assert np.median(lost) > 1.5 * np.median(kept), (np.median(lost), np.median(kept))

"""The field fill's depth bias measured against stereo in the same run and taken out
(stages/depth/debias.py, depth.field.debias): a field that renders short, more so the
farther the surface, fills stereo's holes at the depth stereo would have read."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.common.io import read_depth
from stages.depth.config import FieldFillConfig
from stages.depth.debias import MIN_PAIRS, bias_curve, debiased
from stages.depth.render import write_depths
from tests.stages.test_depth_field import barely_trained_field


def test_a_depth_dependent_shortfall_is_taken_out():
    # renders 1 % short at 1 m, 4 % at 4 m (as the 7-Scenes kitchen's field past 1.5 m),
    # with 1 % noise and a few readings of another surface; the curve from the pairs puts
    # holes filled by the same field back within 1 % of the truth, where they were 2-4 % off
    rng = np.random.default_rng(0)
    short = lambda d: d * (1.0 - 0.01 * d)  # noqa: E731
    stereo = rng.uniform(0.5, 4.0, 4000)
    render = short(stereo) * rng.normal(1.0, 0.01, stereo.size)
    render[:100] *= 0.5  # another surface in front: not a pair
    curve = bias_curve(render, stereo)
    assert curve is not None and len(curve[0]) == 8
    truth = rng.uniform(1.5, 3.5, 1000)
    hole = short(truth)
    assert np.median(np.abs(hole / truth - 1)) > 0.02
    fixed = debiased(hole.astype(np.float32), curve)
    assert np.max(np.abs(fixed / truth - 1)) < 0.01
    assert debiased(np.zeros(3, np.float32), curve).tolist() == [0.0, 0.0, 0.0]


def test_too_few_pairs_change_nothing():
    assert bias_curve(np.ones(MIN_PAIRS - 1), np.ones(MIN_PAIRS - 1)) is None
    d = np.array([1.0, 0.0, 2.0], np.float32)
    assert debiased(d, None) is d
    assert FieldFillConfig().debias is False  # opt-in


def test_the_fill_is_divided_by_the_fields_ratio_to_stereo(tmp_path):
    # a barely trained field fills the right half of each view; "stereo" reads the room's
    # true depth on the left half. With depth.field.debias the fills are the plain fills
    # divided by the curve measured on the renders beside stereo; stereo is untouched.
    cfg, model, cap, truth = barely_trained_field(tmp_path)
    prior = {}
    for i, g in enumerate(truth.frames):
        p = read_depth(g.depth, truth.depth_scale).copy()
        p[:, p.shape[1] // 2 :] = 0.0
        prior[i] = p.astype(np.float32)
    fc = replace(cfg.field, max_spread_agreeing=1000.0)  # renders beside stereo, drops none
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _, plain_facts, plain = write_depths(model, list(cap.frames), fc, tmp_path / "a", prior)
    _, facts, fixed = write_depths(
        model, list(cap.frames), replace(fc, debias=True), tmp_path / "b", prior
    )
    assert plain_facts["spread"]["debias"] is None
    curve = facts["spread"]["debias"]
    assert curve is not None and len(curve["depth"]) >= 1
    at, ratio = np.asarray(curve["depth"]), np.asarray(curve["ratio"])
    assert np.all(np.diff(at) >= 0)
    for p, a, b in zip(prior.values(), plain, fixed, strict=True):
        hole = p <= 0
        np.testing.assert_array_equal(b[~hole], p[~hole])
        want = np.where(a > 0, a / np.interp(a, at, ratio), 0.0)
        np.testing.assert_allclose(b[hole], want[hole], rtol=2e-3, atol=1e-6)
        assert not np.allclose(b[hole & (a > 0)], a[hole & (a > 0)])

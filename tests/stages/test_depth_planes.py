"""Plane fill (stages/depth/planes): the expansion solver against brute force, the plane
hypotheses on exact synthetic points, and fill() on a plain procedural room whose blank
walls stereo cannot read, against the room's exact depth."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from stages.common.capture import read_layout
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label
from stages.depth.planes import PlanesConfig, fill
from stages.depth.planes.hypotheses import find_planes
from stages.depth.planes.solve import energy, expand


def test_expansion_reaches_the_optimum_of_tiny_graphs():
    rng = np.random.default_rng(0)
    n, labels = 6, 3
    exact = 0
    for _ in range(30):
        unary = rng.random((n, labels)) * 2
        edges = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.6])
        edges = edges.reshape(-1, 2)
        # a metric pair cost per edge: weight x (symmetric costs in [1, 1.5] off the diagonal,
        # so every triangle inequality holds): expansion moves are exact there
        w = rng.random(len(edges))
        m = 1 + 0.5 * rng.random((len(edges), labels, labels))
        m = (m + m.transpose(0, 2, 1)) / 2 * w[:, None, None]
        m[:, np.arange(labels), np.arange(labels)] = 0

        def pair(e, a, b, m=m):
            return m[e, a, b]

        x, e = expand(unary, edges, pair, cycles=5)
        assert e == pytest.approx(energy(x, unary, edges, pair))
        every = [
            energy(np.array(lab), unary, edges, pair)
            for lab in itertools.product(range(labels), repeat=n)
        ]
        opt = min(every)
        # the expansion-move bound (Boykov et al. 2001): within 2 x max/min pair cost ratio
        assert e <= 3 * opt + 1e-9
        # and no single expansion move from the result lowers the energy (max-flow is exact)
        for alpha in range(labels):
            for mask in itertools.product((0, 1), repeat=n):
                y = np.where(np.array(mask) == 1, alpha, x)
                assert energy(y, unary, edges, pair) >= e - 1e-3
        exact += e <= opt + 1e-3
    assert exact >= 27  # on these tiny graphs it nearly always finds the optimum itself


def _patch(rng, n, fixed_axis, value, lo, hi, normal):
    p = rng.uniform(lo, hi, (n, 3))
    p[:, fixed_axis] = value + rng.normal(0, 0.003, n)  # 3 mm noise
    return p, np.tile(normal, (n, 1))


def test_hypotheses_on_a_floor_two_walls_and_a_table():
    rng = np.random.default_rng(1)
    parts = [
        _patch(rng, 20000, 2, 0.0, (0, 0, 0), (3, 3, 0), (0, 0, 1)),  # floor
        _patch(rng, 15000, 0, 0.0, (0, 0, 0), (0, 3, 2.5), (1, 0, 0)),  # wall x = 0
        _patch(rng, 15000, 1, 3.0, (0, 3, 0), (3, 3, 2.5), (0, -1, 0)),  # wall y = 3
        _patch(rng, 4000, 2, 0.75, (1, 1, 0), (2, 1.8, 0), (0, 0, 1)),  # table top
    ]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([q for _, q in parts]).astype(np.float64)
    planes = find_planes(pts, nrm, PlanesConfig())
    assert planes[0].kind == "floor" and abs(planes[0].offset) < 0.005
    got = {(p.kind, tuple(np.round(np.abs(p.normal)).astype(int))): p for p in planes}
    assert abs(abs(got["wall", (1, 0, 0)].offset) - 0.0) < 0.005
    assert abs(abs(got["wall", (0, 1, 0)].offset) - 3.0) < 0.005
    top = got["top", (0, 0, 1)]
    assert abs(top.offset - 0.75) < 0.005
    # the table top's support box is the table's extent (2nd-98th percentile of inliers)
    np.testing.assert_allclose(top.lo[:2], [1.02, 1.02], atol=0.03)
    np.testing.assert_allclose(top.hi[:2], [1.98, 1.78], atol=0.03)
    assert len(planes) == 4
    for p in planes:
        assert np.degrees(np.arccos(np.max(np.abs(p.normal)))) < 0.5


@pytest.fixture(scope="module")
def plain_room(tmp_path_factory):
    from stages.synth import make_room
    from stages.synth.realism import Realism

    root = make_room(
        tmp_path_factory.mktemp("plain") / "capture",
        views=12,
        seed=3,
        size=(160, 120),
        realism=Realism.parse("honest"),
    )
    return read_layout(root)


def test_fill_reads_blank_walls_from_the_planes(plain_room):
    cap = plain_room
    wall_id = [k for k, v in cap.classes.items() if v == "wall"][0]
    images, Ks, poses, sparse, depths, exact, walls = [], [], [], [], [], [], []
    for f in cap.frames:
        img = read_image(f.image).astype(np.float32) / 255.0
        d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        gray = img.mean(2)
        std = np.sqrt(np.maximum(uniform_filter(gray**2, 7) - uniform_filter(gray, 7) ** 2, 0))
        textured = std > 0.03  # what stereo reads: the plain walls are not among it
        images.append(img)
        Ks.append(f.intrinsics.K)
        poses.append(np.asarray(f.pose))
        sp = np.zeros_like(d)
        sp[::7, ::7] = np.where(textured[::7, ::7], d[::7, ::7], 0)  # SfM tracks
        sparse.append(sp)
        # the sweep's readings at half size (nearest), only where textured
        depths.append(np.where(textured, d, 0)[::2, ::2].astype(np.float32))
        exact.append(d[::2, ::2])
        walls.append(read_label(f.label)[::2, ::2] == wall_id)
    out, src, facts = fill(images, Ks, poses, sparse, depths, PlanesConfig(enabled=True))
    assert facts["coverage_after"] > facts["coverage_before"] + 0.2
    planes = np.concatenate([(s == 2).reshape(-1) for s in src])
    err = np.abs(np.concatenate([(o - e).reshape(-1) for o, e in zip(out, exact, strict=True)]))
    good = np.concatenate([(e > 0).reshape(-1) for e in exact])
    assert np.mean(err[planes & good] <= 0.03) > 0.9
    blank = np.concatenate([(w & (d == 0)).reshape(-1) for w, d in zip(walls, depths, strict=True)])
    assert np.mean(planes[blank]) > 0.5  # most of the blank walls get plane depth
    assert facts["coverage_by_kind"]["wall"] > 0.1
    for o, s, d in zip(out, src, depths, strict=True):
        assert o.shape == d.shape and s.dtype == np.uint8 and np.isfinite(o).all()
        np.testing.assert_array_equal(o[s == 1], d[s == 1])  # kept stereo is untouched


def test_fill_rejects_mismatched_inputs():
    with pytest.raises(BlunfError, match="differ"):
        fill([np.zeros((8, 8, 3), np.float32)], [], [], [], [], PlanesConfig(enabled=True))

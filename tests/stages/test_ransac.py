"""The RANSAC plane: exact on a noiseless plane among clutter, the same for the same seed."""

import numpy as np

from stages.common.ransac import plane_ransac


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """600 points on the tilted plane 0.2x - 0.1y + z = 1.5 (noise 5 mm), 400 of clutter."""
    xy = rng.uniform(-3, 3, (600, 2))
    z = 1.5 - 0.2 * xy[:, 0] + 0.1 * xy[:, 1] + rng.normal(0, 0.005, 600)
    on = np.column_stack([xy, z])
    clutter = rng.uniform(-3, 3, (400, 3))
    true = np.r_[0.2, -0.1, 1.0, -1.5] / np.linalg.norm([0.2, -0.1, 1.0])
    return np.concatenate([on, clutter]), true


def test_finds_the_plane_among_clutter():
    pts, true = _scene(np.random.default_rng(1))
    plane, inl = plane_ransac(pts, 0.02, 200, np.random.default_rng(0))
    plane = plane * np.sign(plane[2])
    assert np.allclose(plane, true, atol=0.01)
    assert np.isclose(np.linalg.norm(plane[:3]), 1.0)
    assert (inl < 600).sum() >= 597  # all but the plane's 4-sigma outliers
    assert (inl >= 600).sum() < 40  # few clutter points lie within 2 cm of it


def test_same_seed_same_plane_far_from_the_origin():
    pts, _ = _scene(np.random.default_rng(2))
    pts = pts + [5000.0, -3000.0, 0.0]  # a georeferenced world: centring keeps the precision
    runs = [plane_ransac(pts, 0.02, 300, np.random.default_rng(7)) for _ in range(3)]
    for plane, inl in runs[1:]:
        assert np.array_equal(plane, runs[0][0]) and np.array_equal(inl, runs[0][1])
    assert len(runs[0][1]) >= 590


def test_degenerate_points_give_no_plane():
    line = np.outer(np.linspace(0, 1, 50), [1.0, 2.0, 3.0])
    plane, inl = plane_ransac(line, 0.01, 50, np.random.default_rng(0))
    assert not inl.size and not plane.any()
    plane, inl = plane_ransac(line[:2], 0.01, 50, np.random.default_rng(0))
    assert not inl.size

"""pipeline.bench.scale: the true scale a photos-only model is scored against."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.bench.scale import similarity_scale


def test_similarity_scale_recovers_a_known_similarity() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(40, 3)) * [2.0, 1.5, 0.1]  # cameras: nearly planar, as a capture's
    q = Rotation.from_euler("xyz", [10, -70, 200], degrees=True).as_matrix()
    dst = 0.173 * src @ q.T + [4.0, -2.0, 1.0]
    assert similarity_scale(src, dst) == pytest.approx(0.173, rel=1e-9)
    # noise on the target moves it little; a mirror image is not a rotation: it still scores
    noisy = dst + rng.normal(scale=0.002, size=dst.shape)
    assert similarity_scale(src, noisy) == pytest.approx(0.173, rel=0.02)
    assert similarity_scale(src * [1, 1, -1], dst) < 0.173

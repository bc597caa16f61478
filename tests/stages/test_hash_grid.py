"""The radiance field's 3-D hash grid (stages/common/radiance/field.py HashGrid3D) against a
plain reading of Instant-NGP's encoding: per level, the 8 corners of the point's cell, each
indexed densely or through the spatial hash, weighted trilinearly."""

from __future__ import annotations

import numpy as np
import torch

from stages.common.radiance.field import HashGrid3D


def _reference(g: HashGrid3D, x: np.ndarray) -> np.ndarray:
    """float64, one corner at a time, the hash in Python integers (mod 2^32, as int32 wraps)."""
    table = g.table.detach().double().numpy()
    res, mult = g.res.numpy(), g.mult.numpy().astype(np.int64) % 2**32
    mask, offset = g.mask.numpy().astype(np.int64), g.offset.numpy()
    out = np.zeros((len(x), g.levels, g.features))
    x = np.clip(x.astype(np.float32), 0, 1)
    for lv in range(g.levels):
        pos = (x * np.float32(res[lv])).astype(np.float32)
        lo = np.floor(pos)
        f = (pos - lo).astype(np.float64)
        lo = lo.astype(np.int64)
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    c = lo + [dx, dy, dz]
                    h = (c[:, 0] * mult[lv, 0]) ^ (c[:, 1] * mult[lv, 1]) ^ (c[:, 2] * mult[lv, 2])
                    row = (h % 2**32 & mask[lv]) + offset[lv]
                    w = np.prod(np.where([dx, dy, dz], f, 1 - f), axis=1)
                    out[:, lv] += w[:, None] * table[row]
    return out.reshape(len(x), -1)


def test_hash_grid_matches_a_plain_reading_of_the_encoding():
    torch.manual_seed(0)
    # dense coarse levels and hashed fine ones (2^10 rows: 8^3 fits, 16^3 does not)
    g = HashGrid3D(levels=4, features=2, log2_size=10, base_res=4, max_res=64)
    with torch.no_grad():
        g.table.normal_()
    assert g.mult[0].tolist() == [1, 8, 64] and g.mult[-1, 1].item() != 2**7
    x = torch.rand(3000, 3, generator=torch.Generator().manual_seed(1)) * 1.2 - 0.1  # some outside
    got = g(x).detach().double().numpy()
    np.testing.assert_allclose(got, _reference(g, x.numpy()), rtol=0, atol=1e-5)
    # on a vertex of every level (the box's corners) the encoding is that vertex's row, exactly
    v = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.0]])
    rows = _reference(g, v.numpy())
    np.testing.assert_array_equal(g(v).detach().double().numpy(), rows)
    # the table's gradient is the trilinear weights scattered to the rows read
    g.zero_grad()
    g(x).sum().backward()
    assert g.table.grad is not None
    np.testing.assert_allclose(float(g.table.grad.sum()), len(x) * g.levels * g.features, rtol=1e-4)

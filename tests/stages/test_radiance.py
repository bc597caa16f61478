"""The shared radiance library (stages/common/radiance): compositing worked out by hand, and
the field answering a sample batch in one pass with nothing kept between calls."""

from __future__ import annotations

import math

import pytest
import torch

from stages.common.radiance.compositing import accumulate, accumulate_blocks, finish
from stages.common.radiance.config import FieldConfig, SamplingConfig
from stages.common.radiance.field import FieldOut, RadianceField
from stages.common.radiance.marching import Samples
from stages.common.radiance.occupancy import OccupancyGrid

torch.set_num_threads(1)


def _slab_samples() -> tuple[Samples, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ray 0: four samples 0.5 m long at t = 0.25, 0.75, 1.25, 1.75 through a slab of density
    2 / m over [0.5, 1.5) (samples 1 and 2), red then blue, logits (1, 0) then (0, 1). Ray 1:
    no sample at all (far = 3)."""
    samples = Samples(
        ray=torch.tensor([0, 0, 0, 0]),
        k=torch.tensor([0.0, 1.0, 2.0, 3.0]),
        t=torch.tensor([0.25, 0.75, 1.25, 1.75]),
        delta=torch.full((4,), 0.5),
        x=torch.zeros(4, 3),
        near=torch.tensor([0.0, 0.0]),
        far=torch.tensor([2.0, 3.0]),
        per_ray=4,
    )
    sigma = torch.tensor([0.0, 2.0, 2.0, 0.0])
    rgb = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    logits = torch.tensor([[5.0, 5.0], [1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    return samples, sigma, rgb, logits


def test_compositing_a_slab_by_hand():
    # optical depths sigma * delta = (0, 1, 1, 0); transmittance before each sample
    # T = (1, 1, e^-1, e^-2); alpha = 1 - e^-sd = (0, 0.63212, 0.63212, 0);
    # weights w = T alpha = (0, 0.63212, 0.23254, 0) (the green samples weigh nothing);
    # acc = 1 - e^-2 = 0.86466; depth = (0.75 * 0.63212 + 1.25 * 0.23254) / 0.86466 = 0.88447;
    # on a white background rgb = (0.63212, 0, 0.23254) + (1 - acc) = (0.76746, 0.13534,
    # 0.36788); class logits sum to (0.63212, 0.23254). Ray 1 has no sample: acc 0, depth =
    # its far end (3), rgb the background.
    samples, sigma, rgb, logits = _slab_samples()
    out = finish(accumulate(samples, sigma, rgb, logits, False), samples.near, samples.far,
                 torch.ones(3), return_samples=True)  # fmt: skip
    e1 = math.exp(-1.0)
    w = torch.tensor([0.0, 1 - e1, e1 * (1 - e1), 0.0])
    torch.testing.assert_close(out["weights"], w)
    torch.testing.assert_close(out["acc"], torch.tensor([0.86466, 0.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(out["depth"], torch.tensor([0.88447, 3.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(
        out["rgb"], torch.tensor([[0.76746, 0.13534, 0.36788], [1.0, 1.0, 1.0]]), atol=1e-5, rtol=0
    )
    assert out["semantics"] is not None
    torch.testing.assert_close(
        out["semantics"], torch.tensor([[0.63212, 0.23254], [0.0, 0.0]]), atol=1e-5, rtol=0
    )
    # the block-wise pass of full-view renders (no gradient, early stop at 1e-4: nothing is
    # dropped here) gives the same numbers
    dirs = torch.zeros(2, 3)

    def query(x: torch.Tensor, d: torch.Tensor | None) -> FieldOut:
        idx = torch.arange(len(x))  # one block: the ray's four samples in order
        return FieldOut(rgb[idx], sigma[idx], logits[idx])

    blocks = finish(accumulate_blocks(query, dirs, samples, 1e-4), samples.near, samples.far,
                    torch.ones(3), return_samples=True)  # fmt: skip
    for k in ("rgb", "acc", "depth", "semantics", "weights"):
        torch.testing.assert_close(blocks[k], out[k], atol=1e-6, rtol=0)  # type: ignore[literal-required]


def _field(color_grid: bool) -> RadianceField:
    torch.manual_seed(0)
    cfg = FieldConfig(hash_levels=2, hash_log2_size=10, hash_base_res=4, hash_max_res=8,
                      width=16, geo_features=3, color_grid=color_grid)  # fmt: skip
    lo, hi = -torch.ones(3), torch.ones(3)
    return RadianceField(cfg, SamplingConfig(), lo, hi, [1, 2], OccupancyGrid.for_box(lo, hi, 4))


@pytest.mark.parametrize("color_grid", [True, False])
def test_a_field_query_is_one_pass_with_nothing_kept(color_grid):
    # one query runs the density trunk once and answers colour, density and logits; they are
    # what the single-purpose calls give; and nothing is kept between calls: after the
    # weights change, the same tensor asked again gives the new field (a cache keyed on the
    # tensor, as before, returned the old features until someone cleared it)
    field = _field(color_grid)
    calls = []
    field.trunk.register_forward_hook(lambda m, i, o: calls.append(len(i[0])))
    x = torch.rand(50, 3) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(50, 3), dim=1)
    with torch.no_grad():
        f = field.query(x, dirs)
        assert calls == [50], calls  # one pass of the trunk over the batch
        assert f.rgb is not None and f.logits is not None
        assert f.rgb.shape == (50, 3) and f.sigma.shape == (50,) and f.logits.shape == (50, 2)
        torch.testing.assert_close(f.sigma, field.sigma(x), atol=0, rtol=0)
        torch.testing.assert_close(f.rgb, field.color(x, dirs), atol=0, rtol=0)
        torch.testing.assert_close(f.logits, field.logits(x), atol=0, rtol=0)
        no_color = field.query(x, None, semantics=False)
        assert no_color.rgb is None and no_color.logits is None
        field.trunk[-1].bias += 1.0  # raw density + 1: density times e, logits move
        g = field.query(x, dirs)
    torch.testing.assert_close(g.sigma, f.sigma * math.e, rtol=1e-5, atol=0)
    assert g.logits is not None and not torch.equal(g.logits, f.logits)

"""The field before training: its scene box and its occupancy grid seeded from depth."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator

import numpy as np
import torch
from torch import Tensor

from stages.common.radiance.config import TrainingConfig
from stages.common.radiance.field import RadianceField
from stages.common.radiance.occupancy import OccupancyGrid

log = logging.getLogger(__name__)

SEED_FACTOR = 10.0  # seeded cells start at this many times the occupancy threshold
SPARSE_DILATE = 2  # sparse depth: cells kept round each SfM track point (at least)


def scene_box(
    centers: np.ndarray, points: np.ndarray, cfg: TrainingConfig
) -> tuple[Tensor, Tensor]:
    """(lo [3], hi [3]): cameras and robust depth-point bounds, padded by box.pad."""
    if len(points):
        p_lo, p_hi = np.percentile(points, 0.5, axis=0), np.percentile(points, 99.5, axis=0)
        lo = np.minimum(centers.min(0), p_lo)
        hi = np.maximum(centers.max(0), p_hi)
    else:
        lo = centers.min(0) - cfg.box.no_depth_margin
        hi = centers.max(0) + cfg.box.no_depth_margin
    ext = np.maximum(hi - lo, 1e-3)
    lo, hi = lo - cfg.box.pad * ext, hi + cfg.box.pad * ext
    return torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)


def occupancy_threshold(cfg: TrainingConfig, step: float) -> float:
    """Density (1/m) at which one marching step has opacity occupancy.alpha."""
    return -math.log(1.0 - cfg.occupancy.alpha) / step


def build_model(
    cfg: TrainingConfig,
    lo: Tensor,
    hi: Tensor,
    class_ids: list[int],
    seeds: Iterable[np.ndarray],
    dense: bool = True,
) -> RadianceField:
    """A fresh model whose occupancy grid is seeded from the point sets `seeds` ([N, 3]
    each, e.g. one per depth map). With dense depth the seeded cells are the grid; with
    sparse depth (SfM tracks) the seeded cells are kept and updates add more; with no depth
    at all every cell starts occupied."""
    occ = OccupancyGrid.for_box(lo, hi, cfg.occupancy.res)
    model = RadianceField(cfg.field, cfg.sampling, lo, hi, class_ids, occ)
    thr = occupancy_threshold(cfg, model.step)
    dilate = cfg.occupancy.dilate
    if not dense:
        # cells round the tracks, for good; updates add the cells the field fills in
        # between (starting from a full grid costs hundreds of samples a ray for minutes)
        dilate = max(dilate, SPARSE_DILATE)
    counted = [0]

    def point_sets() -> Iterator[Tensor]:
        for pts in seeds:
            counted[0] += len(pts)
            yield torch.from_numpy(pts.astype(np.float32))

    occ.seed(point_sets(), SEED_FACTOR * thr, dilate)
    n_pts = counted[0]
    if n_pts:
        n = int(occ.binary.sum())
        log.info("nerf: occupancy %s seeded from %d depth points: %d cells", occ.shape, n_pts, n)
    else:
        occ.fill(SEED_FACTOR * thr)
    return model

"""A view's labels by alpha-expansion: data costs plus a pair cost on the superpixel graph.

Pair cost between neighbouring superpixels labelled a != b, times the boundary's length over
the mean length: `w_crease` when a and b are planes meeting at the boundary (their depths at
its centre within 2 tol: a room's corner or a counter's edge), otherwise a jump,
`w_jump` x (0.2 + 0.8 g) with g = exp(-(RGB distance / edge_sigma)^2): a strong colour edge
makes a jump cheap. `none` beside a plane costs the jump scaled to `w_none_edge`.
"""

from __future__ import annotations

import numpy as np

from stages.depth.planes.config import PlanesConfig
from stages.depth.planes.geometry import plane_depth, rays
from stages.depth.planes.hypotheses import Plane
from stages.depth.planes.solve import expand
from stages.depth.planes.view import Labelling, ViewData, data_costs, graph, superpixels

EDGE_FLOOR = 0.2  # a jump on the strongest colour edge still costs this share of w_jump


def label_view(
    v: ViewData,
    planes: list[Plane],
    nbrs: list[ViewData],
    cfg: PlanesConfig,
    ceiling: float | None,
    hists: np.ndarray | None = None,
) -> Labelling:
    """Superpixels of the view, their costs and the labels alpha-expansion picks."""
    seg = superpixels(v.rgb, cfg)
    unary, area = data_costs(v, seg, planes, nbrs, cfg, ceiling, hists)
    edges, length, centre, dist = graph(seg, v.rgb)
    n_p = len(planes)
    weight = area / max(float(area.mean()), 1.0)
    u = unary * weight[:, None]
    if not len(edges):
        lab = np.argmin(u, axis=1)
        return Labelling(seg, unary, lab, edges, float(u[np.arange(len(lab)), lab].sum()))
    # plane depths at each boundary's centre: creases where two planes meet there
    r = rays(centre, v.K, v.pose)
    t = plane_depth(r, v.pose[:3, 3], planes).T  # [E, P]
    t = np.concatenate([t, np.zeros((len(edges), 1))], 1)  # none: no depth
    ew = length / max(float(length.mean()), 1.0)
    jump = cfg.w_jump * (EDGE_FLOOR + (1 - EDGE_FLOOR) * np.exp(-((dist / cfg.edge_sigma) ** 2)))

    def pair(e: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        ta, tb = t[e, a], t[e, b]
        planes_both = (a < n_p) & (b < n_p) & (ta > 0) & (tb > 0)
        rel = np.abs(ta - tb) / np.maximum(np.minimum(ta, tb), 1e-6)
        crease = planes_both & (rel <= 2 * cfg.tol)
        c = np.where(crease, cfg.w_crease, jump[e])
        c = np.where((a == n_p) | (b == n_p), cfg.w_none_edge / cfg.w_jump * jump[e], c)
        return np.where(a == b, 0.0, c * ew[e])

    lab, en = expand(u, edges, pair, cycles=cfg.cycles)
    return Labelling(seg, unary, lab, edges, en)

"""Alpha-expansion (Boykov, Veksler, Zabih 2001) on a small graph with scipy's max-flow.

Each move asks every node "keep your label or switch to alpha" and answers it exactly by a
minimum s-t cut (Kolmogorov & Zabih 2004's construction) computed with
`scipy.sparse.csgraph.maximum_flow` on integer capacities. A pair term that is not
submodular for a move (the pairwise costs are not a metric: a crease is cheaper than a jump)
is truncated (Rother et al. 2005), and a move is kept only when it lowers the true energy,
so the energy never rises.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

PairCost = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
SCALE = 1e4  # costs are rounded to 1e-4 for the integer max-flow


def energy(labels: np.ndarray, unary: np.ndarray, edges: np.ndarray, pair: PairCost) -> float:
    """Sum of the nodes' unary costs [N, L] at `labels` and the edges' pair costs."""
    e = float(unary[np.arange(len(labels)), labels].sum())
    if len(edges):
        e += float(pair(np.arange(len(edges)), labels[edges[:, 0]], labels[edges[:, 1]]).sum())
    return e


def expand(
    unary: np.ndarray,
    edges: np.ndarray,
    pair: PairCost,
    cycles: int = 3,
    init: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Labels minimising unary + pair by alpha-expansion moves.

    Args:
        unary: [N, L] finite costs. edges: [E, 2] node pairs (each once).
        pair: f(edge ids [M], label of the first node [M], of the second [M]) -> costs [M],
            0 for equal labels.
        cycles: sweeps over all labels (stops early when a sweep changes nothing).
        init: [N] starting labels (default: each node's cheapest).
    Returns:
        (labels [N] int64, energy).
    """
    n, n_labels = unary.shape
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    x = np.argmin(unary, axis=1) if init is None else np.asarray(init, np.int64).copy()
    best = energy(x, unary, edges, pair)
    for _ in range(cycles):
        changed = False
        for alpha in range(n_labels):
            y = _move(x, alpha, unary, edges, pair)
            if y is None:
                continue
            e = energy(y, unary, edges, pair)
            if e < best - 1e-9:
                x, best, changed = y, e, True
        if not changed:
            break
    return x, best


def _move(
    x: np.ndarray, alpha: int, unary: np.ndarray, edges: np.ndarray, pair: PairCost
) -> np.ndarray | None:
    """The best expansion of `alpha` from x (binary variable 1 = switch to alpha)."""
    n = len(x)
    idx = np.arange(n)
    c0 = unary[idx, x].astype(np.float64)  # cost of keeping
    c1 = unary[:, alpha].astype(np.float64)  # cost of switching
    c1 = np.where(x == alpha, c0, c1)
    src, dst, cap = [], [], []
    if len(edges):
        i, j = edges[:, 0], edges[:, 1]
        eid = np.arange(len(edges))
        a = np.full(len(edges), alpha)
        e00 = pair(eid, x[i], x[j])
        e01 = pair(eid, x[i], a)
        e10 = pair(eid, a, x[j])
        e11 = np.zeros(len(edges))
        # a node already at alpha cannot change: its switch costs equal its keep costs
        e01 = np.where(x[j] == alpha, e00, e01)
        e10 = np.where(x[i] == alpha, e00, e10)
        e11 = np.where(x[i] == alpha, e01, np.where(x[j] == alpha, e10, e11))
        e00 = np.minimum(e00, e01 + e10 - e11)  # truncation of non-submodular terms
        # E = e00 + (e10 - e00) xi + (e11 - e10) xj + (e01 + e10 - e00 - e11) (1 - xi) xj
        np.add.at(c0, i, e00)
        np.add.at(c1, i, e10)
        np.add.at(c1, j, e11 - e10)
        w = e01 + e10 - e00 - e11
        keep = w > 0
        src.append(i[keep])
        dst.append(j[keep])
        cap.append(w[keep])
    # terminals: s = n (x = 0 side), t = n + 1; cut s->i when i switches, i->t when it keeps
    m = np.minimum(c0, c1)
    src += [np.full(n, n), idx]
    dst += [idx, np.full(n, n + 1)]
    cap += [c1 - m, c0 - m]
    s_, d_, c_ = np.concatenate(src), np.concatenate(dst), np.concatenate(cap)
    ci = np.rint(c_ * SCALE).astype(np.int64)
    if ci.sum() > np.iinfo(np.int32).max:
        ci = np.rint(ci * (np.iinfo(np.int32).max / ci.sum())).astype(np.int64)
    ok = ci > 0
    graph = csr_matrix((ci[ok].astype(np.int32), (s_[ok], d_[ok])), shape=(n + 2, n + 2))
    graph.sum_duplicates()
    flow = maximum_flow(graph, n, n + 1).flow
    residual = (graph - flow).tocsr()
    residual.data = np.where(residual.data > 0, 1, 0).astype(np.int32)
    residual.eliminate_zeros()
    reach = breadth_first_order(residual, n, directed=True, return_predecessors=False)
    in_source = np.zeros(n + 2, bool)
    in_source[reach] = True
    y = np.where(in_source[:n], x, alpha)
    return None if np.array_equal(y, x) else y

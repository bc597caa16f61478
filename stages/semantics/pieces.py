"""An object cluster split into pieces where its top height steps.

DBSCAN joins every surface that touches: a counter run, the wall cabinets over it, the
fridge beside it and the island when a stool bridges the gap (the 7-Scenes kitchen: three
clusters of up to 3.9 x 2.0 m). A plan shows each piece of furniture on its own, and pieces
of furniture that stand together differ in height: a 0.9 m counter, a 0.75 m island, a 0.45 m
chair seat beside a table, a 2 m wardrobe.

The cluster's triangles are binned on plan cells of `cell` metres; a cell's top is its
highest triangle centre. Neighbouring cells (4-connected) whose tops differ by at most `step`
are one piece. A piece no disk of `min_width` fits in (a chair back, a sofa's arm, the
bevelled edge between two tops), and one that does not reach down to the floor (a pillow on a
bed, a kettle on a counter, a wall cabinet over it: its lowest triangle above `stands_below`),
joins the neighbouring piece it borders most, smallest first; one that borders none joins the
cluster's largest piece. Every triangle takes
the piece of its cell: the front and legs of a counter go with its top. A piece that fills
less than BOX_FILL of its box (counters round a corner: an L) is cut into straight runs.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

BOX_FILL = 0.8  # a piece filling less of its box is cut into straight runs
CUT_SHARE = 0.2  # ... each holding at least this share of its cells


def split_by_top(
    c: np.ndarray, cell: float, step: float, min_width: float, stands_below: float = np.inf
) -> np.ndarray:
    """Piece index [N] (0..P-1, by decreasing cell count) of each triangle centre [N, 3]; a
    piece whose lowest triangle lies above `stands_below` (metres) stands on another."""
    if len(c) == 0:
        return np.zeros(0, np.int64)
    ij = np.floor(c[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    h, w = ij.max(axis=0) + 1
    flat = ij[:, 0] * w + ij[:, 1]  # [N] cell of each triangle
    top = np.full(h * w, -np.inf)
    np.maximum.at(top, flat, c[:, 2])
    top = top.reshape(h, w)  # [H, W] -inf: no triangle
    low = np.full(h * w, np.inf)
    np.minimum.at(low, flat, c[:, 2])
    full = np.isfinite(top)
    low = np.where(full, low.reshape(h, w), np.inf)  # [H, W] lowest triangle of each cell
    piece = _joined(top, full, step)
    r = max(1, int(round(min_width / cell / 2)))
    piece = _merged(piece, full, r, low, stands_below)
    piece = _merged(_straight(piece, full), full, r, low, stands_below)
    # renumber by decreasing size (ties: first cell in raster order), 0..P-1
    ids, first, size = np.unique(piece[full], return_index=True, return_counts=True)
    order = np.lexsort((first, -size))
    lut = np.zeros(int(piece.max()) + 1, np.int64)
    lut[ids[order]] = np.arange(len(ids))
    return lut[piece.reshape(-1)[flat]]


def _joined(top: np.ndarray, full: np.ndarray, step: float) -> np.ndarray:
    """Pieces [H, W] (1.., 0 = empty): cells joined to their 4-neighbours within `step`."""
    h, w = top.shape
    idx = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    for a, b in ((np.s_[:-1, :], np.s_[1:, :]), (np.s_[:, :-1], np.s_[:, 1:])):
        z = np.where(full, top, 0.0)
        ok = full[a] & full[b] & (np.abs(z[a] - z[b]) <= step)
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    r, k = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r)), (r, k)), shape=(h * w, h * w))
    _, lab = connected_components(graph, directed=False)
    return np.where(full, lab.reshape(h, w) + 1, 0)


def _run_lengths(m: np.ndarray) -> np.ndarray:
    """Length [H, W] of the run of True cells along each row that every cell lies in."""
    out = np.zeros(m.shape, np.int64)
    for r in range(m.shape[0]):
        d = np.diff(np.concatenate([[0], m[r].astype(np.int8), [0]]))
        for i, j in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
            out[r, i:j] = j - i
    return out


def _straight(piece: np.ndarray, full: np.ndarray) -> np.ndarray:
    """Pieces that fill less than BOX_FILL of their box (an L or a U of counters along the
    walls) cut into straight runs: each cell goes with the longer of its runs along x and
    along y (the align stage turned the walls onto x and y), each side's 4-connected parts a
    piece."""
    out = piece.copy()
    for i in np.unique(piece[full]):
        m = piece == i
        sl = ndi.find_objects(m.astype(np.int32))[0]
        mm = m[sl]
        if mm.mean() >= BOX_FILL:
            continue
        along_x = _run_lengths(mm) >= _run_lengths(mm.T).T
        lab_x, kx = ndi.label(mm & along_x)
        lab_y, _ = ndi.label(mm & ~along_x)
        part = np.where(lab_y > 0, lab_y + kx, lab_x)  # [h, w] 1.., 0 outside the piece
        size = np.bincount(part.reshape(-1))
        size[0] = 0
        # a part under CUT_SHARE of the piece is its ragged edge, not a run: it goes back to
        # the part it borders most
        while ((size > 0) & (size < CUT_SHARE * mm.sum())).any():
            j = int(np.flatnonzero((size > 0) & (size < CUT_SHARE * mm.sum()))[0])
            if (size > 0).sum() == 1:
                break
            m_j = part == j
            near = part[ndi.binary_dilation(m_j, np.ones((3, 3), bool)) & ~m_j & (part > 0)]
            into = int(np.bincount(near).argmax()) if len(near) else int(np.argmax(size))
            part[m_j] = into
            size[into] += size[j]
            size[j] = 0
        sub = out[sl]
        nxt = out.max() + 1
        sub[part > 0] = part[part > 0] + nxt
    return out


def _merged(
    piece: np.ndarray, full: np.ndarray, r: int, low: np.ndarray, stands_below: float
) -> np.ndarray:
    """Pieces a disk of radius r cells does not fit in, or whose lowest triangle (low [H, W])
    lies above stands_below, joined to a neighbour (module doc)."""
    disk = np.hypot(*np.mgrid[-r : r + 1, -r : r + 1]) <= r
    ring = np.ones((3, 3), bool)

    def is_thin(i: int) -> bool:
        m = piece == i
        return low[m].min() > stands_below or not ndi.binary_erosion(np.pad(m, r), disk).any()

    ids, counts = np.unique(piece[full], return_counts=True)
    size = dict(zip(ids.tolist(), counts.tolist(), strict=True))
    thin = {i for i in size if is_thin(i)}
    while thin and len(size) > 1:
        i = min(thin, key=lambda k: (size[k], k))
        thin.discard(i)
        m = piece == i
        near = piece[ndi.binary_dilation(m, ring) & ~m & full]
        if len(near):
            into = int(np.bincount(near).argmax())
        else:
            into = max((k for k in size if k != i), key=lambda k: (size[k], -k))
        piece[m] = into
        size[into] += size.pop(i)
        if into in thin and not is_thin(into):
            thin.discard(into)
    return piece

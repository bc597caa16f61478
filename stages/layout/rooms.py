"""Rooms of a home: the inside region split where it narrows to a door, and the rooms each
opening joins.

The split is the distance-transform segmentation of Bormann et al. (ICRA 2016): the distance
of each inside cell to the nearest cell outside (wall, unknown) has one regional maximum per
room (h-maxima: a maximum standing less than `h` over the saddle to a higher one is that
one's); a watershed of the negated distance from those markers grows the rooms until they
meet, at the narrowest point between them. Neighbours whose shared boundary is wider than a
door are one room (an L's two arms, a room's bay) unless it is a gap in a partition, a wall
stub running on from it with a room on either side (a passage flush with a corner); a basin
smaller than a room joins the neighbour it shares most boundary with. Each cut between two
rooms is then drawn straight along the room's axes, and the outlines traced round the rooms
never overlap (disjoint). The wall lines closed over doorways (extract.py) separate most
rooms already; this splits those whose doorway has no wall run beside it to close it (a door
flush with the corner, a wall the views saw only in pieces).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from shapely import contains_xy
from shapely.geometry import Point, Polygon
from shapely.geometry.polygon import orient
from skimage.morphology import h_maxima
from skimage.segmentation import watershed

from stages.common.rows import unique_rows
from stages.layout.extract import Frame

MIN_PIECE = 0.5  # metres: a wall splits into seen and inferred pieces no shorter than this
SEEN_GAP = 0.2  # metres: unseen stretches of a seen wall up to this long are seen (a socket,
#                 a picture frame the views saw as no wall)
OTHER_SIDE = 0.15  # metres beyond a wall's back where the room an opening leads to is looked for


def _boundaries(lab: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """(i, j) with i < j -> the cells [K, 2] (row, col) of label i or j next to the other
    label (4-neighbours)."""
    keys, cells = [], []
    for axis in (0, 1):
        a = lab[:-1] if axis == 0 else lab[:, :-1]
        b = lab[1:] if axis == 0 else lab[:, 1:]
        rows, cols = np.nonzero((a != b) & (a > 0) & (b > 0))
        i, j = a[rows, cols], b[rows, cols]
        key = np.minimum(i, j).astype(np.int64) * (lab.max() + 1) + np.maximum(i, j)
        step = (1, 0) if axis == 0 else (0, 1)
        keys += [key, key]
        cells += [np.stack([rows, cols], 1), np.stack([rows + step[0], cols + step[1]], 1)]
    key, rc = np.concatenate(keys), np.concatenate(cells)
    if len(key) == 0:
        return {}
    order = np.argsort(key, kind="stable")
    key, rc = key[order], rc[order]
    uniq, first = np.unique(key, return_index=True)
    m = lab.max() + 1
    return {
        (int(k // m), int(k % m)): unique_rows(part)[0]
        for k, part in zip(uniq, np.split(rc, first[1:]), strict=True)
    }


def _width(cells: np.ndarray) -> float:
    """The length (cells) of a boundary: the extent of its cells along their main axis."""
    if len(cells) < 2:
        return float(len(cells))
    c = cells - cells.mean(0)
    u = np.linalg.svd(c, full_matrices=False)[2][0]
    t = c @ u
    return float(t.max() - t.min() + 1)


def _straighten(lab: np.ndarray, i: int, j: int, rc: np.ndarray) -> None:
    """The boundary between labels i and j (its cells rc [K, 2]) made one straight cut along
    the longer side of its box, in place: within the box, the cells of i and j on one side of
    a row (a column, for a box taller than wide) take one label and the rest the other, at
    the row and with the sides that relabel the fewest cells. The watershed line between two
    rooms wanders off the door's line where the narrowing is uneven (a door flush with a
    corner, ragged jambs, a partition seen in pieces); left so, the outlines keep a slanted
    edge there and the rooms a wedge of each other's floor."""
    (r0, c0), (r1, c1) = rc.min(0), rc.max(0)
    sub = lab[r0 : r1 + 1, c0 : c1 + 1]
    view = sub if c1 - c0 >= r1 - r0 else sub.T  # rows across the cut
    k, up, down = _cut_row(view, i, j)
    both = (view == i) | (view == j)
    above = np.arange(view.shape[0])[:, None] < k
    view[both & above] = up
    view[both & ~above] = down


def _cut_row(view: np.ndarray, i: int, j: int) -> tuple[int, int, int]:
    """(k, up, down): rows of `view` before k go to label up, the rest to down, with the
    fewest cells of i and j relabelled."""
    a = np.concatenate([[0], np.cumsum((view == i).sum(1))])
    b = np.concatenate([[0], np.cumsum((view == j).sum(1))])
    i_first = b + (a[-1] - a)  # cells moved with i above row k and j from it on
    j_first = a + (b[-1] - b)
    if i_first.min() <= j_first.min():
        return int(np.argmin(i_first)), i, j
    return int(np.argmin(j_first)), j, i


def _partition(
    lab: np.ndarray, i: int, j: int, rc: np.ndarray, wall: np.ndarray, cell: float, run: float
) -> bool:
    """Whether the boundary between labels i and j (cells rc) is a passage in a partition:
    the straight cut across it (as _straighten draws it) runs on at one end into a wall at
    least `run` metres long with i on one side and j on the other (a stub of the wall between
    the rooms), and meets a wall right at its other end (the stub's other half, or the wall
    the partition runs into at a corner). An L's arms meet across a line that runs into the
    outer wall at one end and along one arm's outer face, the other room on neither side of
    it, at the other: no partition."""
    (r0, c0), (r1, c1) = rc.min(0), rc.max(0)
    if c1 - c0 < r1 - r0:  # a cut down a column: the same on the transposed plan
        lab, wall, rc = lab.T, wall.T, rc[:, ::-1]
        (r0, c0), (r1, c1) = rc.min(0), rc.max(0)
    k, up, down = _cut_row(lab[r0 : r1 + 1, c0 : c1 + 1], i, j)
    cut = r0 + k  # between rows cut - 1 and cut
    b = max(2, int(round(0.15 / cell)))  # the wall's band round the line
    far = max(2, int(round(0.5 / cell)))  # the rooms looked for this far beside it
    n = max(2, int(round(run / cell)))
    rows = slice(max(cut - b, 0), cut + b)

    def stub(cols: np.ndarray) -> bool:
        cols = cols[(cols >= 0) & (cols < lab.shape[1])]
        if len(cols) < n or wall[rows, cols].any(0).mean() < 0.9:
            return False
        above = lab[max(cut - b - far, 0) : max(cut - b, 0), cols]
        below = lab[cut + b : cut + b + far, cols]
        return bool((above == up).any(0).mean() >= 0.5 and (below == down).any(0).mean() >= 0.5)

    def walled(cols: np.ndarray) -> bool:
        cols = cols[(cols >= 0) & (cols < lab.shape[1])]
        return len(cols) > 0 and bool(wall[rows, cols].any(0).all())

    right, left = np.arange(c1 + 1, c1 + 1 + n), np.arange(c0 - 1, c0 - 1 - n, -1)
    return (stub(right) and walled(left[:2])) or (stub(left) and walled(right[:2]))


def split(
    inside: np.ndarray,
    cell: float,
    h: float,
    door: float,
    min_area: float,
    wall: np.ndarray | None = None,
    run: float = 0.3,
) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """Rooms of the inside cells [H, W] bool: a label per cell (0 outside, 1..n) and the cuts
    between rooms (label i, label j, the cells [K, 2] along the cut). `h` (metres): the least
    height of a room's distance maximum over its saddle; `door` (metres): neighbours sharing a
    wider boundary are one room, unless it is a passage in a partition (`wall` [H, W] bool
    given: _partition, stubs at least `run` metres); `min_area` (m²): a smaller basin is no
    room of its own."""
    pieces, n = ndi.label(inside)
    if h <= 0 or n == 0:
        return pieces, []
    # unseen holes inside a room (under a table) are no obstacle for the distance
    dist = ndi.distance_transform_edt(np.pad(ndi.binary_fill_holes(inside), 1))[1:-1, 1:-1]
    dist = np.where(inside, dist * cell, 0.0)
    peaks = h_maxima(dist, h)
    markers, _ = ndi.label(peaks & inside)
    # a piece without a marker of its own (narrower than 2 h everywhere) keeps one
    missing = np.setdiff1d(np.arange(1, n + 1), np.unique(pieces[markers > 0]))
    start = markers.max()
    for k, p in enumerate(missing, start=1):
        markers[pieces == p] = start + k
    lab = watershed(-dist, markers, mask=inside)
    area = np.bincount(lab.ravel(), minlength=lab.max() + 1) * cell**2
    # merge: wide boundaries first, then basins too small for a room into their best neighbour
    while True:
        bounds = _boundaries(lab)
        widths = {k: _width(v) * cell for k, v in bounds.items()}
        wide = [
            k
            for k, w in widths.items()
            if w > door and (wall is None or not _partition(lab, *k, bounds[k], wall, cell, run))
        ]
        small = [k for k in widths if min(area[k[0]], area[k[1]]) < min_area and k not in wide]
        if wide:
            i, j = max(wide, key=lambda k: widths[k])
        elif small:
            i, j = max(small, key=lambda k: widths[k])
        else:
            break
        lab[lab == j] = i
        area[i] += area[j]
        area[j] = 0
    for (i, j), rc in _boundaries(lab).items():
        _straighten(lab, i, j, rc)
    # labels 1..n in the order of their first cell
    ids = np.unique(lab[lab > 0])
    remap = np.zeros(lab.max() + 1, np.int64)
    remap[ids] = np.arange(1, len(ids) + 1)
    lab = remap[lab]
    cuts = [(i, j, c) for (i, j), c in _boundaries(lab).items()]
    return lab.astype(np.int32), cuts


def join_rooms(plan: dict) -> dict:
    """The plan with each opening's `rooms`: the indices of the rooms it joins, [i, j] with
    i < j between two rooms, [i] for one to the outside (or to space no room covers): its
    wall's room, and the room that holds the point OTHER_SIDE beyond the wall's back at the
    opening's middle."""
    polys = [Polygon(r["polygon"]) for r in plan["rooms"]]
    walls = plan["walls"]
    out = []
    for o in plan.get("openings", []):
        w = walls[o["wall"]] if 0 <= o.get("wall", -1) < len(walls) else None
        if w is None:
            out.append(o)
            continue
        a, b = np.asarray(w["start"], np.float64), np.asarray(w["end"], np.float64)
        d = (b - a) / max(float(np.linalg.norm(b - a)), 1e-9)
        n = np.array([d[1], -d[0]])  # outwards of the wall's room
        mid = (np.asarray(o["start"], np.float64) + np.asarray(o["end"], np.float64)) / 2
        p = Point(*(mid + n * (float(w["thickness"]) + OTHER_SIDE)))
        here = int(w["room"])
        other = [k for k, q in enumerate(polys) if k != here and q.buffer(0.05).contains(p)]
        out.append({**o, "rooms": sorted({here, *other[:1]})})
    return {**plan, "openings": out}


def cut_openings(
    fr: Frame, cuts: list, room_of: dict[int, int], faces: list, walls: list[dict], door_max: float
) -> list[dict]:
    """An opening for each cut between two rooms (split's cuts; room_of: region label -> room
    index): on the face of the first room that runs along the cut nearest its middle, from the
    cut's first to its last cell along that face."""
    cell = fr.grid.cell
    out = []
    for i, j, rc in cuts:
        if i not in room_of or j not in room_of:
            continue
        xy = fr.xy(rc)
        mid = xy.mean(0)
        best = None
        for wi, (ri, a, b) in enumerate(faces):
            if ri != room_of[i]:
                continue
            length = float(np.linalg.norm(b - a))
            d = (b - a) / length
            t = (xy - a) @ d
            off = abs(float((mid - a) @ np.array([d[1], -d[0]])))
            spread = float(t.max() - t.min())  # a cut runs along the face it crosses
            if t.min() > -cell and t.max() < length + cell and (best is None or off < best[0]):
                best = (off, wi, a, d, t, spread)
        if best is None or best[0] > walls[best[1]]["thickness"] + 2 * cell:
            continue
        _, wi, a, d, t, _ = best
        t0, t1 = float(t.min() - cell / 2), float(t.max() + cell / 2)
        p, q = fr.to_world(np.array([a + t0 * d, a + t1 * d]))
        width = t1 - t0
        out.append(
            {
                "kind": "door" if width <= door_max else "passage",
                "wall": wi,
                "start": np.round(p, 4).tolist(),
                "end": np.round(q, 4).tolist(),
                "width": round(width, 4),
            }
        )
    return out


def seen_pieces(along: np.ndarray, cell: float) -> list[list]:
    """The pieces of a wall along its face from where it was seen (`along`: bool per cell,
    plan.py's _seen_along): [[start, end (fractions of its length), seen], ...]. Gaps up to
    SEEN_GAP in either are closed; a piece shorter than MIN_PIECE joins its neighbours. One
    piece: the wall is not split."""
    if len(along) == 0:
        return []
    g = max(1, int(round(SEEN_GAP / cell)))
    pad = np.pad(along, g, mode="edge")
    smooth = ndi.binary_opening(ndi.binary_closing(pad, np.ones(g, bool)), np.ones(g, bool))
    smooth = smooth[g:-g]
    # runs of equal values: [start, stop, value]
    edges = np.nonzero(np.diff(smooth.astype(np.int8)))[0] + 1
    bounds = np.concatenate([[0], edges, [len(smooth)]])
    runs = [[int(a), int(b), bool(smooth[a])] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    least = MIN_PIECE / cell
    while len(runs) > 1:
        k = min(range(len(runs)), key=lambda i: runs[i][1] - runs[i][0])
        if runs[k][1] - runs[k][0] >= least:
            break
        # the short run takes its neighbours' value, and they join round it
        lo, hi = max(0, k - 1), min(len(runs), k + 2)
        value = runs[k - 1][2] if k > 0 else runs[k + 1][2]
        runs[lo:hi] = [[runs[lo][0], runs[hi - 1][1], value]]
    n = len(along)
    return [[round(a / n, 4), round(b / n, 4), v] for a, b, v in runs] if len(runs) > 1 else []


def split_seen(plan: dict) -> dict:
    """The plan with each wall that carries `pieces` (seen_pieces) split into its pieces along
    its length, each with its own `seen`; openings on it move to the piece that holds their
    middle; a room with an inferred piece continues beyond it."""
    walls: list[dict] = []
    index: list[list] = []  # index[w] = [(new index, start fraction, end fraction), ...]
    for w in plan["walls"]:
        pieces = w.get("pieces")
        w = {k: v for k, v in w.items() if k != "pieces"}
        if not pieces:
            index.append([(len(walls), 0.0, 1.0)])
            walls.append(w)
            continue
        a, b = np.asarray(w["start"], np.float64), np.asarray(w["end"], np.float64)
        mine = []
        for f0, f1, seen in pieces:
            p, q = a + f0 * (b - a), a + f1 * (b - a)
            mine.append((len(walls), f0, f1))
            walls.append(
                {
                    **w,
                    "start": np.round(p, 4).tolist(),
                    "end": np.round(q, 4).tolist(),
                    "length": round(float(np.linalg.norm(q - p)), 4),
                    "seen": bool(seen),
                }
            )
        index.append(mine)
    openings = []
    for o in plan.get("openings", []):
        wi = o.get("wall", -1)
        if not 0 <= wi < len(index) or len(index[wi]) == 1:
            openings.append({**o, "wall": index[wi][0][0]} if 0 <= wi < len(index) else o)
            continue
        w = plan["walls"][wi]
        a, b = np.asarray(w["start"], np.float64), np.asarray(w["end"], np.float64)
        mid = (np.asarray(o["start"], np.float64) + np.asarray(o["end"], np.float64)) / 2
        f = float((mid - a) @ (b - a) / max(float((b - a) @ (b - a)), 1e-12))
        new = next((k for k, f0, f1 in index[wi] if f0 <= f <= f1), index[wi][-1][0])
        openings.append({**o, "wall": new})
    rooms = [
        {**r, "continues": not all(w["seen"] for w in walls if w["room"] == ri)}
        if "continues" in r
        else r
        for ri, r in enumerate(plan["rooms"])
    ]
    return {**plan, "rooms": rooms, "walls": walls, "openings": openings}


def disjoint(
    polys: list[np.ndarray], labels: list[int], region: np.ndarray, fr: Frame
) -> list[np.ndarray | None]:
    """The room outlines (frame xy, counter-clockwise) made disjoint: where two overlap (the
    outline's simplification and the face offset carry a room over a cut between rooms, or
    over a wall stub that the simplification merged away), the overlap stays with the room
    whose cells (`region` == its label) fill more of it and leaves the other, whose outline
    loses it (its largest piece; None when nothing is left). The difference of two outlines
    along the frame's axes runs along them too."""
    cell = fr.grid.cell
    shapes = [Polygon(p) for p in polys]
    for a in range(len(shapes)):
        for b in range(a + 1, len(shapes)):
            if shapes[a].is_empty or shapes[b].is_empty:
                continue
            both = shapes[a].intersection(shapes[b])
            if both.area < 0.5 * cell**2:
                continue
            c = fr.grid.centers()
            inside = contains_xy(both, c[..., 0], c[..., 1])
            na = int((region[inside] == labels[a]).sum())
            nb = int((region[inside] == labels[b]).sum())
            lose, keep = (b, a) if na >= nb else (a, b)
            rest = shapes[lose].difference(shapes[keep])
            if rest.geom_type == "MultiPolygon":
                rest = max(rest.geoms, key=lambda g: g.area)
            shapes[lose] = rest if rest.geom_type == "Polygon" else Polygon()
    out: list[np.ndarray | None] = []
    for s, p in zip(shapes, polys, strict=True):
        if s.is_empty or s.area < 4 * cell**2:
            out.append(None)
        elif s.equals(Polygon(p)):
            out.append(p)
        else:
            s = orient(s.simplify(1e-6), 1.0)
            out.append(np.asarray(s.exterior.coords)[:-1])
    return out

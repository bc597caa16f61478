"""Object instances of the triangles no plane took (segment.py's step 4).

DBSCAN clusters them (Open3D `cluster_dbscan`, on voxels of objects.cluster_eps / 2); a
cluster is an object when it covers objects.min_area and stands on the floor (its lowest
point within objects.max_gap of it), is a table top whose legs no view fused (_table_top),
or rests on an object that stands (_rests_on: a plant on its stand). Each object is split
into pieces where its top steps (pieces.py).
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d

from stages.common.capture import UNKNOWN
from stages.common.classes import OBJECT
from stages.common.rows import unique_rows
from stages.semantics.config import SemanticsConfig
from stages.semantics.pieces import split_by_top
from stages.semantics.segmentation import Segmentation

log = logging.getLogger(__name__)


def _table_top(
    c: np.ndarray, n: np.ndarray, area: np.ndarray, base: float, cfg: SemanticsConfig
) -> bool:
    """Whether a cluster that does not reach the floor is a table whose legs or pedestal no
    view fused: its faces up (horizontal, facing up) cover at least table_min_top m² and a third
    its area, at a median height of at most table_max_top above the floor. A wall cabinet
    shows its front and underside; a lamp, fused noise little that faces up."""
    up = n[:, 2] > np.cos(np.radians(cfg.planes.max_tilt_deg))  # [N]
    a_up = float(area[up].sum())
    if (
        cfg.objects.table_max_top <= 0
        or a_up < cfg.objects.table_min_top
        or a_up < float(area.sum()) / 3
    ):
        return False
    return bool(np.median(c[up, 2]) - base <= cfg.objects.table_max_top)


def _rests_on(
    c: np.ndarray, members: np.ndarray, standing: list[np.ndarray], cell: float, gap: float
) -> bool:
    """Whether a cluster that does not reach the floor rests on an object that does: below
    its lowest point, within `gap` metres, lies the top of a standing object on one of the
    `cell`-metre plan cells it covers (a plant on its stand, a lamp on a desk). A wall
    cabinet hangs higher above the counter than that; a screen on a wall has no object
    under it."""
    if not standing:
        return False
    low = c[members, 2].min()
    mine = np.unique(_plan_cells(c[members], cell))
    other = np.concatenate(standing)
    p = c[other[c[other, 2] <= low + 1e-6]]  # standing surfaces below the cluster
    z = p[np.isin(_plan_cells(p, cell), mine), 2]
    return bool(len(z) and low - float(z.max()) <= gap)


def _plan_cells(p: np.ndarray, cell: float) -> np.ndarray:
    """[N] packed `cell`-metre plan cell of centres p [N, 3]."""
    ij = np.floor(p[:, :2] / cell).astype(np.int64) + (1 << 20)
    return ij[:, 0] * (1 << 21) + ij[:, 1]


def _lowest_by_cell(c: np.ndarray, ok: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(plan cells [K] sorted, the lowest triangle centre's height in each [K]) of the
    triangles `ok` (centres c [N, 3]) on `cell`-metre plan cells: computed once, read by
    every floating cluster (_stands_hidden)."""
    keys, inv = np.unique(_plan_cells(c[ok], cell), return_inverse=True)
    low = np.full(len(keys), np.inf)
    np.minimum.at(low, inv, c[ok, 2])
    return keys, low


def _stands_hidden(
    c: np.ndarray,
    members: np.ndarray,
    lowest: tuple[np.ndarray, np.ndarray],
    cell: float,
    share: float,
) -> bool:
    """Whether a cluster that does not reach the floor stands on something no view saw:
    under fewer than `share` of the plan cells it covers does the mesh hold any surface
    below its lowest point (floor, an object's top, anything; `lowest`: _lowest_by_cell). A
    plant whose pot and stem stood hidden behind a sofa shows its leaves alone; a wall
    cabinet hangs over the counter the views saw, a lamp over its table, fused noise over
    the floor."""
    low = c[members, 2].min()
    mine = np.unique(_plan_cells(c[members], cell))
    keys, lowest_z = lowest
    at = np.minimum(np.searchsorted(keys, mine), len(keys) - 1)
    under = (keys[at] == mine) & (lowest_z[at] < low - 1e-6)
    log.debug(
        "hidden stand: cluster from %.2f m, %d cells, %.2f under", low, len(mine), under.mean()
    )
    return bool(under.mean() < share)


def objects(
    seg: Segmentation,
    c: np.ndarray,
    n: np.ndarray,
    area: np.ndarray,
    ok: np.ndarray,
    cfg: SemanticsConfig,
) -> None:
    """DBSCAN the unlabelled triangles; clusters standing on the floor become instances."""
    rest = np.flatnonzero((seg.cls == UNKNOWN) & ok)
    if len(rest) == 0:
        return
    vox = cfg.objects.cluster_eps / 2.0
    keys = np.floor(c[rest] / vox).astype(np.int64)  # [N, 3]
    cells, _, inv = unique_rows(keys)  # [M, 3], [N]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector((cells + 0.5) * vox))
    lab = np.asarray(
        pc.cluster_dbscan(cfg.objects.cluster_eps, cfg.objects.cluster_min_points), np.int64
    )[inv]
    seg.noise_triangles = int((lab < 0).sum())
    # Without a floor plane, z = 0 is only the align stage's estimate, and from photos alone
    # the floor and the low fronts that reach it are often not reconstructed at all (plain
    # surfaces: no stereo): the 7-Scenes kitchen's photos-only mesh starts 0.44 m up, at the
    # counters, and every cluster "floated" into unknown. There the clusters are measured
    # from the lowest surface the mesh holds (1st percentile), so what stands lowest still
    # counts as standing and what hangs above it (wall cabinets, lamps) still does not.
    base = seg.floor_z
    if not seg.has_floor:
        base = max(base, float(np.percentile(c[rest, 2], 1)))
    seg.object_base_z = base
    found: list[tuple[float, int, np.ndarray]] = []
    floating = []

    def place(members: np.ndarray) -> None:
        if cfg.objects.piece_step <= 0:
            found.append((float(area[members].sum()), int(members.min()), members))
            return
        piece = split_by_top(
            c[members],
            cfg.objects.piece_cell,
            cfg.objects.piece_step,
            cfg.objects.piece_min_width,
            base + cfg.objects.max_gap,
        )
        for k in range(int(piece.max()) + 1):
            part = members[piece == k]
            found.append((float(area[part].sum()), int(part.min()), part))

    for k in np.unique(lab[lab >= 0]):
        members = rest[lab == k]
        a = float(area[members].sum())
        if a < cfg.objects.min_area:
            seg.noise_clusters += 1
        elif c[members, 2].min() - base > cfg.objects.max_gap and not _table_top(
            c[members], n[members], area[members], base, cfg
        ):
            floating.append(members)
        else:
            place(members)
    standing = [m for _, _, m in found]
    if floating and cfg.objects.hidden_stand > 0:
        lowest = _lowest_by_cell(c, ok, cfg.objects.cluster_eps)
    for members in floating:
        big = float(area[members].sum()) >= cfg.objects.rest_min_area
        if big and _rests_on(c, members, standing, cfg.objects.cluster_eps, cfg.objects.max_gap):
            seg.resting_clusters += 1
            place(members)
        elif (
            big
            and cfg.objects.hidden_stand > 0
            and _stands_hidden(
                c, members, lowest, cfg.objects.cluster_eps, cfg.objects.hidden_stand
            )
        ):
            seg.hidden_stand_clusters += 1
            place(members)
        else:
            seg.floating_clusters += 1
    found.sort(key=lambda x: (-x[0], x[1]))  # by area, then position in the mesh: deterministic
    for i, (_, _, members) in enumerate(found, start=1):
        seg.cls[members] = OBJECT
        seg.instance[members] = i

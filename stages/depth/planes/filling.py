"""The plane fill over a capture's views: hypotheses, each view labelled, merged and
checked against the others (the method: stages/depth/planes/__init__.py)."""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from stages.common.camera import depth_to_points
from stages.common.classes import CEILING_NAME
from stages.common.errors import BlunfError
from stages.common.progress import track
from stages.common.threads import side_by_side, torch_threads
from stages.depth.consistency import consistent_depth
from stages.depth.planes.appearance import plane_colours
from stages.depth.planes.bases import feet_finder
from stages.depth.planes.config import PlanesConfig
from stages.depth.planes.hypotheses import KINDS, Plane, find_planes, view_points
from stages.depth.planes.label import label_view
from stages.depth.planes.merge import Merged, merge_view
from stages.depth.planes.prepare import at_size, neighbours, view_data

__all__ = ["fill"]
log = logging.getLogger(__name__)

# the fewest views a sample (sample_every) is checked on: fewer leave each fill too few views
# to agree with (a 12-view procedural room's sample of 4 dropped 69 % of its fills, all 12
# views 17 %)
SAMPLE_VIEWS = 10


def fill(
    images: list[np.ndarray],
    Ks: list[np.ndarray],
    poses: list[np.ndarray],
    sparse: list[np.ndarray],
    depths: list[np.ndarray],
    cfg: PlanesConfig,
    threads: int = 0,
) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    """images: list of HxWx3 float32 in 0..1 (full size); Ks: 3x3 intrinsics at full size;
    poses: 4x4 camera-to-world, OpenCV axes, in the aligned world (metres, z up, floor z=0,
    walls along x and y as far as the align stage made them); sparse: full-size HxW float32
    SfM track z-depth (0 = none); depths: the sweep's checked z-depth maps (h x w, possibly
    smaller than the images: scale K by w/W), 0 = none.
    Returns (depths, sources, facts): the depth maps at the same h x w with plane depth filled
    where a plane wins and wrong stereo dropped, sources uint8 h x w (0 none, 1 stereo, 2 planes),
    and facts for report.json (CPU-s, coverage before/after by plane kind, share of fills the
    multi-view check dropped, the planes found with kind/normal/offset/support). Where the
    check drops more than cfg.max_dropped of the fills (on a sample of the views first:
    cfg.sample_every), with cfg.undo "plane" the planes it drops that much of are taken out of
    every view's fill and the rest checked again (facts "planes_undone"); where it still does
    (or "all"), the maps come back as they came, facts "ran" false with the "reason".
    threads: views labelled side by side, one per torch thread (0: the caller's count, the
    stage's); the labels do not depend on it."""
    n = len(images)
    if not n == len(Ks) == len(poses) == len(sparse) == len(depths):
        raise BlunfError("depth.planes: images, intrinsics, poses, sparse and depth maps differ")
    cpu0, t0 = time.process_time(), time.perf_counter()
    depths = [np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32) for d in depths]
    before = _coverage(depths)
    if not cfg.enabled or n == 0:
        src = [(d > 0).astype(np.uint8) for d in depths]
        return depths, src, {"enabled": False, "coverage_before": before}
    views = view_data(images, Ks, poses, depths, cfg, sparse)
    pts, nrm, col = [], [], []
    for v in views:
        p, q, c = view_points(v.depth_full, v.K_full, v.pose, rgb=at_size(v.rgb, v.depth_full))
        pts += [p]
        nrm += [q]
        col += [c]
    for s, K, pose, img in zip(sparse, Ks, poses, images, strict=True):
        s = np.asarray(s, np.float64)
        p, _ = depth_to_points(s, np.asarray(K, np.float64), pose)
        pts += [p]
        nrm += [np.zeros_like(p)]
        col += [np.asarray(img, np.float64)[s > 0]]
    allp, alln, allc = np.concatenate(pts), np.concatenate(nrm), np.concatenate(col)
    feet = feet_finder(views, cfg) if cfg.wall_feet else None
    planes = find_planes(allp, alln, cfg, feet)
    hists = plane_colours(planes, allp, allc, cfg.band, alln, cfg.normal_cos)
    ceil = [p.offset for p in planes if p.kind == CEILING_NAME]
    ceiling = ceil[0] if ceil else None
    order = neighbours(views, cfg.neighbours)

    def one(i: int) -> Merged:
        lab = label_view(views[i], planes, [views[j] for j in order[i]], cfg, ceiling, hists)
        return merge_view(lab, views[i].depth_full, views[i].K_full, views[i].pose, planes, cfg)

    got: dict[int, Merged] = {}

    def label(idx: list[int], what: str) -> None:
        with torch_threads(threads):
            got.update(zip(idx, track(side_by_side(one, idx), what, len(idx), "view"), strict=True))

    # every `sample_every`-th view first, checked among themselves: a room whose views
    # disagree on its planes is told from them, and the rest is not labelled for nothing
    # (each view's labels depend on its own and its neighbours' readings alone, so the
    # sample's labels are the full run's)
    k = cfg.sample_every
    sample = list(range(0, n, k)) if k > 1 and len(range(0, n, k)) >= SAMPLE_VIEWS else []
    undone: list[dict] = []  # the planes taken out, with what the check dropped of them
    if sample:
        label(sample, "plane fill (sample)")
        part, _, _, facts, undone = _checked(
            [got[i] for i in sample],
            [views[i] for i in sample],
            [depths[i] for i in sample],
            planes,
            before,
            cfg,
            "sample",
        )
        got.update(zip(sample, part, strict=True))
        if facts["fills_dropped_by_check"] > cfg.max_dropped or not _any_fill(part, undone):
            facts["sample"] = {"every": k, "views": len(sample)}
            of = f"the fills of one view in {k} ({len(sample)} views)"
            return _undone(depths, facts, cfg, of, cpu0, t0)
    label([i for i in range(n) if i not in got], "plane fill")
    merged = [got[i] for i in range(n)]
    if undone:  # the sample's verdict holds for the views labelled after it
        merged = [_without(m, {u["plane"] for u in undone}) for m in merged]
    merged, out, src, facts, more = _checked(merged, views, depths, planes, before, cfg, "all")
    undone += more
    facts["planes_undone"] = undone
    facts["cpu_seconds"] = round(time.process_time() - cpu0, 2)
    facts["seconds"] = round(time.perf_counter() - t0, 2)
    log.info(
        "depth/planes: %d planes, coverage %.1f %% -> %.1f %% (%.1f %% of fills dropped by the "
        "multi-view check) in %.0f CPU-s",
        len(planes),
        100 * before,
        100 * facts["coverage_after"],
        100 * facts["fills_dropped_by_check"],
        facts["cpu_seconds"],
    )
    if facts["fills_dropped_by_check"] > cfg.max_dropped or not _any_fill(merged, undone):
        return _undone(depths, facts, cfg, "its fills", cpu0, t0)
    return out, src, facts


def _checked(
    merged: list[Merged],
    views: list,
    depths: list[np.ndarray],
    planes: list[Plane],
    before: float,
    cfg: PlanesConfig,
    views_of: str,
) -> tuple[list[Merged], list[np.ndarray], list[np.ndarray], dict, list[dict]]:
    """The views' fills through the multi-view check: (merged, out, src, facts, planes
    undone). Over cfg.max_dropped with cfg.undo "plane", the planes over it are taken out
    first (_undo_planes; `views_of` names the views counted)."""
    out, src, chk = _check(merged, views, cfg)
    facts = _facts(depths, out, src, merged, chk, planes, before)
    undone: list[dict] = []
    if facts["fills_dropped_by_check"] > cfg.max_dropped and cfg.undo == "plane":
        (merged, out, src, chk), undone = _undo_planes(
            merged, (out, src, chk), views, planes, cfg, views_of
        )
        facts = _facts(depths, out, src, merged, chk, planes, before)
    facts["planes_undone"] = undone
    return merged, out, src, facts, undone


def _plane_drops(merged: list[Merged], checked: list[np.ndarray], n_planes: int) -> np.ndarray:
    """[n_planes, 2] int64: per plane, the pixels it filled before the multi-view check and
    those the check kept."""
    got = np.zeros((n_planes, 2), np.int64)
    for m, c in zip(merged, checked, strict=True):
        filled = (m.fill > 0) & (m.plane >= 0)
        got[:, 0] += np.bincount(m.plane[filled], minlength=n_planes)[:n_planes]
        kept = filled & (c > 0)
        got[:, 1] += np.bincount(m.plane[kept], minlength=n_planes)[:n_planes]
    return got


def _undo_planes(
    merged: list[Merged],
    checked: tuple,
    views: list,
    planes: list[Plane],
    cfg: PlanesConfig,
    views_of: str,
) -> tuple[tuple, list[dict]]:
    """(merged, out, src, checked) with the fills of every plane the check dropped over
    cfg.max_dropped of taken out and the rest checked again (the other views' maps it is
    checked against lose those fills too), and those planes [{plane, kind, offset, fills,
    dropped, views}] (`views_of`: which views were counted, "sample" or "all"); as given when
    no plane is over."""
    counts = _plane_drops(merged, checked[2], len(planes))
    share = 1.0 - counts[:, 1] / np.maximum(counts[:, 0], 1)
    bad = [k for k in range(len(planes)) if counts[k, 0] > 0 and share[k] > cfg.max_dropped]
    if not bad:
        return (merged, *checked), []
    undone = [
        {
            "plane": k,
            "kind": planes[k].kind,
            "offset": round(float(planes[k].offset), 3),
            "fills": int(counts[k, 0]),
            "dropped": round(float(share[k]), 4),
            "views": views_of,
        }
        for k in bad
    ]
    log.info(
        "depth/planes: %d of %d planes give no fill: the check dropped over %.0f %% of their "
        "%d fills (%.0f %% of all)",
        len(bad),
        len(planes),
        100 * cfg.max_dropped,
        int(counts[bad, 0].sum()),
        100 * counts[bad, 0].sum() / max(1, int(counts[:, 0].sum())),
    )
    merged = [_without(m, set(bad)) for m in merged]
    return (merged, *_check(merged, views, cfg)), undone


def _without(m: Merged, planes: set[int]) -> Merged:
    """m with the fills of `planes` taken out (its kept readings stay)."""
    drop = np.isin(m.plane, sorted(planes)) & (m.fill > 0)
    return replace(
        m,
        fill=np.where(drop, 0, m.fill).astype(m.fill.dtype),
        plane=np.where(drop, -1, m.plane).astype(m.plane.dtype),
    )


def _any_fill(merged: list[Merged], undone: list[dict]) -> bool:
    """Whether any fill is left (no plane was undone, or some plane still fills)."""
    return not undone or any((m.fill > 0).any() for m in merged)


def _undone(
    depths: list[np.ndarray], facts: dict, cfg: PlanesConfig, of: str, cpu0: float, t0: float
) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    """The maps as the sweep left them, and the fill's facts saying why (`of`: what the
    share dropped is of): the views disagree on which plane their blank regions lie on, so
    the fills that pass the check are not to be trusted either."""
    reason = (
        f"no plane fill: the multi-view check dropped {100 * facts['fills_dropped_by_check']:.0f}"
        f" % of {of}, over depth.planes.max_dropped {100 * cfg.max_dropped:.0f} % (the views "
        "disagree on the room's planes)"
    )
    if facts.get("planes_undone") and facts["fills_dropped_by_check"] <= cfg.max_dropped:
        where = "" if of == "its fills" else f" ({of})"
        reason = (
            f"no plane fill: the multi-view check dropped over depth.planes.max_dropped "
            f"{100 * cfg.max_dropped:.0f} % of each plane's fills{where} (the views disagree "
            "on the room's planes)"
        )
    facts.update(ran=False, reason=reason, coverage_planes=0.0)
    facts["coverage_after"] = facts["coverage_before"]
    facts["cpu_seconds"] = round(time.process_time() - cpu0, 2)
    facts["seconds"] = round(time.perf_counter() - t0, 2)
    log.info("depth/planes: %s", reason)
    return depths, [(d > 0).astype(np.uint8) for d in depths], facts


def _check(
    merged: list[Merged], views: list, cfg: PlanesConfig
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Each view's fills kept where other views' merged maps agree (multi-view check)."""
    full = [np.where(m.kept > 0, m.kept, m.fill) for m in merged]
    Ks = [v.K_full for v in views]
    poses = [v.pose for v in views]
    out, src, checked = [], [], []
    for i, m in enumerate(merged):
        others = [j for j in range(len(merged)) if j != i]
        f = m.fill
        if others and (f > 0).any():
            refs = ([full[j] for j in others], [Ks[j] for j in others], [poses[j] for j in others])
            (f,), _ = consistent_depth(
                [m.fill],
                [Ks[i]],
                [poses[i]],
                cfg.check_tol,
                cfg.check_agree,
                cfg.check_through,
                cfg.check_views,
                refs=refs,
            )
        elif not others:
            f = np.zeros_like(m.fill)
        d = np.where(m.kept > 0, m.kept, f).astype(np.float32)
        s = np.where(m.kept > 0, 1, np.where(f > 0, 2, 0)).astype(np.uint8)
        out.append(d)
        src.append(s)
        checked.append(f)
    return out, src, checked


def _coverage(maps: list[np.ndarray]) -> float:
    total = sum(m.size for m in maps)
    return float(sum(int((m > 0).sum()) for m in maps) / max(1, total))


def _facts(
    depths: list[np.ndarray],
    out: list[np.ndarray],
    src: list[np.ndarray],
    merged: list[Merged],
    checked: list[np.ndarray],
    planes: list[Plane],
    before: float,
) -> dict:
    total = max(1, sum(d.size for d in depths))
    filled = sum(int((m.fill > 0).sum()) for m in merged)
    kept = sum(int((c > 0).sum()) for c in checked)
    by_kind = {k: 0 for k in KINDS}
    region = {k: np.zeros(3, np.int64) for k in KINDS}  # pixels, with depth before, after
    for k, n in enumerate(_plane_drops(merged, checked, len(planes))[:, 1]):
        by_kind[planes[k].kind] += int(n)
    for m, d, o in zip(merged, depths, out, strict=True):
        for k, p in enumerate(planes):
            r = m.region == k
            region[p.kind] += [int(r.sum()), int((r & (d > 0)).sum()), int((r & (o > 0)).sum())]
    readings = max(1, sum(int((d > 0).sum()) for d in depths))
    return {
        "enabled": True,
        "ran": True,  # False: the fill was undone (max_dropped), the maps are the sweep's
        "coverage_before": round(before, 4),
        "coverage_after": round(_coverage(out), 4),
        "coverage_planes": round(sum(int((s == 2).sum()) for s in src) / total, 4),
        "coverage_by_kind": {k: round(v / total, 4) for k, v in by_kind.items()},
        "regions_by_kind": {  # share of the pixels in regions of each kind, and their coverage
            k: {
                "pixels": round(int(v[0]) / total, 4),
                "before": round(int(v[1]) / max(1, int(v[0])), 4),
                "after": round(int(v[2]) / max(1, int(v[0])), 4),
            }
            for k, v in region.items()
        },
        "fills_dropped_by_check": round(1 - kept / filled, 4) if filled else 0.0,
        "stereo_dropped": round(sum(m.dropped for m in merged) / readings, 4),
        "stereo_snapped": round(sum(m.snapped for m in merged) / readings, 4),
        "planes": [p.to_json() for p in planes],
    }

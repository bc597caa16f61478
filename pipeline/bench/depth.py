"""The photos-only run's depth maps against the sensor's depth of the same views.

For each view the depth stage wrote (`depth/<stem>.npy`, 0 = no reading), every pixel is
read against the sensor depth at that pixel's centre (the same view: no pose enters, only
the photos-only run's metric scale, which the SfM-pose similarity to the sensor-depth run
corrects):
  coverage     percent of the view's pixels with a reading,
  within_5cm   percent of the readings with a sensor reading that lie within 5 cm of it,
  within_3cm   the same within 3 cm,
  absrel       mean |depth - sensor| / sensor over those readings,
  median_ratio median of depth / sensor over them: 1 when the run's scale is right; a
               ratio that drifts with depth is the geometry's (wrong intrinsics), not noise,
pooled over all views, and again per source (`sources/<stem>.png` beside the depth maps:
1 stereo, 2 planes, 3 field; without it every reading counts as stereo; a source's coverage
is its share of all pixels) and per class of the reference run's labels (the sensor-depth
run's semantics: floor, wall, object; coverage: share of that class's pixels), per source
on each class (`source_classes`: where the plane fill is wrong, on furniture or walls), and per
sensor depth band (`bands`, metres: where the errors lie), and per plane of the plane fill
(`planes`: each plane the depth stage's report.json lists, scored on the plane-filled pixels
whose depth is that plane's along the pixel's ray, from the stage's own maps; the pixels
no plane's depth matches are counted in `planes_unmatched`). `tracks`: the SfM track depths
the depth stage started from (the align stage's frames.json), scored the same way: the
agreement of the run's own geometry with the sensor, which no depth method on those poses
and intrinsics can beat (the 7-Scenes kitchen's colour camera at its stated focal: its
tracks lie within 5 cm of the sensor no more often than its stereo does), again per class of
the reference's labels (`tracks.classes`: on the kitchen at SfM's own focal, 69 % of the
tracks on the floor, 52 % of those on the walls).
Sensor readings next to a depth edge or a hole are left out within `erode_px` pixels (the
7-Scenes Kinect's colour and depth are not registered: its edges sit a few pixels off the
colour's).

    python -m pipeline.bench.depth PHOTOS_RUN REFERENCE_RUN [--erode PX] [--scale S]
prints the metrics as JSON (pipeline.bench.real writes them into real.json and the
photos-only run's report.json under metrics.depth).
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

from pipeline.bench.runs import run_poses, stage_file
from stages.common.capture import Capture
from stages.common.classes import FLOOR_NAME, OBJECT_NAME, WALL_NAME
from stages.common.errors import BlunfError
from stages.common.gt_frame import pose_similarity
from stages.common.io import read_depth, read_json, read_label
from stages.depth.planes.geometry import plane_depth, rays
from stages.depth.planes.hypotheses import Plane

SOURCES = {1: "stereo", 2: "planes", 3: "field"}  # sources/<stem>.png codes (0: none)
CLASSES = (FLOOR_NAME, WALL_NAME, OBJECT_NAME)
NEAR_M = 0.05  # within_5cm
TIGHT_M = 0.03  # within_3cm
BANDS = (0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, float("inf"))  # metres of sensor depth
MATCH_REL = 1e-3  # a fill is a plane's where their depths agree this closely (float32 maps)
DEPTH_STAGES = ("depth", "nerf")  # the stage that writes a photos-only run's depth maps


def depth_folder(run: Path) -> Path:
    """The folder holding the run's depth maps (`depth/<stem>.npy`): the depth stage's, named
    in report.json (`depth`, or `nerf` before depth had a stage of its own)."""
    run = Path(run)
    report = run / "report.json"
    if report.is_file():
        for s in read_json(report).get("stages", []):
            if s.get("name") in DEPTH_STAGES and s.get("key"):
                folder = run / s["name"] / s["key"]
                if (folder / "depth").is_dir():
                    return folder
    found = [Path(p).parent for n in DEPTH_STAGES for p in glob.glob(str(run / n / "*" / "depth"))]
    if not found:
        raise BlunfError(f"{run}: no depth maps (no depth/ or nerf/ stage folder with depth/)")
    return max(found, key=lambda p: p.stat().st_mtime)


def _stage_file(run: Path, stage: str, name: str) -> Path:
    """run/stage/<key>/name, the newest when several keys hold it."""
    found = glob.glob(str(Path(run) / stage / "*" / name))
    if not found:
        raise BlunfError(f"{run}: no {stage}/*/{name} (not a finished run folder)")
    return Path(max(found, key=lambda p: Path(p).stat().st_mtime))


def sensor_views(ref_run: Path) -> tuple[Capture, dict[str, Path], dict[int, str]]:
    """(the reference run's sensor depth as its plan read it: the align stage's frames,
    whose depth the poses stage moved into the colour camera when SfM estimated its
    intrinsics (stages/poses/stated.py), else the ingested capture; stem -> its semantics
    label PNG; class id -> name) of a run made from sensor depth. The ingested maps lie in
    the depth camera's pixels: on the 7-Scenes kitchen (focal 585 px against the colour
    camera's ~526) 10 % off the colour's at the image's edges."""
    found = stage_file(ref_run, "align", "frames.json")
    cap = Capture.load(found or _stage_file(ref_run, "ingest", "frames.json"))
    sem = Capture.load(_stage_file(ref_run, "semantics", "frames.json"))
    labels = {f.stem: Path(f.label) for f in sem.frames if f.label is not None}
    return cap, labels, {int(k): v for k, v in sem.classes.items()}


def sensor_depth(cap: Capture, stem: str, erode_px: int = 0) -> np.ndarray:
    """The sensor's depth of one view in metres, 0 where missing or (erode_px > 0) within
    erode_px pixels of a hole or of a depth edge (neighbours more than 5 % apart)."""
    f = next(x for x in cap.frames if x.stem == stem)
    if f.depth is None:
        raise BlunfError(f"{cap.root}: frame {stem!r} has no depth map")
    d = read_depth(f.depth, cap.depth_scale, cap.depth_invalid).astype(np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    if erode_px <= 0:
        return d
    lo = ndimage.minimum_filter(np.where(d > 0, d, np.inf), size=3)
    hi = ndimage.maximum_filter(d, size=3)
    bad = (d <= 0) | (hi - lo > 0.05 * np.maximum(d, 1e-6))
    bad = ndimage.binary_dilation(bad, np.ones((3, 3), bool), iterations=int(erode_px))
    return np.where(bad, 0.0, d)


def at_centres(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """`a` [H, W] read at the pixel centres of a [h, w] map of the same view (nearest)."""
    h, w = shape
    rows = np.minimum(((np.arange(h) + 0.5) * a.shape[0] / h).astype(np.int64), a.shape[0] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * a.shape[1] / w).astype(np.int64), a.shape[1] - 1)
    return a[rows[:, None], cols[None, :]]


class _Tally:
    """Pixel counts and sums for one group (all, a source, a class)."""

    def __init__(self) -> None:
        self.pixels = self.read = self.compared = self.near = self.tight = 0
        self.rel = 0.0
        self.ratios: list[np.ndarray] = []

    def add(self, sel: np.ndarray, got: np.ndarray, ref: np.ndarray) -> None:
        """sel: the group's pixels; got: the run's depth (0 = none); ref: the sensor's."""
        has = sel & (got > 0)
        both = has & (ref > 0)
        err = np.abs(got[both] - ref[both])
        self.pixels += int(sel.sum())
        self.read += int(has.sum())
        self.compared += int(both.sum())
        self.near += int((err < NEAR_M).sum())
        self.tight += int((err < TIGHT_M).sum())
        self.rel += float((err / ref[both]).sum())
        self.ratios.append((got[both] / ref[both]).astype(np.float32))

    def result(self) -> dict:
        def pct(a: int, b: int) -> float | None:
            return round(100.0 * a / b, 2) if b else None

        return {
            "coverage": pct(self.read, self.pixels),
            "within_5cm": pct(self.near, self.compared),
            "within_3cm": pct(self.tight, self.compared),
            "absrel": round(self.rel / self.compared, 4) if self.compared else None,
            "median_ratio": (
                round(float(np.median(np.concatenate(self.ratios))), 4) if self.compared else None
            ),
            "pixels": self.pixels,
            "compared": self.compared,
        }


def photos_scale(photos_run: Path, ref_run: Path) -> float:
    """The factor that takes the photos-only run's lengths to the reference run's metres:
    the scale of the whole-pose similarity between the two runs' poses (1 when no fit)."""
    est, gt = run_poses(photos_run), run_poses(ref_run)
    common = [s for s in gt if s in est]
    m, _ = pose_similarity([est[s] for s in common], [gt[s] for s in common])
    return 1.0 if m is None else float(np.cbrt(np.linalg.det(m[:3, :3])))


def _metres(path: Path, scale: float) -> np.ndarray:
    """A depth map of the run in metres (`scale` times its lengths), 0 where missing."""
    d = np.load(path).astype(np.float64) * scale
    return np.where(np.isfinite(d) & (d > 0), d, 0.0)


def _sources(folder: Path, stem: str, used: Path, got: np.ndarray) -> np.ndarray:
    """Where each reading of `got` (the map the stage hands on) comes from, coded as
    SOURCES: the stage's sources/<stem>.png; else, when the map handed on is not the stage's
    depth/<stem>.npy (a field fill), stereo where that map has a reading and field
    elsewhere; else stereo everywhere."""
    src = folder / "sources" / f"{stem}.png"
    if src.is_file():
        code = read_label(src)
        if code.shape != got.shape:
            raise BlunfError(f"{src}: {code.shape} pixels, its depth map has {got.shape}")
        return code
    code = np.where(got > 0, 1, 0)
    stereo = folder / "depth" / f"{stem}.npy"
    if stereo.is_file() and stereo.resolve() != Path(used).resolve():
        raw = _metres(stereo, 1.0)
        if raw.shape == got.shape:
            code = np.where(got > 0, np.where(raw > 0, 1, 3), 0)
    return code


def track_maps(run: Path) -> tuple[Capture, dict[str, Path]] | None:
    """(the capture the depth stage read, stem -> its SfM track depth map) of a photos-only
    run: the align stage's frames.json that report.json names (else the newest); None when
    there is none."""
    found = stage_file(run, "align", "frames.json")
    if found is None:
        return None
    cap = Capture.load(found)
    return cap, {f.stem: Path(f.depth) for f in cap.frames if f.depth is not None}


def _bands(tally: dict, sel: np.ndarray, got: np.ndarray, ref: np.ndarray) -> None:
    """Add one view's readings to the per sensor-depth band tallies."""
    for a, b in zip(BANDS[:-1], BANDS[1:], strict=True):
        tally.setdefault(f"{a:g}-{b:g}", _Tally()).add(sel & (ref >= a) & (ref < b), got, ref)


def fill_planes(run: Path) -> list[Plane]:
    """The planes of the photos-only run's plane fill as its report.json lists them (the
    depth stage's facts.plane_fill.planes), [] when none."""
    report = Path(run) / "report.json"
    stages = read_json(report).get("stages", []) if report.is_file() else []
    for st in stages:
        if st.get("name") in DEPTH_STAGES:
            listed = (st.get("facts") or {}).get("plane_fill", {}).get("planes") or []
            return [
                Plane(
                    np.asarray(p["normal"], np.float64),
                    float(p["offset"]),
                    p["kind"],
                    np.zeros(3),
                    np.zeros(3),
                    int(p.get("support", 0)),
                )
                for p in listed
            ]
    return []


def _plane_of(planes: list[Plane], fill: np.ndarray, K: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """[h, w] index of the plane whose depth along each pixel's ray is `fill`'s there
    (relative MATCH_REL; run units, z-depth), -1 where none is or `fill` is 0."""
    out = np.full(fill.shape, -1, np.int64)
    v, u = np.nonzero(fill > 0)
    if not len(v) or not planes:
        return out
    pose = np.asarray(pose, np.float64)
    t = plane_depth(rays(np.stack([u, v], -1).astype(np.float64), K, pose), pose[:3, 3], planes)
    f = fill[v, u][None]
    miss = np.where(t > 0, np.abs(t - f) / f, np.inf)  # [P, M]
    k = np.argmin(miss, 0)
    hit = miss[k, np.arange(len(k))] <= MATCH_REL
    out[v[hit], u[hit]] = k[hit]
    return out


def depth_metrics(
    photos_run: Path, ref_run: Path, erode_px: int = 0, scale: float | None = None
) -> dict:
    """metrics.depth of the photos-only run against the sensor depth of the reference run
    (see the module doc). `scale`: photos-only lengths to metres (None: photos_scale)."""
    folder = depth_folder(photos_run)
    cap, labels, classes = sensor_views(ref_run)
    s = photos_scale(photos_run, ref_run) if scale is None else float(scale)
    stems = {f.stem for f in cap.frames}
    used = {  # the maps the stage hands on (frames.json), else its depth/ folder
        f.stem: Path(f.depth)
        for f in (
            Capture.load(folder / "frames.json").frames
            if (folder / "frames.json").is_file()
            else ()
        )
        if f.depth is not None
    }
    for p in (folder / "depth").glob("*.npy"):
        used.setdefault(p.stem, p)
    maps = sorted((k, v) for k, v in used.items() if k in stems)
    if not maps:
        raise BlunfError(f"{folder / 'depth'}: no depth map of a view of {cap.root}")
    total, by_source = _Tally(), {n: _Tally() for n in SOURCES.values()}
    by_class = {n: _Tally() for n in CLASSES}
    cross = {s: {n: _Tally() for n in CLASSES} for s in SOURCES.values()}
    bands: dict[str, _Tally] = {}
    tracks = _Tally()
    by_track_band: dict[str, _Tally] = {}
    by_track_class = {n: _Tally() for n in CLASSES}
    sfm = track_maps(photos_run)
    planes = fill_planes(photos_run)
    by_plane = [_Tally() for _ in planes]
    unmatched = 0
    views_at = {f.stem: f for f in sfm[0].frames if f.pose is not None} if sfm else {}
    per_view = {}
    has_sources = (folder / "sources").is_dir()
    for stem, path in maps:
        label = read_label(labels[stem]) if stem in labels else None  # the reference's classes
        got = _metres(path, s)  # [h, w]
        sensor = sensor_depth(cap, stem, erode_px)  # [H, W] metres, read once a view
        ref = at_centres(sensor, got.shape)
        code = _sources(folder, stem, path, got)
        everything = np.ones(got.shape, bool)
        total.add(everything, got, ref)
        _bands(bands, everything, got, ref)
        if sfm is not None and stem in sfm[1]:
            t = read_depth(sfm[1][stem], sfm[0].depth_scale, sfm[0].depth_invalid)
            t = np.where(np.isfinite(t) & (t > 0), t.astype(np.float64) * s, 0.0)
            tref = at_centres(sensor, t.shape)
            tracks.add(np.ones(t.shape, bool), t, tref)
            _bands(by_track_band, np.ones(t.shape, bool), t, tref)
            if label is not None:
                tlab = at_centres(label, t.shape)
                for cid, name in classes.items():
                    if name in by_track_class:
                        by_track_class[name].add(tlab == cid, t, tref)
        view = _Tally()
        view.add(everything, got, ref)
        per_view[stem] = view.result()
        of = {name: np.where(code == c, got, 0.0) for c, name in SOURCES.items()}  # by source
        if planes and stem in views_at and (code == 2).any():
            f = views_at[stem]
            K = f.intrinsics.scaled(got.shape[1], got.shape[0]).K
            k = _plane_of(planes, of["planes"] / s, K, np.asarray(f.pose))
            unmatched += int(((code == 2) & (got > 0) & (k < 0)).sum())
            for i in np.unique(k[k >= 0]):
                by_plane[i].add(k == i, got, ref)
        for name, g in of.items():
            by_source[name].add(everything, g, ref)
        if label is not None:
            lab = at_centres(label, got.shape)
            for cid, name in classes.items():
                if name in by_class:
                    sel = lab == cid
                    by_class[name].add(sel, got, ref)
                    for src, g in of.items():
                        cross[src][name].add(sel, g, ref)
    out = total.result()
    out["sources"] = {n: t.result() for n, t in by_source.items()}
    out["classes"] = {n: t.result() for n, t in by_class.items()}
    # each source on each class: coverage is the source's share of the class's pixels
    out["source_classes"] = {
        src: {n: t.result() for n, t in by.items()} for src, by in cross.items()
    }
    out["bands"] = {n: t.result() for n, t in bands.items() if t.compared}
    # fills: the plane-filled pixels whose depth is the plane's
    out["planes"] = [
        {
            "kind": p.kind,
            "normal": [float(x) for x in p.normal],
            "offset": p.offset,
            "support": p.support,
            **{k: v for k, v in t.result().items() if k != "coverage"},
            "fills": t.read,
        }
        for p, t in zip(planes, by_plane, strict=True)
        if t.read
    ]
    out["planes_unmatched"] = unmatched
    out["tracks"] = None
    if tracks.compared:  # coverage is not a track map's point: left out
        out["tracks"] = {k: v for k, v in tracks.result().items() if k != "coverage"}
        out["tracks"]["bands"] = {
            n: {k: v for k, v in t.result().items() if k != "coverage"}
            for n, t in by_track_band.items()
            if t.compared
        }
        out["tracks"]["classes"] = {
            n: {k: v for k, v in t.result().items() if k != "coverage"}
            for n, t in by_track_class.items()
            if t.compared
        }
    out.update(
        views=len(maps),
        sources_from="sources/"
        if has_sources
        else "the stereo maps (depth/) and the maps handed on",
        scale=s,
        erode_px=int(erode_px),
        sources_given=has_sources,
        depth_folder=str(folder),
    )
    return {**out, "per_view": per_view}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.depth", description=__doc__)
    ap.add_argument("photos_run", type=Path)
    ap.add_argument("ref_run", type=Path)
    ap.add_argument("--erode", type=int, default=0, help="pixels dropped round sensor edges")
    ap.add_argument("--scale", type=float, help="photos-only lengths to metres (default: fit)")
    a = ap.parse_args(argv)
    try:
        res = depth_metrics(a.photos_run, a.ref_run, a.erode, a.scale)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    res.pop("per_view")
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

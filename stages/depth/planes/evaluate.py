"""Offline measure of the plane fill on a photos-only run against a capture's sensor depth.

    python -m stages.depth.planes.evaluate RUN --sensor CAPTURE [--every K] [--json OUT]

RUN is a photos-only run folder (align/<key>/frames.json: aligned SfM poses, images and
track depth; depth/<key>/depth/<stem>.npy with sources/<stem>.png: the sweep's checked
depth is the readings whose source is stereo; the keys report.json names). CAPTURE holds the
same frames' sensor depth (frames/<stem>.depth.png or depth/<stem>.png, millimetres). The
run's world is metric only up to SfM's scale: one factor (median of sensor / stereo over
all stereo readings) maps it to the sensor's, and is printed. Sensor pixels near a depth
edge or a hole (`--erode` px at full size) are left out: colour and depth are not
registered on real captures. Prints coverage before and after, and per source and plane
kind the share within 5 cm and AbsRel, then each plane with what its fills measured.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from stages.common.camera import pixel_grid
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_image, read_label
from stages.depth.config import STEREO
from stages.depth.planes import PlanesConfig
from stages.depth.planes.filling import fill
from stages.depth.planes.geometry import plane_depth, rays, scale_K
from stages.depth.planes.hypotheses import KINDS, Plane


def load_run(run: Path, every: int = 1) -> tuple[list, list, list, list, list, list[str]]:
    """(images, Ks, poses, sparse, depths, stems) of a photos-only run's cached inputs: the
    sweep's checked depth (the depth stage's readings whose source is stereo)."""
    keys = {}
    report = run / "report.json"
    if report.is_file():
        keys = {
            s["name"]: s["key"]
            for s in json.loads(report.read_text()).get("stages", [])
            if s.get("key")
        }
    fr = [run / "align" / keys["align"] / "frames.json"] if "align" in keys else []
    dd = [run / "depth" / keys["depth"]] if "depth" in keys else []
    fr = [p for p in fr if p.is_file()] or sorted(run.glob("align/*/frames.json"))
    dd = [p for p in dd if (p / "depth").is_dir()] or sorted(
        p.parent for p in run.glob("depth/*/depth")
    )
    if not fr or not dd:
        raise BlunfError(f"{run}: no align/*/frames.json or depth/*/depth (a photos-only run?)")
    cap = Capture.load(fr[-1])
    frames = [f for f in cap.frames if f.pose is not None][:: max(1, every)]
    images, Ks, poses, sparse, depths, stems = [], [], [], [], [], []
    for f in frames:
        images.append(read_image(f.image).astype(np.float32) / 255.0)
        Ks.append(f.intrinsics.K)
        poses.append(np.asarray(f.pose, np.float64))
        h, w = f.intrinsics.height, f.intrinsics.width
        s = read_depth(f.depth, cap.depth_scale, cap.depth_invalid) if f.depth else None
        sparse.append(s if s is not None else np.zeros((h, w), np.float32))
        d = np.load(dd[-1] / "depth" / f"{f.stem}.npy").astype(np.float32)
        src = dd[-1] / "sources" / f"{f.stem}.png"
        if src.is_file():
            d = np.where(read_label(src) == STEREO, d, 0.0).astype(np.float32)
        depths.append(d)
        stems.append(f.stem)
    return images, Ks, poses, sparse, depths, stems


def sensor_at(path: Path, shape: tuple[int, int], erode: int) -> np.ndarray:
    """Sensor depth (m) sampled at the centres of an h x w grid; 0 near edges and holes."""
    d = read_depth(path, 1000.0, (65535,))
    r = 2 * erode + 1
    edge = (maximum_filter(d, r) - minimum_filter(d, r)) > 0.05 * np.maximum(d, 1e-6)
    d = np.where(edge | (minimum_filter(d, r) <= 0), 0.0, d)
    h, w = shape
    H, W = d.shape
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    return d[rows][:, cols]


def sensor_path(root: Path, stem: str) -> Path:
    for p in (root / "frames" / f"{stem}.depth.png", root / "depth" / f"{stem}.png"):
        if p.exists():
            return p
    raise BlunfError(f"{root}: no sensor depth for frame {stem}")


def planes_of(
    out: np.ndarray, src: np.ndarray, K: np.ndarray, pose: np.ndarray, planes: list[Plane]
) -> np.ndarray:
    """Plane index per plane-filled pixel (-1 elsewhere): the plane whose depth it holds."""
    h, w = out.shape
    which = np.full(h * w, -1, np.int64)
    idx = np.flatnonzero(src.reshape(-1) == 2)
    if len(idx) and planes:
        t = plane_depth(rays(pixel_grid(w, h).reshape(-1, 2)[idx], K, pose), pose[:3, 3], planes)
        which[idx] = np.argmin(np.abs(t - out.reshape(-1)[idx][None]), axis=0)
    return which.reshape(h, w)


def stats(pred: np.ndarray, ref: np.ndarray) -> dict:
    ok = (pred > 0) & (ref > 0)
    if not ok.any():
        return {"pixels": 0}
    err = np.abs(pred[ok] - ref[ok])
    return {
        "pixels": int(ok.sum()),
        "within_5cm": round(float((err <= 0.05).mean()), 4),
        "within_3cm": round(float((err <= 0.03).mean()), 4),
        "absrel": round(float((err / ref[ok]).mean()), 4),
        "bias": round(float(np.median((pred[ok] - ref[ok]) / ref[ok])), 4),  # median signed
    }


def evaluate(run: Path, sensor: Path, cfg: PlanesConfig, every: int, erode: int) -> dict:
    images, Ks, poses, sparse, depths, stems = load_run(run, every)
    refs = [
        sensor_at(sensor_path(sensor, s), d.shape, erode)
        for s, d in zip(stems, depths, strict=True)
    ]
    st = np.concatenate([d[(d > 0) & (r > 0)] for d, r in zip(depths, refs, strict=True)])
    se = np.concatenate([r[(d > 0) & (r > 0)] for d, r in zip(depths, refs, strict=True)])
    scale = float(np.median(se / st)) if len(st) else 1.0
    out, src, facts = fill(images, Ks, poses, sparse, depths, cfg)
    planes = [
        Plane(np.array(p["normal"]), p["offset"], p["kind"], np.zeros(3), np.zeros(3), 0)
        for p in facts["planes"]
    ]
    which = []
    for o, s, K, pose, d in zip(out, src, Ks, poses, depths, strict=True):
        kd = scale_K(K, d.shape[1] / images[0].shape[1], d.shape[0] / images[0].shape[0])
        which.append(planes_of(o, s, kd, pose, planes))
    lut = np.array([KINDS.index(p.kind) for p in planes] + [-1], np.int64)
    kinds = [lut[w] for w in which]
    # diagnostic: each view scaled by its own median ratio (what pose and scale drift cost)
    per_view = []
    for d, r in zip(depths, refs, strict=True):
        m = (d > 0) & (r > 0)
        per_view.append(float(np.median(r[m] / d[m])) if m.sum() > 20 else scale)
    cat = lambda xs: np.concatenate([x.reshape(-1) for x in xs])  # noqa: E731
    o, s, r, k, d0 = cat(out) * scale, cat(src), cat(refs), cat(kinds), cat(depths) * scale
    pl = cat(which)
    res = {
        "views": len(images),
        "scale": round(scale, 4),
        "coverage_before": facts["coverage_before"],
        "coverage_after": facts["coverage_after"],
        "fills_dropped_by_check": facts["fills_dropped_by_check"],
        "stereo_dropped": facts["stereo_dropped"],
        "cpu_s_per_view": round(facts["cpu_seconds"] / max(1, len(images)), 2),
        "stereo_before": stats(d0, r),
        "stereo_after": stats(np.where(s == 1, o, 0), r),
        "planes": stats(np.where(s == 2, o, 0), r),
        "view_scales": [round(float(np.percentile(per_view, q)), 4) for q in (5, 50, 95)],
        "stereo_view_scaled": stats(cat([x * f for x, f in zip(depths, per_view, strict=True)]), r),
        "planes_view_scaled": stats(
            cat([np.where(q == 2, x * f, 0) for x, q, f in zip(out, src, per_view, strict=True)]), r
        ),
        "all": stats(o, r),
        "kinds": {
            kn: {"coverage": round(float((k == i).mean()), 4), **stats(np.where(k == i, o, 0), r)}
            for i, kn in enumerate(KINDS)
        },
        "plane_list": facts["planes"],
        # each plane's fills (where a plane fills wrong: a front pasted over a leaning surface)
        "per_plane": [
            {
                **p,
                "coverage": round(float((pl == i).mean()), 4),
                **stats(np.where(pl == i, o, 0), r),
            }
            for i, p in enumerate(facts["planes"])
        ],
    }
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--sensor", type=Path, required=True)
    ap.add_argument("--every", type=int, default=1, help="every k-th view (tuning subset)")
    ap.add_argument("--erode", type=int, default=4, help="sensor edge margin, px at full size")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--set", nargs="*", default=[], help="PlanesConfig overrides key=value")
    a = ap.parse_args(argv)
    over: dict[str, Any] = {}  # PlanesConfig checks each value's range and choice
    for kv in a.set:
        key, val = kv.split("=", 1)
        if not hasattr(PlanesConfig(), key):
            print(f"error: --set {key}: no such setting of PlanesConfig", file=sys.stderr)
            return 1
        kind = type(getattr(PlanesConfig(), key))
        over[key] = val.lower() in ("1", "true", "yes") if kind is bool else kind(val)
    try:
        res = evaluate(a.run, a.sensor, PlanesConfig(**over), a.every, a.erode)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    short = {k: v for k, v in res.items() if k not in ("plane_list", "per_plane")}
    print(json.dumps(short, indent=1))
    for p in res["per_plane"]:
        fills = (
            f" fills {p['pixels']} px, within 5 cm {p['within_5cm']:.3f}, bias {p['bias']:+.3f}"
            if p["pixels"]
            else ""
        )
        print(
            f"  {p['kind']:8s} n={p['normal']} d={p['offset']:+.3f} support={p['support']}" + fills
        )
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The metric scale a capture's photos alone give (poses.scale_from=priors) against its truth.

    python -m pipeline.bench.scale CAPTURE --out DIR [--frames N]

SfM runs on a copy holding the colour images and intrinsics only (as `blunf run` does with
configs/phone.yaml), in SfM units; the estimator of stages/poses/scale.py is applied to the
model, and its scale is compared with the truth: the similarity between the SfM camera
centres and the capture's own poses when it has them (7-Scenes, the procedural rooms), else
the median ratio of the capture's depth to the SfM depth at the observed points (Replica).
Writes DIR/scale.json and prints one line; DIR/sfm (the model) is reused by a second call.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np  # before pycolmap

import pycolmap  # isort: skip

from pipeline.bench.real import stripped_copy
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_depth, write_json
from stages.ingest import load
from stages.poses import scale as est
from stages.poses import sfm
from stages.poses.config import PosesConfig, PosesInputs


def similarity_scale(src: np.ndarray, dst: np.ndarray) -> float:
    """Scale of the least-squares similarity taking points src [N, 3] to dst [N, 3]
    (Umeyama 1991)."""
    a, b = src - src.mean(0), dst - dst.mean(0)
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    return float((s[0] + s[1] + d * s[2]) / (a**2).sum())


def truth(cap: Capture, rec: pycolmap.Reconstruction, ims: list) -> tuple[float, str]:
    """(metres per SfM unit, how) from the capture's poses, else its depth maps."""
    frames = [cap.frames[int(im.name.split("_", 1)[0])] for im in ims]
    if all(f.pose is not None for f in frames):
        gt = np.array([np.asarray(f.pose)[:3, 3] for f in frames])
        c = np.array([im.projection_center() for im in ims])
        return similarity_scale(c, gt), "camera centres against the capture's poses"
    ratios = []
    for im, f in zip(ims, frames, strict=True):
        if f.depth is None:
            raise BlunfError(f"{f.stem}: neither a pose nor depth: no truth to score against")
        obs = im.get_observation_points2D()
        xy = np.array([p.xy for p in obs]).reshape(-1, 2)
        xyz = np.array([rec.points3D[p.point3D_id].xyz for p in obs]).reshape(-1, 3)
        w2c = im.cam_from_world().matrix()
        cam = rec.camera(im.camera_id)
        depth = read_depth(f.depth, cap.depth_scale, cap.depth_invalid)
        z = xyz @ w2c[2, :3] + w2c[2, 3]
        ratios.append(est.depth_ratios(xy - 0.5, z, depth, (int(cam.width), int(cam.height))))
    return est.scale_from_depth(ratios)[0], "depth maps against SfM depth"


def measure(src: Path, out: Path, frames: int = 0) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bare = stripped_copy(src, out / "photos-capture", sensor=False)
    model = out / "sfm"
    if not (model / "sfm.json").is_file():
        cap = load(bare, out / "ingest")
        if frames:
            idx = np.unique(np.linspace(0, len(cap.frames) - 1, frames).round().astype(int))
            cap = cap.with_frames([cap.frames[i] for i in idx])
        (out / "ingest").mkdir(exist_ok=True)
        cap.save(out / "ingest" / "frames.json")
        cfg = PosesConfig(impl="sfm", scale_from="none")
        sfm.run(cfg, PosesInputs(out / "ingest" / "frames.json"), model)
    rec = pycolmap.Reconstruction(str(model / "sparse"))
    ims = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    full = load(Path(src), out / "truth-ingest")  # the capture's own poses / depth
    used = Capture.load(out / "ingest" / "frames.json")
    by_stem = {f.stem: f for f in full.frames}
    cap = full.with_frames([by_stem[f.stem] for f in used.frames])
    t, how = truth(cap, rec, ims)
    c = np.array([im.projection_center() for im in ims])
    rot = np.array([im.cam_from_world().rotation.matrix() for im in ims])
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    s, facts = est.scale_from_priors(c, rot[:, 0], rot[:, 1], pts)
    up, _ = est.up_from_cameras(rot[:, 0], rot[:, 1])
    floor, _ = est.floor_depth(c, up, pts)
    res = {
        "capture": str(src),
        "registered": len(ims),
        "points": len(pts),
        "truth": t,
        "truth_from": how,
        "scale": s,
        "error_pct": 100.0 * (s / t - 1.0),
        "camera_height_true_m": floor * t,  # where the estimator put the floor, in metres
        "estimate": facts,
    }
    write_json(out / "scale.json", res)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.scale", description=__doc__)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=0, help="N views spread evenly (0 = all)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        r = measure(a.capture, a.out, a.frames)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    f = r["estimate"]
    print(
        f"scale error {r['error_pct']:+.1f} % ({f['source']}, +-{f['uncertainty_rel']:.0%}); "
        f"cameras {r['camera_height_true_m']:.2f} m above the floor; "
        f"{r['registered']} views, {r['points']} points"
    )
    print(json.dumps({k: r[k] for k in ("scale", "truth", "truth_from")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

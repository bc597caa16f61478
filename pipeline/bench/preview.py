"""The fast render path (`stages.edit.surface`) against the volume render, on a run.

    python -m pipeline.bench.preview RUN --edits SPEC [--views 0,7,14] [--repeats 3]
        [--threads 2] [--out DIR]

Times both paths on the spec's views with all its edits, at 80x60 (the studio's preview of a
320x240 view) and 320x240: wall and CPU seconds (this process, all threads), medians over
views x repeats, and their ratios. Quality, at 320x240: PSNR (8-bit) of the fast render
against the volume render at the `--views` input views unedited and at the spec's views
edited, the share of pixels the fast path volume rendered (mesh miss or thin band), and per
remove / recolour edit of the spec, the IoU of the pixels it changes (a channel moved by
more than 12 of 255) in each path. Writes DIR/preview.json and prints it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.render import Rendered, Scene, run_files
from stages.common.camera import Intrinsics
from stages.edit.spec import Edit, load_spec

SIZES = ((80, 60), (320, 240))
CHANGED = 12  # a pixel changed when a channel moved by more than this (0-255)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 99.0 if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def changed(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    return np.abs(after.astype(np.int16) - before.astype(np.int16)).max(axis=2) > CHANGED


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = (a | b).sum()
    return 1.0 if u == 0 else float((a & b).sum() / u)


def timed(scene: Scene, pose, intr: Intrinsics, edits, fast: bool) -> tuple[Rendered, float, float]:
    """The render, its wall and CPU seconds."""
    w0, c0 = time.perf_counter(), time.process_time()
    r = scene.render(pose, intr, edits, fast=fast)
    return r, time.perf_counter() - w0, time.process_time() - c0


def bench(run: Path, spec: Path, views: list[int], repeats: int, quality: bool = True) -> dict:
    """Both paths' timings on the spec's views (and, with `quality`, their agreement)."""
    scene = Scene(run_files(run))
    sp = load_spec(spec)
    edits: tuple[Edit, ...] = sp.edits
    for fast in (False, True):  # warm-up: edits resolved, mesh casters built
        scene.render(*scene.view(sp.views[0]), edits, fast=fast)
    out: dict = {"run": str(run), "spec": str(spec), "repeats": repeats, "timing": {}}
    for size in SIZES:
        rows: dict[str, dict[str, list[float]]] = {
            p: {"wall": [], "cpu": []} for p in ("volume", "fast")
        }
        for v in sp.views:
            pose, intr = scene.view(v)
            for _ in range(repeats):
                for name, fast in (("volume", False), ("fast", True)):
                    _, w, c = timed(scene, pose, intr.scaled(*size), edits, fast)
                    rows[name]["wall"].append(w)
                    rows[name]["cpu"].append(c)
        med = {p: {k: statistics.median(x) for k, x in d.items()} for p, d in rows.items()}
        out["timing"][f"{size[0]}x{size[1]}"] = {
            **{p: {k: round(x, 4) for k, x in d.items()} for p, d in med.items()},
            "speedup_wall": round(med["volume"]["wall"] / med["fast"]["wall"], 1),
            "speedup_cpu": round(med["volume"]["cpu"] / med["fast"]["cpu"], 1),
        }
    if not quality:
        return out
    size = SIZES[-1]

    def pair(v: int, eds) -> tuple[np.ndarray, np.ndarray, float]:
        pose, intr = scene.view(v)
        vol = scene.render(pose, intr.scaled(*size), eds).rgb
        fst = scene.render(pose, intr.scaled(*size), eds, fast=True)
        return vol, fst.rgb, fst.volume_rendered or 0.0

    unedited = []
    for v in views:
        vol, fst, fb = pair(v, ())
        unedited.append({"view": v, "psnr": round(psnr(fst, vol), 2), "fallback": round(fb, 4)})
    edited = []
    for v in sp.views:
        vol0, fst0, _ = pair(v, ())
        vol, fst, fb = pair(v, edits)
        row: dict = {"view": v, "psnr": round(psnr(fst, vol), 2), "fallback": round(fb, 4)}
        for e in edits:
            if e.op not in ("remove", "recolor"):
                continue
            v1, f1, _ = pair(v, (e,))
            cv, cf = changed(vol0, v1), changed(fst0, f1)
            row[f"{e.op}_{e.index}"] = {
                "changed_iou": round(iou(cv, cf), 4),
                "changed_volume": int(cv.sum()),
                "changed_fast": int(cf.sum()),
                "psnr": round(psnr(f1, v1), 2),
            }
        edited.append(row)
    out["quality"] = {
        "size": list(size),
        "unedited": unedited,
        "unedited_median_psnr": round(statistics.median(r["psnr"] for r in unedited), 2),
        "edited": edited,
        "edited_median_psnr": round(statistics.median(r["psnr"] for r in edited), 2),
    }
    return out


def main(argv: list[str] | None = None) -> int:
    import torch

    from pipeline.runtime import setup_runtime

    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.preview", description=__doc__)
    ap.add_argument("run", type=Path)
    ap.add_argument("--edits", type=Path, required=True, help="edit spec (YAML)")
    ap.add_argument("--views", default="0,7,14,21", help="input views scored unedited")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    setup_runtime(a.threads)
    torch.set_num_threads(a.threads)
    res = bench(a.run, a.edits, [int(v) for v in a.views.split(",")], a.repeats)
    res["threads"] = a.threads
    text = json.dumps(res, indent=1)
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "preview.json").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

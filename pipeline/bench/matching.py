"""Image pairs against cost: SfM on one capture with each kind of matching.

    python -m pipeline.bench.matching CAPTURE --out DIR [--kinds sequential,retrieval,exhaustive]

For each kind the poses stage's SfM runs on the capture's photos (one thread, no metric
scale) and DIR/matching.json gets, per kind: the pairs tried, the loop pairs (retrieval),
the pairs verified, the longest gap in capture order among them (a walk that returns to its
start closes its loop when this is about the number of views), CPU-s of extraction, matching
and mapping, the views registered, the models, and the ATE against the capture's own poses
(gt/poses.json or the frames' poses) when it has them.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path
from typing import cast

import numpy as np

from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import read_json, write_json
from stages.evaluate.poses import pose_metrics
from stages.ingest import load
from stages.poses import sfm
from stages.poses.config import MATCHINGS, Matching, MatchingConfig, PosesConfig, PosesInputs


def measure(capture: Path, out: Path, kinds: list[str]) -> dict:
    out = Path(out)
    (out / "ingest").mkdir(parents=True, exist_ok=True)
    cap = load(Path(capture), out / "ingest")
    cap.save(out / "ingest" / "frames.json")
    gt_file = Path(capture) / "gt" / "poses.json"
    if gt_file.is_file():
        gt = {k: np.asarray(v, np.float64) for k, v in read_json(gt_file).items()}
    elif all(f.pose is not None for f in cap.frames):
        gt = {f.stem: np.asarray(f.pose, np.float64) for f in cap.frames}
    else:
        gt = {}
    res: dict = {"capture": str(capture), "views": len(cap.frames), "kinds": {}}
    for kind in kinds:
        run_dir = out / kind
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir()
        # main took only kinds among MATCHINGS (and MatchingConfig checks it again)
        matching = MatchingConfig(kind=cast(Matching, kind))
        cfg = PosesConfig(impl="sfm", scale_from="none", threads=1, matching=matching)
        t0, c0 = time.perf_counter(), time.process_time()
        sfm.run(cfg, PosesInputs(out / "ingest" / "frames.json"), run_dir)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        f = read_json(run_dir / "sfm.json")
        got = Capture.load(run_dir / "frames.json")
        est = {fr.stem: np.asarray(fr.pose) for fr in got.frames}
        ate = pose_metrics(est, gt).get("ate_rmse_m") if gt else None
        res["kinds"][kind] = {
            **f["match_pairs"],
            "cpu_seconds": {k: round(v, 2) for k, v in f["cpu_seconds"].items()},
            "cpu_s": round(cpu, 2),
            "wall_s": round(wall, 2),
            "registered": f["registered"],
            "models": f["models"],
            "ate_m": ate,
        }
    write_json(out / "matching.json", res)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.matching", description=__doc__)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--kinds", default="sequential,retrieval,exhaustive")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    kinds = [k.strip() for k in a.kinds.split(",") if k.strip()]
    try:
        bad = [k for k in kinds if k not in MATCHINGS or k == "auto"]
        if bad or not kinds:
            raise BlunfError(f"--kinds: {bad or a.kinds!r}: each one of {MATCHINGS[1:]}")
        r = measure(a.capture, a.out, kinds)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(r["kinds"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

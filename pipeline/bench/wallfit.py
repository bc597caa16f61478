"""How far a run's drawn walls lie from the vertical surfaces its views saw behind them.

For every wall of plan.json (its interior face, room on the left) the fused mesh's vertical
triangles facing the room are read along the face in bins of BIN metres over its inner 90 %,
from REACH in front of the face to REACH behind it, between Z_RANGE (by their centres: a
fused surface's triangles are small). Per bin:
  outermost  the offset of the farthest such surface (metres, + beyond the face): the
             surface that bounds the room there (a wall behind a counter, not the counter's
             front); slabs of SLAB metres holding at least MIN_AREA m² of triangles count;
  near       whether any such surface lies within NEAR of the face.
Per wall: `outer_m` (median outermost offset over the bins that saw any surface), `outer_ok`
(share of those bins whose outermost surface lies within NEAR of the face: the wall stands on
the bounding surface), `seen` (share of all bins with a surface within NEAR: the issue's
"drawn length with a seen vertical surface within 10 cm"), with its length and thickness.

    python -m pipeline.bench.wallfit RUN_DIR [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import cast

import numpy as np
import trimesh

from stages.common.errors import BlunfError
from stages.common.io import read_json

BIN = 0.05  # metres along the wall
REACH = 1.0  # metres either side of the face where surfaces are read
NEAR = 0.10  # metres: a surface this close to the face is the face
SLAB = 0.02  # metres across the wall: the histogram of offsets
MIN_AREA = 0.002  # m² of triangles in a slab of one bin for a surface to count
Z_RANGE = (0.05, 2.5)  # metres above the floor
MAX_TILT = 15.0  # degrees: a triangle within this of vertical is vertical


def _triangles(mesh: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres [T, 3], unit normals [T, 3] and areas [T] of the mesh's triangles."""
    if not Path(mesh).is_file():
        raise BlunfError(f"{mesh}: mesh file not found")
    # force="mesh" gives one Trimesh (a scene's geometries concatenated)
    m = cast(trimesh.Trimesh, trimesh.load(mesh, process=False, force="mesh"))
    p = np.asarray(m.vertices, np.float64)[np.asarray(m.faces, np.int64)]  # [T, 3, 3]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    return p.mean(1), cross / np.maximum(norm, 1e-12)[:, None], norm / 2


def wall_fit(wall: dict, c: np.ndarray, n: np.ndarray, area: np.ndarray) -> dict:
    """The figures of one plan.json wall against triangles (centres, normals, areas)."""
    a, b = np.asarray(wall["start"], np.float64), np.asarray(wall["end"], np.float64)
    length = float(np.linalg.norm(b - a))
    d = (b - a) / max(length, 1e-12)
    out = np.array([d[1], -d[0]])  # outward of a counter-clockwise outline
    facing = (n[:, :2] @ out < -np.cos(np.radians(90 - MAX_TILT))) & (
        np.abs(n[:, 2]) < np.sin(np.radians(MAX_TILT))
    )
    s, t = (c[:, :2] - a) @ d, (c[:, :2] - a) @ out
    keep = facing & (np.abs(t) <= REACH) & (c[:, 2] >= Z_RANGE[0]) & (c[:, 2] <= Z_RANGE[1])
    edges = np.arange(0.05 * length, 0.95 * length + 1e-9, BIN)
    slabs = np.arange(-REACH, REACH + SLAB, SLAB)
    hist = np.histogram2d(s[keep], t[keep], [edges, slabs], weights=area[keep])[0]  # [B, S]
    mid = (slabs[:-1] + slabs[1:]) / 2
    outer, near = [], []
    for row in hist:
        ok = row >= MIN_AREA
        near.append(bool((ok & (np.abs(mid) <= NEAR)).any()))
        if ok.any():
            outer.append(float(mid[np.flatnonzero(ok)[-1]]))
    outer_a = np.asarray(outer)
    return {
        "start": wall["start"],
        "end": wall["end"],
        "length": round(length, 3),
        "thickness": wall.get("thickness"),
        "outer_m": round(float(np.median(outer_a)), 3) if len(outer_a) else None,
        "outer_ok": round(float((np.abs(outer_a) <= NEAR).mean()), 3) if len(outer_a) else 0.0,
        "seen": round(float(np.mean(near)), 3) if near else 0.0,
    }


def measure(run: Path) -> dict:
    """{"walls": [wall_fit per plan.json wall], "seen": their length-weighted seen share}."""
    run = Path(run)
    plan = read_json(run / "plan.json")
    c, n, area = _triangles(run / "mesh.ply")
    walls = [wall_fit(w, c, n, area) for w in plan.get("walls", [])]
    total = sum(w["length"] for w in walls)
    seen = sum(w["length"] * w["seen"] for w in walls) / total if total else 0.0
    return {"walls": walls, "seen": round(seen, 3)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench.wallfit", description=__doc__)
    ap.add_argument("run", type=Path, help="a finished run folder (plan.json, mesh.ply)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here too")
    args = ap.parse_args(argv)
    try:
        res = measure(args.run)
    except BlunfError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for w in res["walls"]:
        print(
            f"wall {w['start']} -> {w['end']}: {w['length']:.2f} m, thickness "
            f"{w['thickness']}, outermost surface {w['outer_m']} m beyond the face "
            f"(within {NEAR} m on {100 * w['outer_ok']:.0f} % of its bins), a seen surface "
            f"within {NEAR} m on {100 * w['seen']:.0f} %"
        )
    print(f"drawn length with a seen vertical surface within {NEAR} m: {100 * res['seen']:.1f} %")
    if args.json is not None:
        args.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Poses far from the origin (georeferenced coordinates, 1e6 m): ingest moves them near it
and keeps the offset, so the plan is the one of the same room near the origin; the exports
(transforms.json, the vector plans) carry the offset back."""

from __future__ import annotations

import json
import shutil

import numpy as np

from stages.common.blueprint import Blueprint
from tests.runs import run_ok

FAR = np.array([1.0e6, -2.0e6, 1.0e6])  # metres added to every camera centre


def _blueprint(run) -> Blueprint:
    return Blueprint.load(run / "blueprint.npz")


def test_a_room_moved_by_1e6_m_gives_the_same_plan(tiny_room, tmp_path) -> None:
    far = tmp_path / "far"
    shutil.copytree(tiny_room, far)
    cams = json.loads((far / "cameras.json").read_text())
    for f in cams["frames"].values():
        pose = np.asarray(f["pose"], np.float64)
        pose[:3, 3] += FAR
        f["pose"] = pose.tolist()
    (far / "cameras.json").write_text(json.dumps(cams))
    if (far / "gt" / "poses.json").is_file():  # its ground truth moved alike
        gt = json.loads((far / "gt" / "poses.json").read_text())
        for k, v in gt.items():
            p = np.asarray(v, np.float64)
            p[:3, 3] += FAR
            gt[k] = p.tolist()
        (far / "gt" / "poses.json").write_text(json.dumps(gt))
    sets = ("--set", "fusion.voxel=0.05", "--set", "run.methods=blunf")
    run_ok(tiny_room, tmp_path / "near", *sets)
    run_ok(far, tmp_path / "far-run", *sets)
    near_bp, far_bp = _blueprint(tmp_path / "near"), _blueprint(tmp_path / "far-run")
    # ingest took whole kilometres off: the same frames up to float64 rounding, the same plan
    assert far_bp.grid.shape == near_bp.grid.shape
    assert np.allclose(far_bp.grid.origin, near_bp.grid.origin, atol=1e-6)
    assert np.array_equal(far_bp.labels, near_bp.labels)
    # the exports are in the capture's own world again: the offset added back
    tf = {
        r: json.loads((tmp_path / r / "transforms.json").read_text())["frames"]
        for r in ("near", "far-run")
    }
    for a, b in zip(tf["near"], tf["far-run"], strict=True):
        ta, tb = np.asarray(a["transform_matrix"]), np.asarray(b["transform_matrix"])
        assert np.allclose(tb[:3, :3], ta[:3, :3], atol=1e-9)
        assert np.allclose(tb[:2, 3], ta[:2, 3] + FAR[:2], atol=1e-6)  # x, y put back
        assert np.isclose(tb[2, 3], ta[2, 3], atol=1e-6)  # z: the floor at 0 in both

    def corners(run) -> np.ndarray:
        g = json.loads((run / "blueprint.geojson").read_text())
        pts = [
            c
            for f in g["features"]
            for ring in (f["geometry"]["coordinates"] if f["geometry"]["type"] == "Polygon" else [])
            for c in ring
        ]
        return np.asarray(pts, np.float64)

    a, b = corners(tmp_path / "near"), corners(tmp_path / "far-run")
    assert len(a) and a.shape == b.shape
    assert np.allclose(b, a + FAR[:2], atol=1e-6)

"""pipeline/bench/walls.py: how far the photos-only run's walls lie from the reference's,
read through the similarity between the runs (a photos-only world at another scale)."""

from __future__ import annotations

import json

import numpy as np

from pipeline.bench.walls import layout_offsets, point_offsets, wall_offsets

CLASSES = {0: "floor", 1: "wall"}


def _plan(x0: float, y0: float, x1: float, y1: float, skip: int | None = None) -> dict:
    """A plan.json of one rectangular room (walls in order: bottom, right, top, left)."""
    c = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    walls = [{"start": c[i], "end": c[(i + 1) % 4], "room": 0} for i in range(4) if i != skip]
    return {"rooms": [{"name": "room 1", "polygon": c}], "walls": walls}


def _sim(scale: float, shift: tuple[float, float]) -> np.ndarray:
    """pred_to_ref: x_ref = scale * x_pred + shift."""
    m = np.eye(4)
    m[:3, :3] *= scale
    m[:2, 3] = shift
    return m


def _to_pred(xy: np.ndarray, scale: float, shift: tuple[float, float]) -> np.ndarray:
    return (np.asarray(xy, float) - shift) / scale


def _outline(x0: float, y0: float, x1: float, y1: float, n: int, rng) -> np.ndarray:
    """n points along each side of the rectangle [N, 2]."""
    t = rng.uniform(0, 1, n)
    return np.concatenate(
        [
            np.c_[x0 + t * (x1 - x0), np.full(n, y0)],
            np.c_[np.full(n, x1), y0 + t * (y1 - y0)],
            np.c_[x0 + t * (x1 - x0), np.full(n, y1)],
            np.c_[np.full(n, x0), y0 + t * (y1 - y0)],
        ]
    )


def test_a_room_drawn_2_cm_small_reads_2_cm_inward_on_every_wall_through_the_similarity():
    ref = _plan(0.0, 0.0, 4.0, 3.0)
    scale, shift = 1.25, (0.3, -0.2)  # the photos-only world: 0.8 x the metres, moved
    inner = _to_pred([[0.02, 0.02], [3.98, 2.98]], scale, shift)
    # its right wall (index 1) is missing; its left one 3 cm outside the reference's room
    pred = _plan(*inner[0], *inner[1], skip=1)
    pred["walls"][-1]["start"][0] = pred["walls"][-1]["end"][0] = (-0.03 - shift[0]) / scale
    got = layout_offsets(ref, pred, _sim(scale, shift))
    assert got[0] is not None and abs(got[0] - 0.02) < 1e-9  # bottom: 2 cm into the room
    assert got[1] is None  # right: no photos-only wall matches
    assert abs(got[2] - 0.02) < 1e-9  # top
    assert abs(got[3] + 0.03) < 1e-9  # left: 3 cm outside, negative


def test_points_give_where_each_wall_piles_up_not_what_stands_in_front_of_it():
    rng = np.random.default_rng(0)
    ref = _plan(0.0, 0.0, 4.0, 3.0)
    pts = _outline(0.04, 0.04, 3.96, 2.96, 500, rng)  # 4 cm inside on every side
    pts = pts + rng.normal(0, 0.005, pts.shape)
    clutter = np.c_[rng.uniform(1, 3, 300), rng.uniform(1, 2, 300)]  # the room's middle
    # a shelf 4-14 cm in front of the bottom wall, 800 points against the wall's 500: their
    # median lies in the shelf
    shelf = np.c_[rng.uniform(0.5, 3.5, 800), rng.uniform(0.08, 0.18, 800)]
    both = np.concatenate([pts, clutter, shelf])
    got = point_offsets(ref, both)
    assert all(abs(g - 0.04) < 0.003 for g in got)
    d = both[:, 1]
    band = (both[:, 0] > 0.2) & (both[:, 0] < 3.8) & (d < 0.15)
    assert np.median(d[band]) > 0.08  # the plain median would read the shelf
    assert point_offsets(ref, pts[:10]) == [None] * 4  # too few points anywhere


def _run(root, plan: dict, wall_xy: np.ndarray) -> None:
    root.mkdir(parents=True)
    (root / "plan.json").write_text(json.dumps(plan))
    (root / "project" / "k").mkdir(parents=True)
    xyz = np.c_[wall_xy, np.ones(len(wall_xy))].astype(np.float32)
    np.savez(
        root / "project" / "k" / "points.npz",
        xyz=xyz,
        label=np.ones(len(xyz), np.uint8),
        view=np.zeros(len(xyz), np.int32),
        classes=json.dumps({str(k): v for k, v in CLASSES.items()}),
    )


def test_two_run_folders_give_layout_and_point_offsets(tmp_path):
    rng = np.random.default_rng(1)
    scale, shift = 0.5, (1.0, 1.0)
    _run(tmp_path / "ref", _plan(0.0, 0.0, 4.0, 3.0), _outline(0.0, 0.0, 4.0, 3.0, 400, rng))
    inner = _to_pred([[0.03, 0.03], [3.97, 2.97]], scale, shift)
    pts = _to_pred(_outline(0.01, 0.01, 3.99, 2.99, 400, rng), scale, shift)
    _run(tmp_path / "photos", _plan(*inner[0], *inner[1]), pts)
    res = wall_offsets(tmp_path / "ref", tmp_path / "photos", _sim(scale, shift))
    assert res is not None and res["walls"] == 4 and "sfm_points" not in res  # no SfM run
    assert res["layout"]["found"] == 4 and abs(res["layout"]["median_cm"] - 3.0) < 1e-6
    assert abs(res["plan_points"]["median_cm"] - 1.0) < 1e-6
    assert abs(res["ref_points"]["median_cm"]) < 1e-6
    (tmp_path / "photos" / "plan.json").unlink()
    assert wall_offsets(tmp_path / "ref", tmp_path / "photos", _sim(scale, shift)) is None

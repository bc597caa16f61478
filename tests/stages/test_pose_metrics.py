"""Pose metrics on hand-made trajectories whose errors are worked out exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.evaluate.poses import pose_metrics


def rot(axis: tuple[float, float, float], deg: float) -> np.ndarray:
    """Rodrigues rotation of `deg` degrees about `axis`. Returns [3, 3]."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def pose(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = r, c
    return p


def gt_trajectory() -> dict[str, np.ndarray]:
    """Six cameras on a non-planar loop, each turned differently."""
    out = {}
    for i in range(6):
        th = 2 * math.pi * i / 6
        c = np.array([2 * math.cos(th), math.sin(th), 1.2 + 0.3 * math.sin(2 * th)])
        out[f"f{i}"] = pose(rot((0.2, 1.0, 0.3 * i), 40 * i), c)
    return out


def test_similarity_of_gt_gives_zero_error() -> None:
    # est = the GT trajectory seen in another world: x_est = s R x_gt + t. The similarity
    # alignment undoes it exactly, so every error is 0 and the alignment scale is 1 / s.
    gt = gt_trajectory()
    s, r, t = 0.37, rot((1, -2, 0.5), 123.0), np.array([4.0, -1.0, 2.5])
    est = {k: pose(r @ p[:3, :3], s * r @ p[:3, 3] + t) for k, p in gt.items()}
    m = pose_metrics(est, gt)
    assert (m["registered"], m["total"]) == (6, 6)
    assert m["rot_err_deg_median"] == pytest.approx(0.0, abs=1e-5)
    assert m["center_err_median_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["ate_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["align_scale"] == pytest.approx(1 / s, rel=1e-9)


def test_rotation_perturbation_gives_its_angles() -> None:
    # Centres exact, cameras turned in pairs by +-theta about a shared world axis (f0 / f5:
    # 3 degrees about y, f1 / f2: 1 about x, f3 / f4: 4 about z). The whole-pose fit sums
    # R_gt R_est^T = rot(a, -theta) over the cameras: each pair adds a symmetric positive
    # matrix, as the exact centres do, so the alignment stays the identity and the errors are
    # 3, 1, 1, 4, 4, 3 degrees: median 3.
    gt = gt_trajectory()
    turns = [((0, 1, 0), -3), ((1, 0, 0), 1), ((1, 0, 0), -1)]
    turns += [((0, 0, 1), 4), ((0, 0, 1), -4), ((0, 1, 0), 3)]
    est = {k: pose(rot(*turns[i]) @ p[:3, :3], p[:3, 3]) for i, (k, p) in enumerate(gt.items())}
    m = pose_metrics(est, gt)
    assert m["rot_err_deg_median"] == pytest.approx(3.0, abs=1e-6)
    assert m["center_err_median_m"] == pytest.approx(0.0, abs=1e-9)
    assert m["align_scale"] == pytest.approx(1.0, abs=1e-12)


def test_centre_perturbation_gives_worked_out_error() -> None:
    # GT centres: square corners (+-1, +-1, 0). Estimates lift them by +-d in z in a pattern
    # uncorrelated with x and y (signs + - - +), so the best similarity has R = I and t = 0,
    # and scale s = var(gt) / var(est) = 2 / (2 + d^2) (Umeyama). Each aligned centre
    # s * (x, y, +-d) misses (x, y, 0) by sqrt(2 (1 - s)^2 + s^2 d^2) = d * sqrt(s):
    # all four equal, so the median and the RMSE are both d * sqrt(s).
    d = 0.1
    corners = [(1, 1, d), (1, -1, -d), (-1, 1, -d), (-1, -1, d)]
    gt = {f"c{i}": pose(np.eye(3), np.array([x, y, 0.0])) for i, (x, y, _) in enumerate(corners)}
    est = {f"c{i}": pose(np.eye(3), np.array(c, np.float64)) for i, c in enumerate(corners)}
    s = 2 / (2 + d**2)
    m = pose_metrics(est, gt)
    assert m["align_scale"] == pytest.approx(s, rel=1e-9)
    assert m["center_err_median_m"] == pytest.approx(d * math.sqrt(s), rel=1e-9)
    assert m["ate_rmse_m"] == pytest.approx(d * math.sqrt(s), rel=1e-9)
    assert m["rot_err_deg_median"] == pytest.approx(0.0, abs=1e-5)


def test_unregistered_and_extra_frames() -> None:
    # Two GT frames missing from the estimate, one estimated frame not in GT (ignored).
    gt = gt_trajectory()
    est = {k: p for k, p in gt.items() if k not in ("f1", "f4")}
    est["stray"] = pose(np.eye(3), np.array([100.0, 0, 0]))
    m = pose_metrics(est, gt)
    assert (m["registered"], m["total"]) == (4, 6)
    assert m["ate_rmse_m"] == pytest.approx(0.0, abs=1e-9)


def test_too_few_frames_gives_no_errors() -> None:
    gt = gt_trajectory()
    m = pose_metrics({k: gt[k] for k in ("f0", "f1")}, gt)
    assert (m["registered"], m["total"]) == (2, 6)
    assert m["rot_err_deg_median"] is None and m["ate_rmse_m"] is None


def test_slightly_scaled_gt_rotations_are_not_an_error() -> None:
    # Real GT (e.g. 7-Scenes) has rotation blocks with det ~0.9998. Read naively through
    # acos((trace - 1) / 2), 0.99985 * R against R gives acos(1 - 2.25e-4) ~ 1.2 degrees;
    # projected onto rotations it is exactly R, so the error must be 0.
    gt = gt_trajectory()
    scaled = {k: pose(0.99985 * p[:3, :3], p[:3, 3]) for k, p in gt.items()}
    m = pose_metrics(gt, scaled)
    assert m["rot_err_deg_median"] == pytest.approx(0.0, abs=1e-5)

"""The scoring frame comes from whole poses: a straight camera path leaves the rotation about
it free under camera centres alone, the orientations fix it (stages/common/gt_frame.py)."""

from __future__ import annotations

import math

import numpy as np

from stages.common.blueprint import Grid
from stages.common.gt_frame import FRAME_ALIGNED, plan_frame, pose_similarity, similarity
from stages.evaluate.poses import pose_metrics


def _turn(axis: tuple[float, float, float], deg: float) -> np.ndarray:
    """Rodrigues rotation of `deg` degrees about `axis`. Returns [3, 3]."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def _straight_path() -> dict[str, np.ndarray]:
    """Eight cameras 5 cm apart on a line along x at 1.4 m, looking across it (+y) and
    panning a little: a short sideways walk, as in a 1.6 s clip."""
    out = {}
    look = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]).T  # camera x, y, z -> world
    for i in range(8):
        p = np.eye(4)
        p[:3, :3] = _turn((0, 0, 1), 3.0 * i) @ look
        p[:3, 3] = [0.05 * i, 0.0, 1.4]
        out[f"f{i}"] = p
    return out


def test_a_straight_path_is_aligned_by_its_orientations() -> None:
    gt = _straight_path()
    # the reconstruction's frame: turned 18 degrees about the path (x), scaled, moved
    s = np.eye(4)
    s[:3, :3] = 0.5 * _turn((1, 0, 0), 18.0) @ _turn((0, 0, 1), 40.0)
    s[:3, 3] = [1.0, -2.0, 0.3]
    inv = np.linalg.inv(s)
    est = {k: inv @ v for k, v in gt.items()}
    m, frame = plan_frame(True, est, gt, Grid((0.0, 0.0), 0.05, (20, 20)))
    assert frame == FRAME_ALIGNED
    np.testing.assert_allclose(m, s, atol=1e-9)
    got = pose_metrics(est, gt)
    assert got["rot_err_deg_median"] < 1e-5 and got["ate_rmse_m"] < 1e-9
    facts = got["alignment"]
    assert facts["centres_conditioning"] < 1e-6  # the centres alone hold no turn about x
    assert facts["centres_vs_poses_deg"] is None
    assert facts["conditioning"] > 0.3
    # the centres alone put the same path at another turn about it: that is the failure
    keys = sorted(gt)
    centres = similarity(
        np.stack([est[k][:3, 3] for k in keys]), np.stack([gt[k][:3, 3] for k in keys])
    )
    assert centres is not None
    off = np.linalg.inv(s[:3, :3] / 2.0) @ (centres[:3, :3] / 2.0)
    assert np.degrees(np.arccos(np.clip((np.trace(off) - 1) / 2, -1, 1))) > 5.0


def test_orientations_pull_the_fit_only_as_far_as_they_disagree() -> None:
    """A loop of cameras (centres hold every turn) whose orientations all carry the same
    3 degree error: the fit lies between the centres' answer (0) and the orientations' (3),
    and the facts say how far apart the two are."""
    gt = {}
    for i in range(10):
        a = 2 * math.pi * i / 10
        p = np.eye(4)
        p[:3, :3] = _turn((0, 0, 1), 36.0 * i)
        p[:3, 3] = [2 * math.cos(a), math.sin(a), 1.2 + 0.2 * math.sin(2 * a)]
        gt[f"f{i}"] = p
    off = _turn((0, 1, 0), 3.0)
    est = {k: np.block([[off @ v[:3, :3], v[:3, 3:]], [v[3:]]]) for k, v in gt.items()}
    keys = sorted(gt)
    m, facts = pose_similarity([est[k] for k in keys], [gt[k] for k in keys])
    assert m is not None
    r = m[:3, :3] / np.cbrt(np.linalg.det(m[:3, :3]))  # the scale (cos of the turn) out
    turn = np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
    assert 0.5 < turn < 2.5
    assert abs(facts["centres_vs_poses_deg"] - turn) < 1e-6
    assert facts["conditioning"] > facts["centres_conditioning"] > 0.1

"""Pose metrics: estimated camera-to-world poses against ground truth, up to a similarity
of the whole poses (`stages.common.gt_frame.pose_similarity`)."""

from __future__ import annotations

import numpy as np

from stages.common.gt_frame import MIN_ALIGN, pose_similarity


def _rotation(m: np.ndarray) -> np.ndarray:
    """Nearest rotation to the 3x3 block of a (possibly scaled) pose. Returns [3, 3]."""
    u, _, vt = np.linalg.svd(np.asarray(m, np.float64)[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:  # reflection: flip the weakest axis
        u[:, -1] *= -1
        r = u @ vt
    return r


def _angle_deg(r: np.ndarray) -> np.ndarray:
    """Rotation angles of [N, 3, 3] rotations, in degrees. Returns [N]."""
    cos = (np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pose_metrics(est: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> dict:
    """Registration and accuracy of estimated poses after a similarity alignment to ground truth.

    Args:
        est: stem -> [4, 4] estimated camera-to-world pose (frames that did not register absent).
        gt: stem -> [4, 4] ground-truth camera-to-world pose (metres).
    Returns:
        registered (gt frames with an estimate), total (= len(gt)), rot_err_deg_median,
        center_err_median_m, ate_rmse_m (RMSE of aligned camera centres) and align_scale (the
        alignment's scale: 1 when the estimate is metric), "alignment" (pose_similarity's
        facts: how well the poses fix it). The error entries are None when fewer
        than 3 frames are shared or the centres are degenerate (all equal).
    """
    common = [s for s in gt if s in est]
    out: dict = {
        "registered": len(common),
        "total": len(gt),
        "rot_err_deg_median": None,
        "center_err_median_m": None,
        "ate_rmse_m": None,
        "align_scale": None,
        "alignment": None,
    }
    if len(common) < MIN_ALIGN:
        return out
    pe = np.stack([np.asarray(est[s], np.float64) for s in common])  # [C, 4, 4]
    pg = np.stack([np.asarray(gt[s], np.float64) for s in common])  # [C, 4, 4]
    ce, cg = pe[:, :3, 3], pg[:, :3, 3]  # [C, 3] camera centres
    m, out["alignment"] = pose_similarity(list(pe), list(pg))
    if m is None:
        return out
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    r_align = m[:3, :3] / scale  # [3, 3]
    center_err = np.linalg.norm(ce @ m[:3, :3].T + m[:3, 3] - cg, axis=1)  # [C]
    r_est = np.stack([r_align @ _rotation(p) for p in pe])  # [C, 3, 3] aligned world
    r_gt = np.stack([_rotation(p) for p in pg])  # [C, 3, 3]
    rot_err = _angle_deg(np.transpose(r_gt, (0, 2, 1)) @ r_est)  # [C]
    out.update(
        rot_err_deg_median=float(np.median(rot_err)),
        center_err_median_m=float(np.median(center_err)),
        ate_rmse_m=float(np.sqrt(np.mean(center_err**2))),
        align_scale=scale,
    )
    return out

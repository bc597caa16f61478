"""The frame a plan is scored in against the ground truth: the similarity from the frames'
whole poses (camera centres and orientations) to the ground-truth ones, when the poses were
estimated or moved.

Camera centres alone leave the rotation about a straight camera path free (a short or
straight path scores an arbitrary turn of the plan about it), so the rotation is fitted to
the centres and the orientations together (`pose_similarity`: Umeyama's cross-covariance of
the centres, each set scaled to unit spread, plus the sum of the orientation pairs, i.e.
points one spread along each camera axis); the scale and translation then follow from the
centres. `similarity` (points only) comes from skimage's `SimilarityTransform`; pycolmap's
aligners need Reconstruction objects, which the callers do not have.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from skimage.transform import SimilarityTransform

from stages.common.blueprint import Grid
from stages.common.capture import Capture
from stages.common.io import read_json
from stages.common.plan_metrics import to_frame

log = logging.getLogger(__name__)

MIN_ALIGN = 3  # a similarity in 3-D needs at least 3 non-collinear centres
FRAME_GT = "gt"  # the plan was built in the ground truth's frame (given poses, not moved)
FRAME_ALIGNED = "aligned to gt poses"  # read through the camera-centre similarity
FRAME_UNALIGNED = "estimated, not aligned"  # estimated poses that could not be aligned


def similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """The similarity (Umeyama, with scale) best mapping points src [N, 3] onto dst [N, 3].

    Returns the 4x4 matrix, or None when fewer than 3 points are given, either set is
    degenerate (all points equal) or the estimate fails.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if len(src) < MIN_ALIGN or len(src) != len(dst):
        return None
    if np.ptp(src, axis=0).max() < 1e-12 or np.ptp(dst, axis=0).max() < 1e-12:
        return None
    tf = SimilarityTransform.from_estimate(src, dst)
    return np.asarray(tf.params, np.float64) if tf else None


def _fit_rotation(cov: np.ndarray) -> np.ndarray:
    """The rotation R maximising trace(R^T cov) (Kabsch, no reflection). Returns [3, 3]."""
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    return u @ d @ vt


def _rotation_conditioning(cov: np.ndarray) -> float:
    """How well a cross-covariance fixes a rotation: the turn about singular axis k is held
    by the sum of the other two singular values, so (s2 + s3) / (s1 + s2): 0 = a turn is
    free (collinear centres alone), 1 = every turn equally held."""
    sv = np.linalg.svd(cov, compute_uv=False)
    return float((sv[1] + sv[2]) / max(sv[0] + sv[1], 1e-300))


def _unit_rotation(m: np.ndarray) -> np.ndarray:
    """Nearest rotation to the 3x3 block of a (possibly scaled) pose. Returns [3, 3]."""
    u, _, vt = np.linalg.svd(np.asarray(m, np.float64)[:3, :3])
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    return u @ d @ vt


def pose_similarity(est: list[np.ndarray], gt: list[np.ndarray]) -> tuple[np.ndarray | None, dict]:
    """The similarity best mapping estimated camera-to-world poses onto ground-truth ones.

    Args:
        est, gt: paired [4, 4] camera-to-world poses (same length).
    Returns:
        (4x4 matrix or None when fewer than 3 poses are given or the centres are all equal,
        facts): "poses", "conditioning" (of the whole-pose rotation fit, see
        _rotation_conditioning), "centres_conditioning" (of the centres alone: near 0 for a
        straight path) and "centres_vs_poses_deg" (the turn between the rotation the centres
        alone give and the whole-pose one; None when the centres leave it free).
    """
    facts: dict = {"poses": len(est), "conditioning": None, "centres_conditioning": None}
    facts["centres_vs_poses_deg"] = None
    if len(est) < MIN_ALIGN or len(est) != len(gt):
        return None, facts
    pe = np.stack([np.asarray(p, np.float64) for p in est])  # [N, 4, 4]
    pg = np.stack([np.asarray(p, np.float64) for p in gt])  # [N, 4, 4]
    ce, cg = pe[:, :3, 3], pg[:, :3, 3]  # [N, 3] camera centres
    de, dg = ce - ce.mean(0), cg - cg.mean(0)  # [N, 3] centred
    se, sg = np.sqrt((de**2).sum(1).mean()), np.sqrt((dg**2).sum(1).mean())  # RMS spreads
    if se < 1e-12 or sg < 1e-12:
        return None, facts
    cov_c = (dg / sg).T @ (de / se) / len(pe)  # [3, 3] centres, unit spread each side
    re = np.stack([_unit_rotation(p) for p in pe])  # [N, 3, 3]
    rg = np.stack([_unit_rotation(p) for p in pg])  # [N, 3, 3]
    cov_r = np.einsum("nij,nkj->ik", rg, re) / len(pe)  # [3, 3] sum of R_gt R_est^T
    cov = cov_c + cov_r
    r = _fit_rotation(cov)  # [3, 3]
    s = float(np.einsum("ni,ni->", dg, de @ r.T) / (de**2).sum())
    if not np.isfinite(s) or s <= 0:
        return None, facts
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = s * r, cg.mean(0) - s * r @ ce.mean(0)
    facts["conditioning"] = _rotation_conditioning(cov)
    facts["centres_conditioning"] = _rotation_conditioning(cov_c)
    if facts["centres_conditioning"] > 1e-6:
        turn = _fit_rotation(cov_c).T @ r
        cos = (np.trace(turn) - 1.0) / 2.0
        facts["centres_vs_poses_deg"] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return m, facts


def pose_pairs(frames: Path, gt_poses: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(stem -> [4, 4] pose of frames.json, stem -> [4, 4] ground-truth pose of poses.json)."""
    cap = Capture.load(frames)
    est = {f.stem: np.asarray(f.pose, np.float64) for f in cap.frames if f.pose is not None}
    return est, {k: np.asarray(v, np.float64) for k, v in read_json(gt_poses).items()}


def gt_frame(
    frames: Path, gt_poses: Path | None, estimated: bool, grid: Grid
) -> tuple[np.ndarray | None, str]:
    """plan_frame for the plans projected from frames.json, given the capture's GT poses
    (None or missing: the plans are taken to be in the GT frame unless poses were estimated)."""
    if gt_poses is None or not gt_poses.is_file():
        return plan_frame(estimated, {}, {}, grid)
    return plan_frame(estimated, *pose_pairs(frames, gt_poses), grid)


def plan_frame(
    estimated: bool, est: dict[str, np.ndarray], gt: dict[str, np.ndarray], grid: Grid
) -> tuple[np.ndarray | None, str]:
    """(prediction-to-GT similarity or None, the frame's name) for the plan metrics; the
    similarity is pose_similarity's (whole poses, not centres alone).

    Args:
        estimated: whether a stage estimated the poses the plans were built from.
        est: stem -> [4, 4] camera-to-world pose the plans were built from.
        gt: stem -> [4, 4] ground-truth camera-to-world pose (empty when there is none).
        grid: the GT plan's grid; given poses that the alignment moves by less than a tenth
            of its cell anywhere on it count as the GT frame itself.
    """
    common = [s for s in gt if s in est]
    m, facts = pose_similarity([est[s] for s in common], [gt[s] for s in common])
    if m is not None:
        log.info(
            "evaluate: plans aligned to the GT poses (%d poses, conditioning %.3f, centres "
            "alone %.3f)",
            len(common),
            facts["conditioning"],
            facts["centres_conditioning"],
        )
    if m is None:
        if not estimated:
            return None, FRAME_GT
        log.warning(
            "evaluate: poses were estimated but cannot be aligned to ground-truth poses "
            "(%d shared frames); plans are compared cell by cell as they are",
            len(common),
        )
        return None, FRAME_UNALIGNED
    if not estimated and _moves(m, grid) < 0.1 * grid.cell:
        return None, FRAME_GT
    return m, FRAME_ALIGNED


def _moves(pred_to_gt: np.ndarray, grid: Grid) -> float:
    """How far (metres) the GT grid's corners land from where they are, read through it."""
    h, w = grid.shape
    corners = np.asarray(grid.origin) + np.array([[0, 0], [w, 0], [0, h], [w, h]]) * grid.cell
    return float(np.linalg.norm(to_frame(corners, pred_to_gt) - corners, axis=1).max())

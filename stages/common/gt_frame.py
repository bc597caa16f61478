"""The frame a plan is scored in against the ground truth: the similarity from the frames'
camera centres to the ground-truth ones, when the poses were estimated or moved.

The similarity (Umeyama, with scale) comes from skimage's `SimilarityTransform`, which works in
3-D; pycolmap's aligners need Reconstruction objects, which the callers do not have.
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
    """(prediction-to-GT similarity or None, the frame's name) for the plan metrics.

    Args:
        estimated: whether a stage estimated the poses the plans were built from.
        est: stem -> [4, 4] camera-to-world pose the plans were built from.
        gt: stem -> [4, 4] ground-truth camera-to-world pose (empty when there is none).
        grid: the GT plan's grid; given poses that the alignment moves by less than a tenth
            of its cell anywhere on it count as the GT frame itself.
    """
    common = [s for s in gt if s in est]
    m = None
    if common:
        ce = np.stack([est[s][:3, 3] for s in common])  # [C, 3] camera centres of the plans
        cg = np.stack([gt[s][:3, 3] for s in common])  # [C, 3] ground-truth camera centres
        m = similarity(ce, cg)
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

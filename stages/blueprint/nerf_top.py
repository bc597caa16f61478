"""The NeRF top-view baseline (the paper's "NeRF top view"): vertical rays through the
semantic NeRF from a set of heights; the plan is the labels seen from the best height.

As in the paper, the best height is the one whose plan scores the highest fwIoU against a
reference: the ground-truth plan when the capture has one (scored as the evaluate stage
scores it: same frame, same class table), else the majority vote of the projected labels
(MVR), so the choice never looks at anything the other methods do not have.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from stages.blueprint.config import BlueprintConfig, BlueprintOutputs, NerfTopInputs
from stages.blueprint.instances import instance_raster
from stages.blueprint.mvr import majority_vote
from stages.common.blueprint import Blueprint
from stages.common.errors import BlunfError
from stages.common.gt_frame import gt_frame
from stages.common.io import write_json
from stages.common.plan_metrics import evaluate_plan, plan_metrics
from stages.common.points import read_grid, read_instances, read_points

log = logging.getLogger(__name__)


def run(cfg: BlueprintConfig, inputs: NerfTopInputs, out: Path) -> BlueprintOutputs:
    """Render the semantic NeRF from above at each height; keep the best plan."""
    from stages.common.radiance.field import load_field  # torch: imported when needed
    from stages.common.radiance.render import top_view_labels

    c = cfg.nerf_top
    if not c.heights or min(c.heights) <= 0:
        raise BlunfError(f"blueprint.nerf_top.heights must be positive metres, got {c.heights}")
    t0 = time.perf_counter()
    grid = read_grid(inputs.grid)
    xyz, label, _, classes = read_points(inputs.points)
    model = load_field(inputs.model)
    if model.sem_head is None:
        raise BlunfError(f"{inputs.model}: the NeRF has no semantic head (no labels to learn)")
    plans = top_view_labels(model, grid, list(c.heights), c.chunk)
    if inputs.reference is not None:
        # scored exactly as the evaluate stage will score it: in the GT's frame (through the
        # camera-centre similarity for estimated poses) and class table (coarsened for
        # derived floor / wall / object labels)
        gt = Blueprint.load(inputs.reference)
        pred_to_gt = None  # without frames: the plan is taken to be in the GT's frame
        if inputs.frames is not None:
            args = (inputs.frames, inputs.gt_poses, inputs.poses_estimated, gt.grid)
            pred_to_gt, _ = gt_frame(*args)
        scores = {
            h: evaluate_plan(Blueprint(p, grid, classes), gt, pred_to_gt)["fwiou"]
            for h, p in plans.items()
        }
        against = "ground truth"
    else:
        ref, _ = majority_vote(xyz[:, :2], label, grid)
        scores = {h: plan_metrics(p, ref, classes)["fwiou"] for h, p in plans.items()}
        against = "projected labels (MVR)"
    best = max(scores, key=lambda h: (scores[h], -h))
    outs = BlueprintOutputs(Path(out) / "blueprint.npz", Path(out) / "nerf_top.json")
    inst = instance_raster(plans[best], grid, xyz[:, :2], label, read_instances(inputs.points))
    Blueprint(plans[best], grid, classes, inst).save(outs.blueprint)
    write_json(
        outs.stats,
        {
            "height": best,
            "chosen_against": against,
            "fwiou_by_height": {f"{h:.2f}": round(s, 3) for h, s in scores.items()},
            "seconds": round(time.perf_counter() - t0, 3),
        },
    )
    log.info(
        "blueprint/nerf_top: best height %.2f m (fwIoU %.1f vs %s)", best, scores[best], against
    )
    return outs

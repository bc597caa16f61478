"""Settings of a radiance field: its network and sampler (a trained field carries them with
it), and how it is trained (the occupancy grid, the scene box, the losses, the loop).

`TrainingConfig` gathers them; the nerf stage's config (`nerf.*`) and the depth stage's field
fill (`depth.field.*`) are both one. Messages name the nerf stage's keys; the field fill's
are the same under `depth.field`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, get_args

from stages.common.errors import BlunfError

FieldKind = Literal["hash", "pe"]
FIELDS = get_args(FieldKind)  # field.kind (a loaded model.pt is checked against them too)


@dataclass(frozen=True)
class FieldConfig:
    """The network: an encoding of world points, a density trunk, colour and class heads."""

    kind: FieldKind = "hash"  # "hash" (Instant-NGP grid + small MLP) | "pe" (NeRF PE + MLP)
    hash_levels: int = 8  # hash: resolution levels
    hash_features: int = 2  # hash: features per level
    hash_log2_size: int = 17  # hash: log2 of the table entries per level
    hash_base_res: int = 16  # hash: coarsest resolution (cells across the scene box)
    hash_max_res: int = 512  # hash: finest resolution (cells across the scene box)
    width: int = 64  # hidden units of the density / colour / semantic heads
    color_grid: bool = True  # hash: colour reads a hash grid of its own (same sizes)
    geo_features: int = 15  # features passed from the density MLP to the colour / semantic heads
    pe_freqs: int = 10  # pe: octaves of the position encoding (NeRF: 10)
    pe_dir_freqs: int = 4  # pe / view_dependent: octaves of the direction encoding (NeRF: 4)
    pe_width: int = 128  # pe: hidden units of the trunk MLP
    pe_layers: int = 4  # pe: hidden layers of the trunk MLP
    view_dependent: bool = False  # colour also depends on the view direction (PE of dirs)


@dataclass(frozen=True)
class SamplingConfig:
    """How rays are marched through the field and what a rendered pixel counts as."""

    samples_across: int = 512  # ray-marching step = diagonal of the scene box / this
    near: float = 0.05  # metres: rays start this far from the camera
    prune_eps: float = 1e-4  # samples after transmittance < this are not evaluated (0 = off)
    acc_threshold: float = 0.5  # rendered depth is 0 (missing) where opacity is below this


@dataclass(frozen=True)
class OccupancyConfig:
    """The occupancy grid that skips empty space."""

    res: int = 128  # occupancy cells along the longest side of the scene box
    every: int = 16  # steps between occupancy-grid updates
    decay: float = 0.95  # decay of the cells' density estimate per update
    alpha: float = 0.01  # a cell is occupied when one step through it is this opaque
    cells: int = 65536  # cells re-evaluated per update (half random, half occupied)
    dilate: int = 1  # cells of dilation around depth pixels when seeding the grid
    seeded_only: bool = True  # with depth: the grid keeps exactly the seeded cells (no updates)


@dataclass(frozen=True)
class BoxConfig:
    """The scene box the field lives in."""

    pad: float = 0.05  # scene box = bounds of cameras and depth points, + this fraction
    no_depth_margin: float = 3.0  # metres around the cameras when there are no depth points
    depth_stride: int = 4  # pixel stride of the depth points bounding the scene box


@dataclass(frozen=True)
class LossConfig:
    """The terms of the training loss (losses.py)."""

    rgb: str = "mse"  # "mse" | "huber" (delta 0.1)
    depth_weight: float = 1.0  # weight of the L1 loss on expected depth (metres)
    surface_weight: float = 1.0  # with depth: weight of (1 - opacity) + weight in front of it
    semantic_weight: float = 0.5  # weight of the semantic cross-entropy (Semantic-NeRF
    # uses 0.04 over 200k steps; in a few hundred steps 0.04 leaves every class "wall")
    trunc_steps: int = 4  # with depth, training rays end this many steps behind it (0 = off)
    surface_rays: int = 16384  # with depth: extra pixels per step whose colour is fitted at
    # their depth point (one field query each, no marching); 0 = off
    surface_jitter: float = 0.0  # those points are jittered along the ray by +- this many steps
    surface_rgb_weight: float = 1.0  # weight of that colour loss
    geo_rays: int = 8192  # with depth: pixels per step whose density is fitted directly:
    # empty in front of the depth reading, opaque just behind it (two field queries each)
    geo_weight: float = 1.0  # weight of that loss (binary cross-entropy on one step's opacity)
    geo_front: float = 0.3  # metres in front of the reading where the free-space point is drawn
    edge_rays: int = 4096  # dense depth: pixels per step beside a nearer reading (a silhouette)
    # whose ray is fitted empty where it passes that reading (one field query each); 0 = off
    edge_radius: int = 2  # pixels: how far from a pixel the nearer reading is looked for
    edge_gap: float = 0.1  # metres: ... and how much nearer than the pixel's own it must be

    def __post_init__(self) -> None:
        for name in ("edge_rays", "edge_radius"):
            if getattr(self, name) < 0:
                raise BlunfError(f"nerf.losses.{name}: must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.edge_gap < float("inf"):
            raise BlunfError(
                f"nerf.losses.edge_gap: must be a finite number > 0, got {self.edge_gap}"
            )


@dataclass(frozen=True)
class TrainConfig:
    """The optimisation loop: batches, learning rate, held-out scoring, when to stop."""

    batch_rays: int = 1024  # rays per step
    edge_batch: float = 0.0  # fraction of the marched rays drawn among the pixels beside a
    #                          silhouette (dense depth; configs/edit.yaml: 0.5, crisper
    #                          outlines for a lower PSNR)
    dense_depth: float = 0.5  # depth on at least this fraction of pixels counts as dense
    surface_color: bool = False  # with depth: render each ray's colour at its expected depth
    lr: float = 1e-2  # Adam learning rate, decayed exponentially to lr * lr_final
    lr_final: float = 0.1  # final learning rate as a fraction of lr
    lr_decay_steps: int = 3000  # steps over which lr decays to lr * lr_final (then constant)
    holdout_every: int = 8  # every k-th view (index % k == k // 2) is held out; 0 = none
    eval_every: int = 200  # steps between held-out evaluations
    eval_rays: int = 4096  # held-out pixels scored at each evaluation (fixed random subset)
    # the final held-out scores (psnr_heldout, depth_absrel): "views" renders every held-out
    # view in full, "rays" reuses the last evaluation's eval_rays pixels
    # (docs/figures.md#train-heldout-score)
    heldout_score: Literal["views", "rays"] = "views"
    patience: int = 5  # stop after this many evaluations without a gain of min_delta
    min_delta: float = 0.05  # dB: a smaller held-out PSNR gain does not count as improving
    # the three stops: docs/figures.md#train-stop
    time_budget: float = 0.0  # an opt-in guard: seconds of training (evaluations excluded)
    #                          after which it stops (once past min_steps), reported as
    #                          stop_reason "time" and a warning; 0 = none
    max_steps: int = 250  # stop after this many steps (reproducible); 0 = no limit (then
    #                       the time budget or a held-out plateau stops it)
    min_steps: int = 100  # the time budget never stops training before this many steps
    # torch threads while training: a fixed count, not the free cores, so the weights do not
    # depend on how busy the machine is (2 threads against 1 split the weight gradients' sums
    # and the element-wise kernels' vector tails differently: the kitchen's field fill gave 52 %
    # other depth pixels). On one thread the kitchen's field fill trains in 88 s (108 s before
    # the faster hash grid, 78 s on two idle cores then) (docs/figures.md#train-threads); 0 =
    # the stage's thread count
    threads: int = 1

    def __post_init__(self) -> None:
        if not 0.0 <= self.edge_batch <= 1.0:
            raise BlunfError(f"nerf.train.edge_batch: must be in [0, 1], got {self.edge_batch}")
        if self.min_steps < 0:
            raise BlunfError(f"nerf.train.min_steps: must be >= 0, got {self.min_steps}")
        if self.threads < 0:
            raise BlunfError(f"nerf.train.threads: must be >= 0, got {self.threads}")
        if self.max_steps < 0 or not 0.0 <= self.time_budget < float("inf"):
            raise BlunfError(
                "nerf.train.max_steps must be >= 0 and nerf.train.time_budget a finite number "
                f">= 0, got {self.max_steps}, {self.time_budget}"
            )
        if self.max_steps == 0 and self.time_budget == 0 and self.eval_every == 0:
            raise BlunfError(
                "nerf.train.max_steps: 0 with no time_budget and no held-out evaluation "
                "(eval_every 0) never stops: give a step count"
            )
        if self.heldout_score == "rays" and self.eval_rays < 1:
            raise BlunfError("nerf.train.heldout_score: rays needs nerf.train.eval_rays >= 1")


@dataclass(frozen=True)
class TrainingConfig:
    """A radiance field and its training (what stages.common.radiance.fit reads)."""

    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)  # the network
    sampling: SamplingConfig = dataclasses.field(
        default_factory=SamplingConfig
    )  # marching, opacity
    occupancy: OccupancyConfig = dataclasses.field(default_factory=OccupancyConfig)  # empty space
    box: BoxConfig = dataclasses.field(default_factory=BoxConfig)  # the scene box
    losses: LossConfig = dataclasses.field(default_factory=LossConfig)  # the loss terms
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)  # the optimisation loop
    semantics: bool = True  # train a semantic head when every frame has a label map
    seed: int = 0  # seeds the initialisation, ray batches and jitter
    chunk: int = 16384  # rays per forward pass when rendering full views

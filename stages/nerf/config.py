"""Configuration and the input / output contract of the NeRF stage."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class NerfConfig:
    """The radiance field, its sampler and its training (defaults: a few minutes on a CPU)."""

    impl: str = "grid"  # registry key in stages.nerf.IMPLS: "grid" (occupancy-grid sampler)
    field: str = "hash"  # "hash" (Instant-NGP grid + small MLP) | "pe" (NeRF PE + MLP)
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
    semantics: bool = True  # train a semantic head when every frame has a label map
    samples_across: int = 512  # ray-marching step = diagonal of the scene box / this
    near: float = 0.05  # metres: rays start this far from the camera
    occ_res: int = 128  # occupancy cells along the longest side of the scene box
    occ_every: int = 16  # steps between occupancy-grid updates
    occ_decay: float = 0.95  # decay of the cells' density estimate per update
    occ_alpha: float = 0.01  # a cell is occupied when one step through it is this opaque
    occ_cells: int = 65536  # cells re-evaluated per update (half random, half occupied)
    occ_dilate: int = 1  # cells of dilation around depth pixels when seeding the grid
    trunc_steps: int = 4  # with depth, training rays end this many steps behind it (0 = off)
    prune_eps: float = 1e-4  # samples after transmittance < this are not evaluated (0 = off)
    batch_rays: int = 1024  # rays per step
    surface_rays: int = 16384  # with depth: extra pixels per step whose colour is fitted at
    # their depth point (one field query each, no marching); 0 = off
    surface_jitter: float = 0.0  # those points are jittered along the ray by +- this many steps
    surface_rgb_weight: float = 1.0  # weight of that colour loss
    surface_color: bool = False  # with depth: render each ray's colour at its expected depth
    geo_rays: int = 8192  # with depth: pixels per step whose density is fitted directly:
    # empty in front of the depth reading, opaque just behind it (two field queries each)
    geo_weight: float = 1.0  # weight of that loss (binary cross-entropy on one step's opacity)
    geo_front: float = 0.3  # metres in front of the reading where the free-space point is drawn
    edge_rays: int = 4096  # dense depth: pixels per step beside a nearer reading (a silhouette)
    # whose ray is fitted empty where it passes that reading (one field query each); 0 = off
    edge_radius: int = 2  # pixels: how far from a pixel the nearer reading is looked for
    edge_gap: float = 0.1  # metres: ... and how much nearer than the pixel's own it must be
    edge_batch: float = 0.0  # fraction of the marched rays drawn among those pixels (dense depth;
    #                          configs/edit.yaml: 0.5, crisper outlines for a lower PSNR)
    dense_depth: float = 0.5  # depth on at least this fraction of pixels counts as dense
    occ_seeded_only: bool = True  # with depth: the grid keeps exactly the seeded cells (no updates)
    lr: float = 1e-2  # Adam learning rate, decayed exponentially to lr * lr_final
    lr_final: float = 0.1  # final learning rate as a fraction of lr
    lr_decay_steps: int = 3000  # steps over which lr decays to lr * lr_final (then constant)
    rgb_loss: str = "mse"  # "mse" | "huber" (delta 0.1)
    depth_weight: float = 1.0  # weight of the L1 loss on expected depth (metres)
    surface_weight: float = 1.0  # with depth: weight of (1 - opacity) + weight in front of it
    semantic_weight: float = 0.5  # weight of the semantic cross-entropy (Semantic-NeRF
    # uses 0.04 over 200k steps; in a few hundred steps 0.04 leaves every class "wall")
    holdout_every: int = 8  # every k-th view (index % k == k // 2) is held out; 0 = none
    eval_every: int = 200  # steps between held-out evaluations
    eval_rays: int = 4096  # held-out pixels scored at each evaluation (fixed random subset)
    patience: int = 5  # stop after this many evaluations without a gain of min_delta
    min_delta: float = 0.05  # dB: a smaller held-out PSNR gain does not count as improving
    time_budget: float = 120.0  # seconds of training (evaluations excluded); 0 = no limit
    max_steps: int = 0  # stop after this many steps; 0 = no limit (reproducible stop)
    seed: int = 0  # seeds the initialisation, ray batches and jitter
    threads: int = 0  # torch threads (0 = leave torch's setting)
    chunk: int = 16384  # rays per forward pass when rendering full views
    depth_render_scale: int = 2  # sparse depth: depth for fusion rendered at 1/k resolution
    acc_threshold: float = 0.5  # rendered depth is 0 (missing) where opacity is below this
    depth_check: bool = False  # sparse depth: drop rendered readings the other views do not
    #                           confirm (multi-view consistency, consistency.py) before fusion
    depth_check_tol: float = 0.03  # relative depth difference within which two views agree
    depth_check_agree: int = 1  # a reading is kept when at least this many views agree ...
    depth_check_through: int = 0  # ... and at most this many see through it (a floater)
    depth_check_views: int = 10  # each view is checked against the views overlapping it most
    stereo: bool = True  # sparse depth (photos only): plane-sweep stereo (stereo.py) gives the
    #                     training views dense depth first, and the field trains as with a sensor
    stereo_planes: int = 64  # depth planes of the sweep, even in inverse depth
    stereo_refine: int = 16  # then per pixel this many across a plane step either side (0 = no)
    stereo_views: int = 4  # views each view is matched against (those overlapping it most)
    stereo_window: int = 7  # pixels: side of the correlation window (odd)
    stereo_max_cost: float = 0.4  # a reading needs 1 - ZNCC below this
    stereo_min_std: float = 0.02  # ... and this grey-level spread (0-1) in its window
    stereo_tol: float = 0.02  # relative depth within which other views confirm a reading
    stereo_agree: int = 2  # ... and this many of them must
    stereo_fuse: bool = True  # depth for fusion: the stereo reading where there is one (full
    #                           resolution), the field's render elsewhere (held-out views: the
    #                           render only)
    stereo_check: int = 1  # ... a rendered reading is kept only where this many other views'
    #                        stereo readings agree with it (stereo_tol) and none sees through
    #                        it (0, or stereo too sparse to train on: every rendered
    #                        reading). Demo room, photos only: plan fwIoU 78.3 with the whole
    #                        render, 82.3-82.9 with this check
    aabb_pad: float = 0.05  # scene box = bounds of cameras and depth points, + this fraction
    no_depth_margin: float = 3.0  # metres around the cameras when there are no depth points
    depth_stride: int = 4  # pixel stride of the depth points bounding the scene box

    def __post_init__(self) -> None:
        if not 0.0 <= self.edge_batch <= 1.0:
            raise BlunfError(f"nerf.edge_batch: must be in [0, 1], got {self.edge_batch}")
        for name in ("edge_rays", "edge_radius"):
            if getattr(self, name) < 0:
                raise BlunfError(f"nerf.{name}: must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.edge_gap < float("inf"):
            raise BlunfError(f"nerf.edge_gap: must be a finite number > 0, got {self.edge_gap}")
        if self.stereo_check < 0:
            raise BlunfError(f"nerf.stereo_check: must be >= 0, got {self.stereo_check}")


@dataclass(frozen=True)
class NerfInputs:
    frames: Path  # frames.json (Capture) with poses; depth and labels optional


@dataclass(frozen=True)
class NerfOutputs:
    STATS: ClassVar[str | None] = "nerf.json"  # its stats file: the report's facts
    model: Path  # model.pt: load with stages.nerf.load_model
    stats: Path  # nerf.json: steps, seconds, stop_reason, psnr_heldout, depth_absrel, curve
    frames: Path  # frames.json: the input capture with depth -> the rendered depth maps
    depth: Path  # depth/<stem>.npy: rendered z-depth, float32 metres, 0 where opacity is low

    @classmethod
    def at(cls, out: Path) -> NerfOutputs:
        """The outputs inside a finished nerf folder."""
        out = Path(out)
        return cls(
            model=out / "model.pt",
            stats=out / "nerf.json",
            frames=out / "frames.json",
            depth=out / "depth",
        )

"""Configuration and the input / output contract of the NeRF stage.

Settings are nested as nerfstudio nests its configs: `nerf.field.*` (the network),
`nerf.sampling.*`, `nerf.occupancy.*`, `nerf.box.*`, `nerf.losses.*`, `nerf.train.*`,
`nerf.stereo.*` and `nerf.depth_check.*` (e.g. `--set nerf.stereo.planes=32`). The flat keys
of earlier versions are listed in `NerfConfig.RENAMED` and fail with their new name.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from stages.common.errors import BlunfError
from stages.common.radiance.config import FieldConfig, SamplingConfig

HELDOUT_SCORES = ("views", "rays")  # nerf.train.heldout_score


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
    # uses 0.04 over 200k steps; in a few hundred steps 0.04 leaves every class a wall)
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
    heldout_score: str = "views"  # the final held-out scores (psnr_heldout, depth_absrel):
    #   "views": every held-out view rendered in full (heldout/<stem>.png), the mean of the
    #   views' PSNR and AbsRel; "rays": the last evaluation's eval_rays pixels, scored once at
    #   the last step and reused, no held-out view rendered (PSNR of their pooled error,
    #   median AbsRel). Demo room, 200 steps: 25.19 dB on 4096 rays against 25.23 over the
    #   7 views, whose renders took 64 s of the stage's 163 (one thread)
    patience: int = 5  # stop after this many evaluations without a gain of min_delta
    min_delta: float = 0.05  # dB: a smaller held-out PSNR gain does not count as improving
    time_budget: float = 120.0  # seconds of training (evaluations excluded); 0 = no limit
    max_steps: int = 0  # stop after this many steps; 0 = no limit (reproducible stop)
    min_steps: int = 100  # the time budget never stops training before this many steps: on
    #                       a loaded machine make demo's photos-only field got 35 steps in
    #                       its 120 s (held-out PSNR 5.7 dB) and fusion received no depth

    def __post_init__(self) -> None:
        if not 0.0 <= self.edge_batch <= 1.0:
            raise BlunfError(f"nerf.train.edge_batch: must be in [0, 1], got {self.edge_batch}")
        if self.min_steps < 0:
            raise BlunfError(f"nerf.train.min_steps: must be >= 0, got {self.min_steps}")
        if self.heldout_score not in HELDOUT_SCORES:
            raise BlunfError(
                f"nerf.train.heldout_score: must be one of {HELDOUT_SCORES}, "
                f"got {self.heldout_score!r}"
            )
        if self.heldout_score == "rays" and self.eval_rays < 1:
            raise BlunfError("nerf.train.heldout_score: rays needs nerf.train.eval_rays >= 1")


@dataclass(frozen=True)
class StereoConfig:
    """Plane-sweep stereo among the photos (stereo.py), for sparse depth (photos only)."""

    enabled: bool = True  # sparse depth (photos only): plane-sweep stereo gives the training
    #                       views dense depth first, and the field trains as with a sensor
    planes: int = 64  # depth planes, even in inverse depth between the view's track bounds
    #                 (configs/phone.yaml: 32, measured there; the 96x72 test room keeps 8 %
    #                 of its pixels with 32 against 14 % with 64)
    plane_px: float = 0.0  # > 0: each view sweeps only as many planes (at most `planes`,
    #                 at least 8) as put one plane step at <= plane_px pixels of its widest
    #                 neighbour's image (disparity range = focal x baseline x (1/near -
    #                 1/far)): close neighbours need fewer planes; 0 = always `planes`
    refine: int = 16  # then per pixel this many planes across one coarse step either side
    #                   (0 or 1 = no refinement): a plane step is ~10 cm at 3 m here
    views: int = 4  # views each view is matched against (those overlapping it most)
    scale: int = 1  # depth maps at 1/scale of the photos' resolution (k x k binned); 0 = the
    #                 largest at which a pixel at the median track depth spans <= `cell`.
    #                 Demo room, photos only, stereo alone: scale 2 with coarse 2 took 17
    #                 CPU-s against 155 at scale 1 but the plan fell to fwIoU 72.6 (one run),
    #                 hence 1 until the coarse maps are fused better
    cell: float = 0.02  # metres: the plan's cell, for scale 0 (a finer depth map adds no
    #                     detail to the plan)
    coarse: int = 1  # the planes are swept at a further 1/coarse, the per-pixel refinement at
    #                  1/scale round that estimate (coarse to fine; needs refine >= 3)
    window: int = 7  # pixels: side of the correlation window (odd)
    max_cost: float = 0.4  # a reading needs 1 - ZNCC below this (ZNCC above 0.6)
    min_std: float = 0.02  # ... and this grey-level spread (0-1) in its window
    tol: float = 0.02  # relative depth within which other views confirm a reading
    agree: int = 2  # ... and this many of them must
    fuse: bool = True  # depth for fusion: the stereo reading where there is one (full
    #                    resolution), the field's render elsewhere (held-out views: the
    #                    render only)
    field_fill: bool | Literal["auto"] = "auto"  # photos only: train the field on the
    #                 stereo depth and fill stereo's holes with its render (grid.fit); false:
    #                 the stereo readings alone feed fusion and no field trains unless an
    #                 edit or the NeRF top view asks for one (nerf/sweep.py); auto: the
    #                 field trains only when stereo gives depth to fewer than
    #                 field_fill_below of the pixels. Measured: the demo room (60 views
    #                 320x240, phone.yaml; stereo covers ~79 %) fwIoU 84.6 off against 84.5
    #                 on with 0.38x the depth step's CPU time; the real 7-Scenes kitchen (20
    #                 frames at 240 px; stereo covers 19 %: white walls and floor) 0.1 off
    #                 against 30.8 on
    field_fill_below: float = 0.5  # auto: the stereo coverage under which the field trains
    fill_samples_across: int = 256  # the filling field's marching step: the scene box's
    #                 diagonal / this (sampling.samples_across for fields that edits and
    #                 views render). Its depth fills a sweep no finer than the plan's cell:
    #                 the 7-Scenes kitchen (100 views, box diagonal 6.2 m) from its photos,
    #                 2.4 cm steps against 1.2: 36 samples a ray against 70, plan fwIoU 47.2
    #                 against 47.1-50.5 (three runs), the field's depth renders half the time
    check: int = 1  # ... a rendered reading is kept only where this many other views'
    #                 stereo readings agree with it (tol) and none sees through it (0, or
    #                 stereo too sparse to train on: every rendered reading). Demo room,
    #                 photos only: plan fwIoU 78.3 with the whole render, 82.3-82.9 with
    #                 this check

    def __post_init__(self) -> None:
        if self.planes < 3 or self.views < 1 or self.refine == 2 or self.refine < 0:
            raise BlunfError(
                "nerf.stereo.planes must be >= 3, nerf.stereo.views >= 1 and "
                "nerf.stereo.refine 0, 1 or >= 3, got "
                f"{self.planes}, {self.views}, {self.refine}"
            )
        if self.scale < 0 or self.coarse < 1 or (self.coarse > 1 and self.refine < 3):
            raise BlunfError(
                "nerf.stereo.scale must be >= 0 and nerf.stereo.coarse >= 1 (> 1 only with "
                f"refine >= 3), got {self.scale}, {self.coarse} (refine {self.refine})"
            )
        if not 0.0 <= self.plane_px < float("inf"):
            raise BlunfError(
                f"nerf.stereo.plane_px must be a finite number >= 0, got {self.plane_px}"
            )
        if not 0 < self.cell < float("inf"):
            raise BlunfError(f"nerf.stereo.cell must be a finite number > 0, got {self.cell}")
        if self.window < 3 or self.window % 2 == 0:
            raise BlunfError(f"nerf.stereo.window must be odd and >= 3, got {self.window}")
        if not 0 < self.max_cost <= 2:
            raise BlunfError(f"nerf.stereo.max_cost must be in (0, 2], got {self.max_cost}")
        if self.fill_samples_across < 1:
            raise BlunfError(
                f"nerf.stereo.fill_samples_across must be >= 1, got {self.fill_samples_across}"
            )
        if not 0.0 <= self.field_fill_below <= 1.0:
            raise BlunfError(
                f"nerf.stereo.field_fill_below must be in [0, 1], got {self.field_fill_below}"
            )
        if self.check < 0:
            raise BlunfError(f"nerf.stereo.check: must be >= 0, got {self.check}")


@dataclass(frozen=True)
class DepthCheckConfig:
    """Sparse depth: drop rendered readings the other views do not confirm (multi-view
    consistency, consistency.py) before fusion."""

    enabled: bool = False  # run the check
    tol: float = 0.03  # relative depth difference within which two views agree
    agree: int = 1  # a reading is kept when at least this many views agree ...
    through: int = 0  # ... and at most this many see through it (a floater)
    views: int = 10  # each view is checked against the views overlapping it most


@dataclass(frozen=True)
class NerfConfig:
    """The radiance field, its sampler and its training (defaults: a few minutes on a CPU)."""

    # sections that every implementation reads although one implementation bears their name
    # (the `stereo` sweep; `grid` sweeps too before training): they stay in each cache key
    SHARED: ClassVar[tuple[str, ...]] = ("stereo",)
    impl: str = "grid"  # registry key in stages.nerf.IMPLS: "grid" (occupancy-grid sampler)
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)  # the network
    sampling: SamplingConfig = dataclasses.field(
        default_factory=SamplingConfig
    )  # marching, opacity
    occupancy: OccupancyConfig = dataclasses.field(default_factory=OccupancyConfig)  # empty space
    box: BoxConfig = dataclasses.field(default_factory=BoxConfig)  # the scene box
    losses: LossConfig = dataclasses.field(default_factory=LossConfig)  # the loss terms
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)  # the optimisation loop
    stereo: StereoConfig = dataclasses.field(
        default_factory=StereoConfig
    )  # photos only: stereo depth
    depth_check: DepthCheckConfig = dataclasses.field(
        default_factory=DepthCheckConfig
    )  # before fusion
    semantics: bool = True  # train a semantic head when every frame has a label map
    seed: int = 0  # seeds the initialisation, ray batches and jitter
    threads: int = 0  # torch threads (0 = leave torch's setting)
    chunk: int = 16384  # rays per forward pass when rendering full views
    depth_render_scale: int = 2  # sparse depth: depth for fusion rendered at 1/k resolution

    # the flat keys of earlier versions -> their place now (an old key fails naming it)
    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"field.{k}" for k in (
            "hash_levels", "hash_features", "hash_log2_size", "hash_base_res", "hash_max_res",
            "width", "color_grid", "geo_features", "pe_freqs", "pe_dir_freqs", "pe_width",
            "pe_layers", "view_dependent")},
        "field": "field.kind",
        **{k: f"sampling.{k}" for k in ("samples_across", "near", "prune_eps", "acc_threshold")},
        **{f"occ_{k}": f"occupancy.{k}" for k in (
            "res", "every", "decay", "alpha", "cells", "dilate", "seeded_only")},
        "aabb_pad": "box.pad",
        "no_depth_margin": "box.no_depth_margin",
        "depth_stride": "box.depth_stride",
        "rgb_loss": "losses.rgb",
        **{k: f"losses.{k}" for k in (
            "depth_weight", "surface_weight", "semantic_weight", "trunc_steps", "surface_rays",
            "surface_jitter", "surface_rgb_weight", "geo_rays", "geo_weight", "geo_front",
            "edge_rays", "edge_radius", "edge_gap")},
        **{k: f"train.{k}" for k in (
            "batch_rays", "edge_batch", "dense_depth", "surface_color", "lr", "lr_final",
            "lr_decay_steps", "holdout_every", "eval_every", "eval_rays", "patience",
            "min_delta", "time_budget", "max_steps")},
        "stereo": "stereo.enabled",
        **{f"stereo_{k}": f"stereo.{k}" for k in (
            "planes", "refine", "window", "max_cost", "min_std", "tol", "agree", "fuse",
            "check")},
        "stereo_views": "stereo.views",
        "depth_check": "depth_check.enabled",
        **{f"depth_check_{k}": f"depth_check.{k}" for k in ("tol", "agree", "through", "views")},
    }  # fmt: skip


@dataclass(frozen=True)
class NerfInputs:
    frames: Path  # frames.json (Capture) with poses; depth and labels optional


@dataclass(frozen=True)
class StereoOutputs:
    """The stereo-only implementation's outputs (sweep.py): depth for fusion, no field."""

    STATS: ClassVar[str | None] = "stereo.json"  # its stats file: the report's facts
    stats: Path  # stereo.json: fractions matched and kept, scale, planes, seconds
    frames: Path  # frames.json: the input capture with depth -> the stereo depth maps
    depth: Path  # depth/<stem>.npy: z-depth, float32 metres, 0 = none, sweep resolution

    @classmethod
    def at(cls, out: Path) -> StereoOutputs:
        """The outputs inside a finished stereo folder."""
        out = Path(out)
        return cls(stats=out / "stereo.json", frames=out / "frames.json", depth=out / "depth")


@dataclass(frozen=True)
class NerfOutputs:
    STATS: ClassVar[str | None] = "nerf.json"  # its stats file: the report's facts
    model: Path  # model.pt: load with stages.common.radiance.field.load_field
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

"""Configuration and the input / output contract of the NeRF stage.

Settings are nested as nerfstudio nests its configs: `nerf.field.*` (the network),
`nerf.sampling.*`, `nerf.occupancy.*`, `nerf.box.*`, `nerf.losses.*` and `nerf.train.*`
(e.g. `--set nerf.train.max_steps=300`; the sections live in stages.common.radiance.config,
shared with the depth stage's field fill). The flat keys of earlier versions are listed in
`NerfConfig.RENAMED` and fail with their new name; the photos-only depth settings that moved
to the depth stage (`nerf.stereo.*`, `nerf.depth_check.*`) in `NerfConfig.MOVED`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.common.radiance.config import TrainingConfig


@dataclass(frozen=True)
class NerfConfig(TrainingConfig):
    """The radiance field, its sampler and its training (defaults: a few minutes on a CPU)."""

    impl: str = "grid"  # registry key in stages.nerf.IMPLS: "grid" (occupancy-grid sampler)
    threads: int = 0  # torch threads (0 = leave torch's setting)

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
    }  # fmt: skip

    # the photos-only depth's settings, now the depth stage's (an old key fails naming it)
    MOVED: ClassVar[dict[str, str]] = {
        "stereo": "depth.stereo",
        "stereo.field_fill": "depth.field.fill",
        "stereo.field_fill_below": "depth.field.below",
        "stereo.fill_samples_across": "depth.field.sampling.samples_across",
        "stereo.check": "depth.field.check",
        "depth_check": "depth.check",
        "depth_render_scale": "depth.field.render_scale",
        **{f"stereo_{k}": f"depth.stereo.{k}" for k in (
            "planes", "refine", "window", "max_cost", "min_std", "tol", "agree", "fuse",
            "views")},
        "stereo_check": "depth.field.check",
        **{f"depth_check_{k}": f"depth.check.{k}" for k in ("tol", "agree", "through", "views")},
    }  # fmt: skip


@dataclass(frozen=True)
class NerfInputs:
    frames: Path  # frames.json (Capture) with poses; depth and labels optional


@dataclass(frozen=True)
class NerfOutputs:
    STATS: ClassVar[str | None] = "nerf.json"  # its stats file: the report's facts
    model: Path  # model.pt: load with stages.common.radiance.field.load_field
    stats: Path  # nerf.json: steps, seconds, stop_reason, psnr_heldout, depth_absrel, curve
    frames: Path  # frames.json: the input capture (its depth is the depth the field trained on)
    depth: Path  # depth/: empty (depth for fusion from the photos is the depth stage's)

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

"""Settings a trained radiance field carries with it: its network and how it is sampled."""

from __future__ import annotations

from dataclasses import dataclass

FIELDS = ("hash", "pe")


@dataclass(frozen=True)
class FieldConfig:
    """The network: an encoding of world points, a density trunk, colour and class heads."""

    kind: str = "hash"  # "hash" (Instant-NGP grid + small MLP) | "pe" (NeRF PE + MLP)
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

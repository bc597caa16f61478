"""Configuration, inputs and outputs of the fusion stage (TSDF of depth -> mesh, clean depth)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.common.errors import BlunfError
from stages.common.memory import check_memory

VOXEL_BYTES = 20  # float tsdf, weight and RGB per voxel (as fusion/tsdf.py allocates them)
MIN_BLOCKS = 64  # blocks any fused scene touches at least (docs/figures.md#fusion-min-blocks)


@dataclass(frozen=True)
class FusionConfig:
    """How depth maps are fused into one surface and ray-cast back into every view."""

    impl: str = "tsdf"  # "tsdf": Open3D tensor VoxelBlockGrid (CPU)
    voxel: float = 0.02  # voxel size, metres
    trunc_voxels: float = 4.0  # TSDF truncation distance, in voxels
    depth_min: float = 0.1  # readings nearer than this (metres) are not fused
    depth_max: float = 5.0  # readings farther than this (metres) are not fused
    far_share: float = 0.05  # > 0: the far limit grows past depth_max to the farthest
    #                          view's depth with this share of its readings beyond it; 0 =
    #                          fixed (docs/figures.md#fusion-far-share)
    far_max: float = 10.0  # metres: far_share grows the far limit up to this at most (a
    #                        patch of junk readings far off never moves it further)
    block_resolution: int = 16  # voxels along each side of a hashed voxel block
    weight_threshold: float = 0.5  # a voxel is surface only when more than this many frames
    #                                saw it (0.5 = every observed voxel; 1.5 = two frames)
    min_support: int = 0  # keep the fused surface only where this many views have a
    #                       reading within support_voxels of it (fusion/carve.py: removes what
    #                       averaging disagreeing depth leaves between the readings); 0 = off
    max_through: float = 0.0  # > 0: also remove the fused surface where more than this many
    #                        views per view whose reading lies on it read beyond it (they saw
    #                        through it: free space there, fusion/carve.py); 0 = off
    #                        (docs/figures.md#fusion-max-through)
    support_voxels: float = 2.5  # ... within this many voxels, along the view's optical axis
    region_mb: float = 200.0  # voxels of more than this (MB) touched: fuse region by region,
    #                           each a box of blocks holding at most this much (2560 blocks of
    #                           16^3; fusion/regions.py: the same surface, memory of the
    #                           largest box); 0 = one grid always
    raycast: bool = True  # ray-cast the fused mesh into every view as that view's clean depth

    def __post_init__(self) -> None:
        if not self.voxel > 0:
            raise BlunfError(f"fusion.voxel: must be > 0 metres, got {self.voxel}")
        if not self.trunc_voxels >= 1:
            raise BlunfError(f"fusion.trunc_voxels: must be >= 1, got {self.trunc_voxels}")
        if not 0 <= self.depth_min < self.depth_max:
            raise BlunfError(
                f"fusion: need 0 <= depth_min < depth_max, got {self.depth_min}, {self.depth_max}"
            )
        if not self.far_max > 0:
            raise BlunfError(f"fusion.far_max: must be > 0 metres, got {self.far_max}")
        if not 0 <= self.far_share < 0.5:
            raise BlunfError(f"fusion.far_share: must be in [0, 0.5), got {self.far_share}")
        if self.block_resolution < 1:
            raise BlunfError(f"fusion.block_resolution: must be >= 1, got {self.block_resolution}")
        check_memory(
            MIN_BLOCKS * self.block_resolution**3 * VOXEL_BYTES,
            f"fusion.block_resolution={self.block_resolution} (voxel {self.voxel} m)",
        )
        if not self.region_mb >= 0:
            raise BlunfError(f"fusion.region_mb: must be >= 0 MB, got {self.region_mb}")
        if self.min_support < 0:
            raise BlunfError(f"fusion.min_support: must be >= 0, got {self.min_support}")
        if not self.max_through >= 0:
            raise BlunfError(f"fusion.max_through: must be >= 0, got {self.max_through}")
        if not self.support_voxels > 0:
            raise BlunfError(f"fusion.support_voxels: must be > 0, got {self.support_voxels}")
        if not self.weight_threshold >= 0:
            raise BlunfError(f"fusion.weight_threshold: must be >= 0, got {self.weight_threshold}")

    @property
    def region_blocks(self) -> int:
        """Voxel blocks a region holds at most (region_mb); 0 = one grid always."""
        if not self.region_mb:
            return 0
        return max(1, int(self.region_mb * 2**20 / (self.block_resolution**3 * VOXEL_BYTES)))


@dataclass(frozen=True)
class FusionInputs:
    frames: Path  # frames.json (a `Capture`): every frame with depth and a finite pose


@dataclass(frozen=True)
class FusionOutputs:
    STATS: ClassVar[str | None] = "fusion.json"  # its stats file: the report's facts
    mesh: Path  # mesh.ply: fused surface with vertex colours
    cloud: Path  # cloud.ply: points on the fused surface with colours and normals
    depth: Path  # depth/: <stem>.npy per view, ray-cast depth in float32 metres (0 = no hit)
    frames: Path  # frames.json: the input capture with depth pointing at depth/<stem>.npy
    stats: Path  # fusion.json: voxel size, blocks, timings, vertex and triangle counts

    @classmethod
    def at(cls, out: Path) -> FusionOutputs:
        """The outputs inside a finished out folder."""
        out = Path(out)
        return cls(
            mesh=out / "mesh.ply",
            cloud=out / "cloud.ply",
            depth=out / "depth",
            frames=out / "frames.json",
            stats=out / "fusion.json",
        )

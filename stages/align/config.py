"""Configuration, inputs and outputs of the align stage (world z up, floor at z = 0)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class AlignConfig:
    """How the world is turned z up and shifted so that the floor is at z = 0."""

    impl: str = "auto"  # "auto" (gravity when the capture has one, else floor) | "gravity"
    #                     | "floor" | "none" (identity)
    frames_used: int = 20  # frames (evenly spaced over the capture) whose depth is sampled
    stride: int = 8  # pixel stride when sampling those depth maps (at most; see min_samples)
    min_samples: int = 1000  # the stride is lowered (down to 1) for small images until a frame
    #                          gives this many depth samples (a 16x12 frame at stride 8 gives 2)
    plane_dist: float = 0.02  # metres: floor inlier distance, and bin of the height histogram
    max_tilt_deg: float = 15.0  # a point is on a horizontal surface when its normal is within
    #                             this angle of up
    up_cone_deg: float = 45.0  # floor impl: the floor normal may be this far from the cameras'
    #                            mean up direction (cameras looking down tilt that mean)
    min_floor_fraction: float = 0.05  # a height counts as a floor when it holds this fraction
    #                                   of the horizontal points below the cameras
    # floor impl: when no floor plane can be fitted, the up is the direction square to the
    # cameras' x axes if they are level to within this RMS roll, degrees (planes.level_up;
    # 0 = never). The honest procedural room from photos (rendered, no roll): up 4.74 ->
    # 0.03 degrees from its sensor's, plan against the sensor at SfM poses 81.10 -> 87.37;
    # the 7-Scenes kitchen rolls 5.3 degrees RMS and is not read so; its floor and the
    # office's are fitted, their align unchanged (docs/figures.md#align-level)
    level_roll_deg: float = 1.0
    normal_neighbours: int = 16  # nearest neighbours (within one frame) for point normals
    manhattan: bool = True  # also turn about z so that the main wall directions (azimuths of
    #                         the near-horizontal normals, modulo 90 deg) lie on x and y
    manhattan_min_confidence: float = 0.2  # keep the yaw when the resultant length of
    #                                        exp(4i azimuth) over those normals is below this
    # where the yaw is read: "lines" = the horizontal directions of the photos' straight edges
    # (lines.py), "normals" = the depth points' normals, "auto" = the edges when the depth is
    # SfM's sparse tracks and the edges give MIN_EDGE_VOTES votes and a resultant of at least
    # lines_min_confidence, else normals (dense depth's normals agree with the edges within
    # 0.2 degrees on the kitchen and the office: its photos are not read). SfM tracks'
    # normals scatter: the photos-only plan stood turned from the sensor's at the same poses
    # by 2.7 degrees on the kitchen and 0.55 on the office; by the edges 0.25 and 0.24. Plan
    # against the sensor at SfM poses, SfM seeds 0 / 1: office 80.25 / 79.58 -> 81.90 /
    # 81.44 (wall 50.2 / 51.3), kitchen 75.15 / 75.72 -> 73.47 / 75.90 (its far wall parallel
    # now, 5 cm in front of the sensor's, as SfM's points on it are). The demo and honest
    # procedural rooms' textures give too few straight edges: normals, unchanged
    # (docs/figures.md#align-lines)
    yaw_from: Literal["auto", "lines", "normals"] = "auto"
    lines_min_confidence: float = 0.2

    def __post_init__(self) -> None:
        for name in ("frames_used", "stride", "min_samples"):
            if getattr(self, name) < 1:
                raise BlunfError(f"align.{name}: must be >= 1, got {getattr(self, name)}")
        if self.normal_neighbours < 3:
            raise BlunfError(f"align.normal_neighbours: must be >= 3, got {self.normal_neighbours}")
        if not self.plane_dist > 0:
            raise BlunfError(f"align.plane_dist: must be > 0 metres, got {self.plane_dist}")
        if not 0 < self.max_tilt_deg <= self.up_cone_deg < 90:
            raise BlunfError(
                "align: need 0 < max_tilt_deg <= up_cone_deg < 90, got "
                f"{self.max_tilt_deg} and {self.up_cone_deg}"
            )
        for name in ("manhattan_min_confidence", "lines_min_confidence"):
            if not 0 <= getattr(self, name) <= 1:
                raise BlunfError(f"align.{name}: must be in [0, 1], got {getattr(self, name)}")
        if self.yaw_from not in ("auto", "lines", "normals"):
            raise BlunfError(
                f"align.yaw_from: must be auto, lines or normals, got {self.yaw_from!r}"
            )
        if not 0 <= self.level_roll_deg < 90:
            raise BlunfError(
                f"align.level_roll_deg: must be in [0, 90) degrees, got {self.level_roll_deg}"
            )
        if not 0 < self.min_floor_fraction <= 1:
            raise BlunfError(
                f"align.min_floor_fraction: must be in (0, 1], got {self.min_floor_fraction}"
            )


@dataclass(frozen=True)
class AlignInputs:
    frames: Path  # frames.json (a `Capture`) with a camera-to-world pose on every frame
    free_yaw: bool = False  # the input world's turn about z means nothing (SfM's world): the
    #                         first camera sets it (manhattan.heading_turn), so runs of one
    #                         capture give plans in one frame


@dataclass(frozen=True)
class AlignOutputs:
    STATS: ClassVar[str | None] = "align.json"  # its stats file: the report's facts
    frames: Path  # frames.json with every pose replaced by T @ pose
    align: Path  # align.json: T, method, floor height before the shift, inliers, Manhattan
    #              yaw and its confidence, notes

    @classmethod
    def at(cls, out: Path) -> AlignOutputs:
        """The outputs inside a finished out folder."""
        out = Path(out)
        return cls(frames=out / "frames.json", align=out / "align.json")

"""Configuration and the input / output contract of the project stage (the paper's Π)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.common.errors import BlunfError

LABELLINGS = ("auto", "labels", "height")
OCCLUSIONS = ("top", "none")


@dataclass(frozen=True)
class ProjectConfig:
    """How labelled pixels become plan points."""

    impl: str = "pinhole"  # registry key in stages.project.IMPLS
    stride: int = 0  # keep every stride-th pixel in u and v (1 = every pixel); 0 = the
    #                  stride whose samples at the capture's median depth lie nearest one
    #                  plan cell apart (docs/figures.md#project-stride)
    cell: float = 0.02  # plan cell size in metres
    # metres added around the robust bounds of the points: the plan covers the walls' thickness
    # (points stop at their inner faces) and a margin; BluNF fills it, MVR leaves it unknown
    pad: float = 0.3
    bounds_pct: float = 0.1  # percent of points dropped on each side when bounding the plan
    labelling: str = "auto"  # "labels" | "height" | "auto" (labels when the capture has them)
    floor_band: float = 0.05  # height labelling: z below this (metres) is floor
    ceiling_cut: float = 2.0  # height labelling: z at or above this (metres) is dropped
    max_cells: int = 25_000_000  # refuse larger plans (a sign of bad poses or units)
    occlusion: str = "top"  # "top": keep what a top view sees (topview.py) | "none": every point
    occlusion_cell: float = 0.06  # top view: cell (metres) over which the top is taken; 0 = cell
    top_band: float = 0.1  # top view: a class is seen when it reaches this close to the top (m)
    top_min_points: int = 2  # top view: the top is the n-th highest point; sparser cells kept
    occlusion_shifts: int = 2  # top view: n x n grids offset by 1/n cell; dropped only if in all
    seen_radius: float = 0.25  # metres: a plan cell is seen when a projected point lies this
    #                            close (observed.py); the blueprint labels only cells seen or
    #                            within the room's extent (inside)
    ray_every: int = 64  # every n-th point casts a free-space ray from its camera (0 = none):
    #                      the cells it crosses were looked through, so they are in the room
    inside_close: float = 0.25  # metres: the room's extent closes gaps up to twice this wide
    fill_radius: float = 0.3  # metres: within the room's extent the plan is labelled up to
    #                            this far from a point (BluNF fills the gaps between them);
    #                            farther cells stay unknown (255) rather than guessed
    # views with index % k == k // 2 are held out of the plan (scored by evaluate's
    # heldout_pacc) when the frames carry labels; 0 = none (1 is refused: nothing left)
    holdout_every: int = 8
    # free space only where the view's own reading (the readings input: the depth the fusion
    # read) reaches, not through a hole in the fused surface: the free-space rays come from
    # the points their view read that far (points._read), and a view looks past the space
    # over a cell only where its reading reads past it too (observed.looked_past). From
    # photos: the 3-room home fwIoU 83.84 -> 84.05 (corner F1 0.96 -> 1.0), the 7-Scenes
    # kitchen 71.10 -> 72.02, the office 64.55 -> 64.56, the demo room 85.86 -> 85.87; the
    # sensor home 90.54 -> 90.33 (docs/figures.md#project-free-read)
    free_read: bool = True

    def __post_init__(self) -> None:
        check_config(self)


@dataclass(frozen=True)
class ProjectInputs:
    frames: Path  # frames.json of a capture with poses and depth (Capture.save)
    holdout: bool = True  # hold views out for heldout_pacc (the planner: no GT plan to score)
    # frames.json whose depth the fusion read (the sensor's, or the depth stage's from photos):
    # with free_read, the free-space rays and the views looking past a cell go only where a
    # view's own reading reaches (a hole in the fused surface is not space looked through)
    readings: Path | None = None


@dataclass(frozen=True)
class ProjectOutputs:
    STATS: ClassVar[str | None] = "project.json"  # its stats file: the report's facts
    # points.npz: xyz float32 [N, 3] offsets from origin float64 [3] (read_points adds them),
    # label uint8 [N], view int32 [N], instance int32 [N] (object instance, 0 = none; absent
    # from files written before it: read_instances gives zeros), classes
    points: Path
    grid: Path  # grid.json: the plan Grid (Grid.to_json) + "bounds" [xmin, ymin, xmax, ymax]
    # of the points it was padded from

    @classmethod
    def at(cls, out: Path) -> ProjectOutputs:
        """The outputs inside a finished project folder."""
        return cls(points=Path(out) / "points.npz", grid=Path(out) / "grid.json")

    @property
    def heldout(self) -> Path:
        """heldout.json beside the points: {"every": k, "views": [index], "stems": [stem]}."""
        return self.points.parent / "heldout.json"

    @property
    def observed(self) -> Path:
        """observed.npz beside the points: near, free, inside, labelled uint8 [H, W] and past
        uint16 [H, W] on the plan grid (observed.py)."""
        return self.points.parent / "observed.npz"

    @property
    def classes(self) -> Path:
        """classes.json beside the points: {"classes": {id: name}, "labelling": ...}."""
        return self.points.parent / "classes.json"


def check_config(cfg: ProjectConfig) -> None:
    """Every setting in range (at config load: before any stage runs)."""
    if cfg.holdout_every < 0 or cfg.holdout_every == 1:
        raise BlunfError(f"project.holdout_every must be 0 (off) or >= 2, got {cfg.holdout_every}")
    if cfg.stride < 0:
        raise BlunfError(f"project.stride must be >= 1, or 0 (auto), got {cfg.stride}")
    if not cfg.cell > 0:
        raise BlunfError(f"project.cell must be > 0 metres, got {cfg.cell}")
    if not 0 <= cfg.bounds_pct < 50:
        raise BlunfError(f"project.bounds_pct must be in [0, 50), got {cfg.bounds_pct}")
    if cfg.pad < 0:
        raise BlunfError(f"project.pad must be >= 0 metres, got {cfg.pad}")
    if (
        not (cfg.seen_radius > 0 and cfg.fill_radius > 0)
        or cfg.inside_close < 0
        or cfg.ray_every < 0
    ):
        raise BlunfError(
            f"project.seen_radius ({cfg.seen_radius}) and fill_radius ({cfg.fill_radius}) must "
            f"be > 0 metres, project.inside_close "
            f"({cfg.inside_close}) >= 0 and project.ray_every ({cfg.ray_every}) >= 0"
        )
    if cfg.labelling not in LABELLINGS:
        raise BlunfError(f"project.labelling must be one of {LABELLINGS}, got {cfg.labelling!r}")
    if cfg.occlusion not in OCCLUSIONS:
        raise BlunfError(f"project.occlusion must be one of {OCCLUSIONS}, got {cfg.occlusion!r}")
    if cfg.occlusion_cell < 0 or cfg.top_band < 0:
        raise BlunfError(
            f"project.occlusion_cell ({cfg.occlusion_cell}) and project.top_band "
            f"({cfg.top_band}) must be >= 0 metres"
        )
    if cfg.top_min_points < 1 or cfg.occlusion_shifts < 1:
        raise BlunfError(
            f"project.top_min_points ({cfg.top_min_points}) and project.occlusion_shifts "
            f"({cfg.occlusion_shifts}) must be >= 1"
        )
    if not cfg.floor_band < cfg.ceiling_cut:
        raise BlunfError(
            f"project.floor_band ({cfg.floor_band}) must be below "
            f"project.ceiling_cut ({cfg.ceiling_cut})"
        )

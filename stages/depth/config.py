"""Configuration and the input / output contract of the depth stage (photos only).

The stage's parts run in order: the plane sweep (`depth.stereo.*`, sweep.py), the plane fill
(where stereo read nothing, the room's planes), the field fill (`depth.field.*`, field.py: a
radiance field trained on what the parts before found, its render filling the holes where
other views confirm it) and the multi-view check of the result (`depth.check.*`,
consistency.py). These settings were `nerf.stereo.*`, `nerf.depth_check.*` and
`nerf.depth_render_scale` before; those keys fail naming their place here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from stages.common.errors import BlunfError
from stages.common.radiance.config import SamplingConfig, TrainingConfig
from stages.depth.planes.config import PlanesConfig

# depth sources, one uint8 per pixel of sources/<stem>.png
NONE, STEREO, PLANES, FIELD = 0, 1, 2, 3
SOURCES = {STEREO: "stereo", PLANES: "planes", FIELD: "field"}


@dataclass(frozen=True)
class StereoConfig:
    """Plane-sweep stereo among the photos (sweep.py): the photos-only depth's first part."""

    enabled: bool = True  # false: no sweep, the field fill learns depth from the photos and
    #                       the SfM tracks alone
    planes: int = 64  # depth planes, even in inverse depth between the view's track bounds
    #                 (docs/figures.md#depth-stereo-planes)
    plane_px: float = 0.0  # > 0: each view sweeps only as many planes (at most `planes`,
    #                 at least 8) as put one plane step at <= plane_px pixels of its widest
    #                 neighbour's image (disparity range = focal x baseline x (1/near -
    #                 1/far)): close neighbours need fewer planes; 0 = always `planes`
    refine: int = 16  # then per pixel this many planes across one coarse step either side
    #                   (0 or 1 = no refinement): a plane step is ~10 cm at 3 m here
    views: int = 4  # views each view is matched against (those overlapping it most)
    select_angle: float = 0.0  # > 0: degrees; rank those views by the angle their rays
    #   meet at too (consistency.overlap_order); 0 = overlap alone. 5: kitchen photos fwIoU
    #   68.6 -> 70.0, office 62.2 -> 60.2, demo 84.5 -> 84.3 (docs/figures.md#depth-stereo-
    #   select-angle)
    scale: int = 1  # depth maps at 1/scale of the photos' resolution (k x k binned); 0 = the
    #                 largest at which a pixel at the median track depth spans <= `cell`
    #                 (docs/figures.md#depth-stereo-scale)
    cell: float = 0.02  # metres: the plan's cell, for scale 0 (a finer depth map adds no
    #                     detail to the plan)
    coarse: int = 1  # the planes are swept at a further 1/coarse, the per-pixel refinement at
    #                  1/scale round that estimate (coarse to fine; needs refine >= 3)
    window: int = 7  # pixels: side of the correlation window (odd)
    max_cost: float = 0.4  # a reading needs 1 - ZNCC below this (ZNCC above 0.6)
    min_std: float = 0.02  # ... and this grey-level spread (0-1) in its window
    tol: float = 0.02  # relative depth within which other views confirm a reading
    agree: int = 2  # ... and this many of them must
    edge_px: int = 0  # > 0: drop the readings within this many pixels of a reading 10 %
    #                   farther: the near side of a depth edge, where a window over an
    #                   object's edge matched the object and carried it out over what lies
    #                   behind, and surfaces seen at a grazing angle (sweep.near_edge,
    #                   after the plane fill); 0 = keep them (docs/figures.md#depth-stereo-
    #                   edge-px)
    fuse: bool = True  # depth for fusion: the stereo (and plane) reading where there is one,
    #                    the field's render elsewhere; false: the field's render alone

    def __post_init__(self) -> None:
        if self.planes < 3 or self.views < 1 or self.refine == 2 or self.refine < 0:
            raise BlunfError(
                "depth.stereo.planes must be >= 3, depth.stereo.views >= 1 and "
                "depth.stereo.refine 0, 1 or >= 3, got "
                f"{self.planes}, {self.views}, {self.refine}"
            )
        if self.scale < 0 or self.coarse < 1 or (self.coarse > 1 and self.refine < 3):
            raise BlunfError(
                "depth.stereo.scale must be >= 0 and depth.stereo.coarse >= 1 (> 1 only with "
                f"refine >= 3), got {self.scale}, {self.coarse} (refine {self.refine})"
            )
        if not 0.0 <= self.plane_px < float("inf"):
            raise BlunfError(
                f"depth.stereo.plane_px must be a finite number >= 0, got {self.plane_px}"
            )
        if not 0 < self.cell < float("inf"):
            raise BlunfError(f"depth.stereo.cell must be a finite number > 0, got {self.cell}")
        if self.edge_px < 0:
            raise BlunfError(f"depth.stereo.edge_px must be >= 0, got {self.edge_px}")
        if self.window < 3 or self.window % 2 == 0:
            raise BlunfError(f"depth.stereo.window must be odd and >= 3, got {self.window}")
        if not 0 < self.max_cost <= 2:
            raise BlunfError(f"depth.stereo.max_cost must be in (0, 2], got {self.max_cost}")


@dataclass(frozen=True)
class DepthCheckConfig:
    """Drop readings the other views do not confirm (multi-view consistency,
    consistency.py), the last part before fusion."""

    enabled: bool = False  # run the check
    tol: float = 0.03  # relative depth difference within which two views agree
    agree: int = 1  # a reading is kept when at least this many views agree ...
    through: int = 0  # ... and at most this many see through it (a floater)
    views: int = 10  # each view is checked against the views overlapping it most


@dataclass(frozen=True)
class FieldFillConfig(TrainingConfig):
    """The field fill (field.py): a radiance field trained on the photos and the depth found
    so far; its render fills the holes where other views' readings confirm it. The field's
    own settings (`depth.field.field.*`, `.sampling.*`, `.train.*`, ...) are the nerf
    stage's sections (stages.common.radiance.config), with their own defaults here."""

    fill: bool | Literal["auto"] = "auto"  # true: always; false: never (the readings found
    #                 so far alone feed fusion); auto: only when they cover fewer than
    #                 `below` of the pixels (docs/figures.md#depth-field-fill)
    below: float = 0.5  # auto: the coverage under which the field trains
    check: int = 1  # a rendered reading is kept only where this many other views' readings
    #                 agree with it (depth.stereo.tol) and none sees through it (0, or too few
    #                 readings to train on: every rendered reading)
    #                 (docs/figures.md#depth-field-check)
    render_scale: int = 2  # depth rendered at 1/k (never finer than the sweep ran)
    # a rendered reading whose compositing weights spread along its ray by more than this
    # share of its depth (their standard deviation over the expected depth) is dropped: a
    # plain floor or wall the photos do not pin down, rendered as fog hanging in front of it
    # (render.py); 0 = off (docs/figures.md#depth-field-max-spread)
    max_spread: float = 0.0
    # > 0: the limit is this many times the median spread of the field's renders that agree
    # with stereo (within depth.stereo.tol) in this run, never under max_spread: a briefly
    # trained field spreads wide everywhere and gets a looser limit (spread.py); 0 = off
    # (docs/figures.md#depth-field-max-spread-agreeing)
    max_spread_agreeing: float = 0.0
    # divide each fill by the field's median ratio to stereo at its depth, measured beside
    # stereo in this run (debias.py): the field renders short (docs/depth.md, "Where the
    # kitchen's floor goes")
    debias: bool = False
    # the filling field's marching step: the scene box's diagonal / 256 (512 for fields that
    # edits and views render) (docs/figures.md#depth-field-sampling)
    sampling: SamplingConfig = dataclasses.field(
        default_factory=lambda: SamplingConfig(samples_across=256)
    )

    def __post_init__(self) -> None:
        if not 0.0 <= self.below <= 1.0:
            raise BlunfError(f"depth.field.below must be in [0, 1], got {self.below}")
        if self.check < 0:
            raise BlunfError(f"depth.field.check: must be >= 0, got {self.check}")
        if not 0.0 <= self.max_spread < float("inf"):
            raise BlunfError(
                f"depth.field.max_spread: must be a finite number >= 0, got {self.max_spread}"
            )
        if not 0.0 <= self.max_spread_agreeing < float("inf"):
            raise BlunfError(
                "depth.field.max_spread_agreeing: must be a finite number >= 0, got "
                f"{self.max_spread_agreeing}"
            )
        if self.render_scale < 1:
            raise BlunfError(f"depth.field.render_scale: must be >= 1, got {self.render_scale}")


@dataclass(frozen=True)
class DepthConfig:
    """Depth from the photos: sweep, plane fill, field fill, check."""

    # sections every implementation reads although one bears an implementation's name
    SHARED: ClassVar[tuple[str, ...]] = ("stereo", "field")
    impl: str = "stereo"  # "stereo": sweep, then fill; "field": the field fill alone (no
    #                       stereo, or no SfM tracks to bound the sweep: poses given)
    stereo: StereoConfig = dataclasses.field(default_factory=StereoConfig)
    planes: PlanesConfig = dataclasses.field(default_factory=PlanesConfig)
    field: FieldFillConfig = dataclasses.field(default_factory=FieldFillConfig)
    check: DepthCheckConfig = dataclasses.field(default_factory=DepthCheckConfig)
    threads: int = 0  # torch threads (0 = leave torch's setting)


@dataclass(frozen=True)
class DepthInputs:
    frames: Path  # frames.json (Capture) with poses; depth = the SfM tracks, if any


@dataclass(frozen=True)
class DepthOutputs:
    STATS: ClassVar[str | None] = "depth.json"  # its stats file: the report's facts
    stats: Path  # depth.json: each part's coverage, CPU-s and facts; by source
    frames: Path  # frames.json: the input capture with depth -> depth/<stem>.npy
    depth: Path  # depth/<stem>.npy: z-depth, float32 metres, 0 = none (fusion rescales)
    sources: Path  # sources/<stem>.png: uint8, same size: 0 none, 1 stereo, 2 planes, 3 field
    field: Path  # field/: the filling field (model.pt, nerf.json), when it trained

    @classmethod
    def at(cls, out: Path) -> DepthOutputs:
        """The outputs inside a finished depth folder."""
        out = Path(out)
        return cls(
            stats=out / "depth.json",
            frames=out / "frames.json",
            depth=out / "depth",
            sources=out / "sources",
            field=out / "field",
        )

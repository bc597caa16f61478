"""Configuration and the input / output contract of the edit stage.

Settings are nested by job: `edit.select.*` (how a plan selection becomes a 3-D extent),
`edit.render.*` (how the edited scene is drawn), `edit.refine.*` (the surface fused again
round each selection) and `edit.gif.*` (the orbit GIF). The flat keys of earlier versions
are listed in `EditConfig.RENAMED` and fail with their new name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

from stages.common.classes import FLOOR_NAME, UNKNOWN_NAME
from stages.common.errors import BlunfError

REMOVED_LABELS = (FLOOR_NAME, UNKNOWN_NAME)


def _metres(section: str, obj: object, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if not 0 <= v < float("inf"):
            raise BlunfError(f"edit.{section}.{name}: must be a finite number >= 0 metres, got {v}")


def _positive(section: str, obj: object, *names: str) -> None:
    for name in names:
        if getattr(obj, name) < 1:
            raise BlunfError(f"edit.{section}.{name}: must be >= 1, got {getattr(obj, name)}")


def _scale(section: str, v: float) -> None:
    if not 0 < v <= 4:
        raise BlunfError(f"edit.{section}.scale: must be in (0, 4], got {v}")


@dataclass(frozen=True)
class SelectConfig:
    """How a selection on the plan becomes a 3-D extent over the fused mesh."""

    floor_class: str = FLOOR_NAME  # name of the floor class in the plan's class table
    floor_band: float = 0.05  # metres: geometry within this of z = 0 is floor; a floor selection
    #                           is the slab |z| <= floor_band, an object's top ignores it
    floor_clear: float = 0.02  # metres: an object's extent starts this high (floor under it kept)
    gap: float = 0.3  # metres: a vertical gap this large separates an object from what is above
    min_run: float = 0.05  # fraction of a footprint's vertices a vertical run needs to count as
    #                        the object (smaller runs below it are noise)
    top_margin: float = 0.05  # metres added above an object's measured top
    pad: float = 0.02  # metres the footprint grows by sideways (the field's blur at object sides)

    def __post_init__(self) -> None:
        _metres("select", self, "floor_band", "floor_clear", "gap", "top_margin", "pad")
        if not 0 <= self.min_run <= 1:
            raise BlunfError(f"edit.select.min_run: must be in [0, 1], got {self.min_run}")


@dataclass(frozen=True)
class RenderConfig:
    """How the edited scene is drawn (the stage's views, `blunf render`, the studio)."""

    # "volume": every ray marched through the field; "surface": the fused mesh ray-cast and
    # the field asked at the hit (stages/edit/surface.py: the studio's fast path)
    path: Literal["volume", "surface"] = "volume"
    scale: float = 1.0  # renders at this fraction of the frames' resolution
    mask_threshold: float = 0.5  # a pixel is selected when its weight inside the extent >= this
    chunk: int = 16384  # rays per forward pass
    threads: int = 0  # torch threads while rendering (0 = leave torch's setting)

    def __post_init__(self) -> None:
        _scale("render", self.scale)
        _positive("render", self, "chunk")
        if not 0 <= self.mask_threshold <= 1:
            raise BlunfError(
                f"edit.render.mask_threshold: must be in [0, 1], got {self.mask_threshold}"
            )


@dataclass(frozen=True)
class RefineConfig:
    """The depth round each selection (not a floor) fused again, finer, to outline the edit
    in the surface path (stages/edit/refine.py; needs EditInputs.depth)."""

    voxel: float = 0.0  # metres; 0 = off
    trunc: float = 2.0  # voxels: thinner than the thin parts (chair legs ~3.5 cm)
    margin: float = 0.05  # metres each box grows by round its selection's extent

    def __post_init__(self) -> None:
        _metres("refine", self, "voxel", "margin")
        if not 1 <= self.trunc < float("inf"):
            raise BlunfError(f"edit.refine.trunc: must be >= 1 voxels, got {self.trunc}")


@dataclass(frozen=True)
class GifConfig:
    """The orbit GIF when the spec's views are frame indices (a spec's own orbit is the views
    themselves, at render.scale)."""

    frames: int = 24  # frames of the orbit
    scale: float = 0.5  # rendered at this fraction of the frames' resolution
    ms: int = 100  # milliseconds per frame

    def __post_init__(self) -> None:
        _scale("gif", self.scale)
        _positive("gif", self, "frames", "ms")


@dataclass(frozen=True)
class EditConfig:
    """How a selection becomes a 3-D extent, and how the edited scene is rendered and scored."""

    impl: Literal["nerf"] = "nerf"  # registry key in stages.edit.IMPLS (edits applied while
    #                                 rendering)
    # plan cells of removed selections become floor (when the plan has it and the selection
    # is not floor) or unknown (255); checked against the class vocabulary's names
    removed_label: str = FLOOR_NAME
    change_threshold: float = 0.02  # a pixel changed when a channel moved more than this (RGB 0-1)
    select: SelectConfig = field(default_factory=SelectConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    gif: GifConfig = field(default_factory=GifConfig)

    # the flat keys of earlier versions -> their place now (an old key fails naming it)
    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"select.{k}" for k in (
            "floor_class", "floor_band", "floor_clear", "gap", "min_run", "top_margin", "pad")},
        "render": "render.path",
        "render_scale": "render.scale",
        **{k: f"render.{k}" for k in ("mask_threshold", "chunk", "threads")},
        **{f"refine_{k}": f"refine.{k}" for k in ("voxel", "trunc", "margin")},
        **{f"gif_{k}": f"gif.{k}" for k in ("frames", "scale", "ms")},
    }  # fmt: skip

    def __post_init__(self) -> None:
        if not 0 <= self.change_threshold <= 1:
            raise BlunfError(
                f"edit.change_threshold: must be in [0, 1], got {self.change_threshold}"
            )
        if self.removed_label not in REMOVED_LABELS:
            raise BlunfError(
                f"edit.removed_label: must be one of {REMOVED_LABELS}, got {self.removed_label!r}"
            )


@dataclass(frozen=True)
class EditInputs:
    spec: Path  # the edit spec (YAML, DESIGN.md "Edit spec")
    blueprint: Path  # blueprint.npz the selections refer to
    model: Path  # model.pt of the nerf stage
    mesh: Path  # mesh.ply of the fusion stage (z up, floor at z = 0)
    frames: Path  # frames.json: the posed frames `views` indexes
    gt: Path | None = None  # ground-truth folder (instances/<stem>.png, instances.json), if any
    depth: Path | None = None  # frames.json with the depth the fusion stage read (sensor or
    #                            stereo; for edit.refine.voxel), None: no refinement
    textures: tuple[Path, ...] = ()  # the texture files the spec names (`spec_textures(spec)`),
    #                                  listed so that a changed texture changes the cache key


@dataclass(frozen=True)
class EditOutputs:
    STATS: ClassVar[str | None] = "edit.json"  # its stats file: the report's facts
    views: Path  # views/<name>.png: before | after side by side, per requested view
    masks: Path  # masks/<name>_<edit>.png: each selection's mask in each view (0 / 255)
    gif: Path  # orbit.gif: the edited scene along an orbit
    blueprint: Path  # blueprint_edited.npz (Blueprint.save)
    blueprint_png: Path  # blueprint_edited.png (export's plan picture)
    mesh: Path  # mesh_edited.ply: the fused mesh with the edits applied
    stats: Path  # edit.json: per edit its selection, extent and metrics; `metrics.edit`

    @classmethod
    def at(cls, out: Path) -> EditOutputs:
        """The outputs inside a finished edit folder."""
        out = Path(out)
        return cls(
            views=out / "views",
            masks=out / "masks",
            gif=out / "orbit.gif",
            blueprint=out / "blueprint_edited.npz",
            blueprint_png=out / "blueprint_edited.png",
            mesh=out / "mesh_edited.ply",
            stats=out / "edit.json",
        )

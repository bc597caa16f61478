"""Configuration and the input / output contract of the edit stage."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.common.classes import FLOOR_NAME, UNKNOWN_NAME
from stages.common.errors import BlunfError

REMOVED_LABELS = (FLOOR_NAME, UNKNOWN_NAME)
RENDERS = ("volume", "surface")


@dataclass(frozen=True)
class EditConfig:
    """How a selection becomes a 3-D extent, and how the edited scene is rendered and scored."""

    impl: str = "nerf"  # registry key in stages.edit.IMPLS: "nerf" (edits applied while rendering)
    floor_class: str = FLOOR_NAME  # name of the floor class in the plan's class table
    floor_band: float = 0.05  # metres: geometry within this of z = 0 is floor; a floor selection
    #                           is the slab |z| <= floor_band, an object's top ignores it
    floor_clear: float = 0.02  # metres: an object's extent starts this high (floor under it kept)
    gap: float = 0.3  # metres: a vertical gap this large separates an object from what is above
    min_run: float = 0.05  # fraction of a footprint's vertices a vertical run needs to count as
    #                        the object (smaller runs below it are noise)
    top_margin: float = 0.05  # metres added above an object's measured top
    pad: float = 0.02  # metres the footprint grows by sideways (the field's blur at object sides)
    removed_label: str = FLOOR_NAME  # plan cells of removed selections become floor (when the
    #                                 plan has it and the selection is not floor) or unknown (255)
    mask_threshold: float = 0.5  # a pixel is selected when its weight inside the extent >= this
    change_threshold: float = 0.02  # a pixel changed when a channel moved more than this (RGB 0-1)
    render_scale: float = 1.0  # renders at this fraction of the frames' resolution
    # "volume": every ray marched through the field; "surface": the fused mesh ray-cast and
    # the field asked at the hit (stages/edit/surface.py: the studio's fast path), so what an
    # edit changes is outlined by the mesh, and the colours need a less trained field
    render: str = "volume"
    # > 0: the depth round each selection (not a floor) is fused again at this voxel
    # (metres) with a truncation of refine_trunc voxels, and that surface outlines the edit
    # in the fast render path (stages/edit/refine.py; needs EditInputs.depth); 0 = off
    refine_voxel: float = 0.0
    refine_trunc: float = 2.0  # voxels: thinner than the thin parts (chair legs ~3.5 cm)
    refine_margin: float = 0.05  # metres each box grows by round its selection's extent
    gif_frames: int = 24  # frames of the orbit GIF when the spec's views are frame indices
    gif_scale: float = 0.5  # ... rendered at this fraction of the frames' resolution (a
    #                         spec's own orbit is the views themselves, at render_scale)
    gif_ms: int = 100  # milliseconds per GIF frame
    chunk: int = 16384  # rays per forward pass
    threads: int = 0  # torch threads while rendering (0 = leave torch's setting)

    def __post_init__(self) -> None:
        for name in ("floor_band", "floor_clear", "gap", "top_margin", "pad"):
            v = getattr(self, name)
            if not 0 <= v < float("inf"):
                raise BlunfError(f"edit.{name}: must be a finite number >= 0 metres, got {v}")
        for name in ("refine_voxel", "refine_margin"):
            if not 0 <= getattr(self, name) < float("inf"):
                raise BlunfError(
                    f"edit.{name}: must be a finite number >= 0 metres, got {getattr(self, name)}"
                )
        if not 1 <= self.refine_trunc < float("inf"):
            raise BlunfError(f"edit.refine_trunc: must be >= 1 voxels, got {self.refine_trunc}")
        for name in ("min_run", "mask_threshold", "change_threshold"):
            v = getattr(self, name)
            if not 0 <= v <= 1:
                raise BlunfError(f"edit.{name}: must be in [0, 1], got {v}")
        if self.removed_label not in REMOVED_LABELS:
            raise BlunfError(
                f"edit.removed_label: must be one of {REMOVED_LABELS}, got {self.removed_label!r}"
            )
        if self.render not in RENDERS:
            raise BlunfError(f"edit.render: must be one of {RENDERS}, got {self.render!r}")
        for name in ("render_scale", "gif_scale"):
            if not 0 < getattr(self, name) <= 4:
                raise BlunfError(f"edit.{name}: must be in (0, 4], got {getattr(self, name)}")
        for name in ("gif_frames", "gif_ms", "chunk"):
            if getattr(self, name) < 1:
                raise BlunfError(f"edit.{name}: must be >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class EditInputs:
    spec: Path  # the edit spec (YAML, DESIGN.md "Edit spec")
    blueprint: Path  # blueprint.npz the selections refer to
    model: Path  # model.pt of the nerf stage
    mesh: Path  # mesh.ply of the fusion stage (z up, floor at z = 0)
    frames: Path  # frames.json: the posed frames `views` indexes
    gt: Path | None = None  # ground-truth folder (instances/<stem>.png, instances.json), if any
    depth: Path | None = None  # frames.json with the depth the fusion stage read (sensor or
    #                            stereo; for edit.refine_voxel), None: no refinement
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

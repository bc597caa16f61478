"""Configuration, inputs and outputs of the layout stage (the plan as an architect draws it)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class LayoutConfig:
    """How walls, rooms, openings and object footprints are read off the blueprint."""

    impl: str = "walls"  # registry key in stages.layout.IMPLS
    max_opening: float = 1.3  # metres: a gap in a wall line up to this wide is an opening
    #                           (the wall line runs through it); wider gaps split the walls
    max_passage: float = 2.1  # metres: wider gaps up to this wide close the wall line too
    #                           where the floor runs through them and no wall lies beside
    #                           them across (a passage, not a ragged face); 0 = off
    min_run: float = 0.3  # metres: only stretches of wall at least this long close a gap
    max_thickness: float = 0.5  # metres: a wall band deeper than this (the plan calls all
    #                             the space outside the room wall) gets default_thickness
    notch: float = 0.3  # metres: the room outline closes notches narrower than this (stray
    #                     wall cells along the face)
    min_opening: float = 0.4  # metres: narrower gaps in a wall are no opening
    door_max: float = 1.2  # metres: an opening up to this wide is a door, wider a passage
    tolerance: float = 0.03  # metres: the room outline is simplified within this
    min_wall: float = 0.2  # metres: outline edges shorter than this are merged away
    min_free_wall: float = 1.0  # metres: edges off the room's directions shorter than this
    #                             are merged away too (ragged faces of a noisy plan)
    snap_deg: float = 10.0  # an edge within this angle of the room's two directions takes
    #                         that direction; others keep their own (free) angle
    face_offset: float = 0.5  # cells: the traced faces move out by this much. A projected
    #                           plan (BluNF, MVR) labels wall the cell the wall's surface falls
    #                           in, whose centre is the face on average: 0.5; a plan of
    #                           vertical rays through the cell centres (gt/blueprint.npz): 0
    room_split_h: float = 0.3  # metres: the inside splits into rooms where it narrows to a
    #                            door (rooms.py): a room's widest point stands this much over
    #                            the narrowing (its distance maximum over the saddle); 0 = off
    min_room_area: float = 1.0  # m²: a closed space smaller than this is no room
    min_object_area: float = 0.02  # m²: smaller object footprints are left out
    box_slack: float = 0.15  # an object leaving less than this share of its oriented
    #                          rectangle empty is drawn as the rectangle, otherwise as its
    #                          outline (a round plant leaves 21 %)
    default_thickness: float = 0.1  # metres: a wall whose thickness the plan does not show

    def __post_init__(self) -> None:
        for name in (
            "max_opening",
            "door_max",
            "tolerance",
            "min_wall",
            "default_thickness",
            "min_run",
            "max_thickness",
            "notch",
            "min_free_wall",
            "min_opening",
        ):
            if not getattr(self, name) > 0:
                raise BlunfError(f"layout.{name}: must be > 0, got {getattr(self, name)}")
        if not 0 <= self.snap_deg < 45:
            raise BlunfError(f"layout.snap_deg: must be in [0, 45), got {self.snap_deg}")
        if not 0 <= self.box_slack < 1:
            raise BlunfError(f"layout.box_slack: must be in [0, 1), got {self.box_slack}")
        for name in (
            "min_room_area",
            "min_object_area",
            "face_offset",
            "max_passage",
            "room_split_h",
        ):
            if not getattr(self, name) >= 0:
                raise BlunfError(f"layout.{name}: must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class LayoutInputs:
    blueprint: Path  # blueprint.npz (labels, cell, origin, classes, optional instances)
    mesh: Path | None = None  # mesh.ply, world frame: object heights (None: heights unknown)


@dataclass(frozen=True)
class LayoutOutputs:
    STATS: ClassVar[str | None] = "layout.json"  # counts (and why empty): the report's facts
    plan_json: Path  # plan.json: rooms, walls, openings, objects as vectors in metres
    plan_svg: Path  # plan.svg: the plan drawn as an architect would
    plan_dxf: Path  # plan.dxf: layers WALLS, OPENINGS, OBJECTS, DIMENSIONS, TEXT

    @classmethod
    def at(cls, out: Path) -> LayoutOutputs:
        out = Path(out)
        return cls(out / "plan.json", out / "plan.svg", out / "plan.dxf")

"""The class vocabulary: class names, their ids in each labelling, their colours, and which
classes are the room's structure. Every other module names a class through this one.

A plan's class table (`Blueprint.classes`, id -> name) comes from one of three labellings:
the semantics stage's geometry (GEOMETRY: floor, wall, ceiling, object), the project stage's
height bands (HEIGHT: floor, occupied), or a capture's own labels (the procedural room's are
SYNTH; a real capture's are its dataset's). The structure ids are the same in all three.
"""

from __future__ import annotations

import colorsys

# ---- names: what a plan's class table says ------------------------------------------------
FLOOR_NAME = "floor"
WALL_NAME = "wall"
CEILING_NAME = "ceiling"
OBJECT_NAME = "object"  # the geometry's one class for whatever stands in the room
OCCUPIED_NAME = "occupied"  # the height bands' one class above the floor
UNKNOWN_NAME = "unknown"  # the name shown for UNKNOWN (unseen, or outside every room)

STRUCTURE = (FLOOR_NAME, WALL_NAME, CEILING_NAME)  # the room's shell; the rest are objects
CATCH_ALL = (OBJECT_NAME, OCCUPIED_NAME)  # coarse classes that stand for every object class
KEPT = (FLOOR_NAME, WALL_NAME)  # structure a coarse labelling keeps apart from the catch-all

# ---- ids ------------------------------------------------------------------------------------
UNKNOWN = 255  # blueprint / label value for unknown or unseen (never a class of a table)
FLOOR, WALL, CEILING = 0, 1, 2  # the same in every labelling made here
OBJECT = 3  # GEOMETRY
OCCUPIED = 1  # HEIGHT
TABLE, CHAIR, SOFA, CABINET, BED, PLANT = range(3, 9)  # SYNTH

GEOMETRY = {FLOOR: FLOOR_NAME, WALL: WALL_NAME, CEILING: CEILING_NAME, OBJECT: OBJECT_NAME}
GEOMETRY_IGNORE = (CEILING,)  # labelled in the views, never projected to the plan
HEIGHT = {FLOOR: FLOOR_NAME, OCCUPIED: OCCUPIED_NAME}
SYNTH = {
    FLOOR: FLOOR_NAME,
    WALL: WALL_NAME,
    CEILING: CEILING_NAME,
    TABLE: "table",
    CHAIR: "chair",
    SOFA: "sofa",
    CABINET: "cabinet",
    BED: "bed",
    PLANT: "plant",
}
SYNTH_IGNORE = (CEILING,)  # never projected to the plan

# ---- colours --------------------------------------------------------------------------------
# the procedural room's base colours (linear RGB in [0, 1]); each instance a jittered copy
SYNTH_COLORS = {
    FLOOR: (0.62, 0.48, 0.34),
    WALL: (0.78, 0.76, 0.70),
    CEILING: (0.85, 0.85, 0.85),
    TABLE: (0.55, 0.33, 0.18),
    CHAIR: (0.30, 0.42, 0.62),
    SOFA: (0.62, 0.22, 0.24),
    CABINET: (0.80, 0.70, 0.45),
    BED: (0.35, 0.60, 0.50),
    PLANT: (0.25, 0.55, 0.20),
}
# a plan's colours: Kelly's colours of maximum contrast (greys, black and white left out),
# indexed by class id
PALETTE = [
    (243, 195, 0),
    (135, 86, 146),
    (243, 132, 0),
    (161, 202, 241),
    (190, 0, 50),
    (194, 178, 128),
    (0, 136, 86),
    (230, 143, 172),
    (0, 103, 165),
    (249, 147, 121),
    (96, 78, 151),
    (246, 166, 0),
    (179, 68, 108),
    (220, 211, 0),
    (136, 45, 23),
    (141, 182, 0),
    (101, 69, 34),
    (226, 88, 34),
    (43, 61, 38),
]
UNKNOWN_COLOR = (240, 240, 240)  # unseen / outside cells: blank (a paper grey)


def class_color(cid: int) -> tuple[int, int, int]:
    """The fixed RGB colour (0-255) of a class id on a plan (UNKNOWN_COLOR for UNKNOWN)."""
    if cid == UNKNOWN:
        return UNKNOWN_COLOR
    if 0 <= cid < len(PALETTE):
        return PALETTE[cid]
    r, g, b = colorsys.hsv_to_rgb((cid * 0.618033988749895) % 1.0, 0.7, 0.85)  # golden-ratio hue
    return (round(r * 255), round(g * 255), round(b * 255))


def ids_named(classes: dict[int, str], *names: str) -> list[int]:
    """The ids of a class table whose name is one of `names`."""
    return [k for k, v in classes.items() if v in names]


def label_name(classes: dict[int, str], cid: int) -> str:
    """A label's name in a class table: UNKNOWN_NAME for UNKNOWN, `class <id>` when missing."""
    return UNKNOWN_NAME if cid == UNKNOWN else classes.get(cid, f"class {cid}")

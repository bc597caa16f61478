"""Class ids, names and base colours of the procedural room."""

FLOOR, WALL, CEILING, TABLE, CHAIR, SOFA, CABINET, BED, PLANT = range(9)
CLASSES = {
    FLOOR: "floor",
    WALL: "wall",
    CEILING: "ceiling",
    TABLE: "table",
    CHAIR: "chair",
    SOFA: "sofa",
    CABINET: "cabinet",
    BED: "bed",
    PLANT: "plant",
}
IGNORE = (CEILING,)  # never projected to the plan

# Base colours (linear RGB in [0, 1]); each instance gets a jittered copy.
PALETTE = {
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

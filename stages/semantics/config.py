"""Configuration, inputs and outputs of the semantics stage (classes derived from geometry)."""

from __future__ import annotations

import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class PlanesConfig:
    """Floor, ceiling and wall planes: RANSAC over the mesh's triangles (segment.py)."""

    max_tilt_deg: float = 15.0  # a triangle is horizontal when its normal is within this angle
    #                             of z, vertical when within this angle of the horizontal
    plane_dist: float = 0.03  # metres: RANSAC inlier distance; unlabelled triangles this close
    #                           to a floor, wall or ceiling plane (within its extent) join it
    ransac_iters: int = 1000  # RANSAC iterations per plane
    ransac_points: int = 5_000  # planes are fitted on at most this many triangle centres
    #                              (a seeded sample); inliers are counted on all of them
    max_planes: int = 24  # at most this many planes are fitted per kind (floor, ceiling, wall)
    floor_max_z: float = 0.25  # floor: horizontal, facing up, centre within this of z = 0 (m)
    ceiling_min_z: float = 1.9  # ceiling: horizontal, facing down, centre above this (m)
    min_area: float = 0.2  # m²: a horizontal plane smaller than this is not floor/ceiling

    def __post_init__(self) -> None:
        if not 0 < self.max_tilt_deg < 45:
            raise BlunfError(
                f"semantics.planes.max_tilt_deg: must be in (0, 45), got {self.max_tilt_deg}"
            )
        _positive(self, "planes", ("plane_dist",))
        _at_least_one(self, "planes", ("ransac_iters", "max_planes"))
        if self.ransac_points < 3:
            raise BlunfError(
                f"semantics.planes.ransac_points: must be >= 3, got {self.ransac_points}"
            )
        _non_negative(self, "planes", ("min_area",))
        if not 0 <= self.floor_max_z < self.ceiling_min_z:
            raise BlunfError(
                "semantics.planes: need 0 <= floor_max_z < ceiling_min_z, got "
                f"{self.floor_max_z} and {self.ceiling_min_z}"
            )


@dataclass(frozen=True)
class WallsConfig:
    """Which vertical planes are walls (segment.py), and the wall fill (wallfill.py)."""

    min_height: float = 1.0  # a wall's inliers span at least this in z (5-95 %, metres)
    #                          (docs/figures.md#semantics-wall-bounds)
    min_length: float = 1.0  # ... and at least this along the floor (5-95 %, metres)
    min_area: float = 0.6  # ... and cover at least this many m²
    # ... and stand within this many degrees of upright on the floor (of the floor plane's
    # normal's perpendicular; z without a floor); 90 = off. Every wall of the real captures'
    # sensor runs and of the procedural rooms measured leans under 1 degree off its floor;
    # the office from photos gave a plane leaning 5-7 degrees across its sofa back and the
    # wall above it, 0.05-0.2 m before the wall. 90 -> 3 against the sensor at SfM poses,
    # with the views' point walls counted as walls behind (`behind`): office plan fwIoU 63.5
    # -> 65.1 (floor 68.9 -> 71.9, wall 36.4 -> 41.5; this alone 59.9: the whiteboard
    # before the wall, upright, became the wall); honest procedural room, kitchen, 3-room
    # photos home and every sensor reference the same to the digit
    # (docs/figures.md#semantics-max-lean)
    max_lean_deg: float = 3.0
    # metres: a wall plane with another facing the same way behind it, this close, along half
    # its length, is no wall (blinds, cubicle panels, tall cabinets before the wall); a wall
    # from the views' points counts, from beyond its dist (a whiteboard before a plain wall
    # photos leave in patches); 0 = off (docs/figures.md#semantics-walls-behind)
    behind: float = 0.6
    # metres: what lies from this close before a surface hanging before a wall to the wall
    # behind it is its frame or stand, unknown as it is; a surface hanging this close to the
    # wall (blinds) is wall; 0 = off (docs/figures.md#semantics-hanger-slab)
    hanger_slab: float = 0.1
    # rays that hit nothing and cross a wall inside its extent are wall there (wallfill.py;
    # needs floor_fill) (docs/figures.md#semantics-wall-fill)
    fill: bool = False

    def __post_init__(self) -> None:
        _positive(self, "walls", ("min_height", "min_length"))
        _non_negative(self, "walls", ("min_area", "behind", "hanger_slab", "max_lean_deg"))


@dataclass(frozen=True)
class ObjectsConfig:
    """Object clusters of what is left (segment.py) and their pieces (pieces.py)."""

    cluster_eps: float = 0.08  # metres: DBSCAN radius joining object surfaces (run on voxels
    #                            of cluster_eps / 2, one point per occupied voxel)
    cluster_min_points: int = 3  # DBSCAN: voxels within cluster_eps for a core voxel; voxels
    #                              DBSCAN calls noise are labelled unknown (255)
    min_area: float = 0.01  # m²: smaller clusters are noise, labelled unknown (255)
    # metres: a cluster whose lowest point is higher above the floor (or above the top of an
    # object it rests on) is unknown (255) (docs/figures.md#semantics-max-gap)
    max_gap: float = 0.3
    # m²: a cluster resting on an object covers at least this
    # (docs/figures.md#semantics-rest-min-area)
    rest_min_area: float = 0.05
    # a cluster above max_gap (of at least rest_min_area) under less than this share of
    # whose plan cells the mesh holds any surface stands on something no view saw (objects.
    # _stands_hidden); 0 = off
    hidden_stand: float = 0.0
    # a cluster above max_gap that faces up over at least table_min_top m² and a third its
    # area, at a median height of at most table_max_top, is an object all the same (a table
    # whose legs no view fused); 0 = off (docs/figures.md#semantics-tables)
    table_max_top: float = 1.1  # metres above the floor
    table_min_top: float = 0.15  # m²
    # a cluster is split into pieces where its top steps by more than piece_step, on cells of
    # piece_cell; a piece narrower than piece_min_width joins its neighbour (pieces.py);
    # 0 = off: a cluster is one instance (docs/figures.md#semantics-pieces)
    piece_step: float = 0.1  # metres
    piece_cell: float = 0.05  # metres
    piece_min_width: float = 0.3  # metres
    # object triangles outside the room's footprint (the floor fill's) are unknown
    # (docs/figures.md#semantics-outside-unknown)
    outside_unknown: bool = False

    def __post_init__(self) -> None:
        _positive(self, "objects", ("cluster_eps", "piece_cell", "piece_min_width"))
        _at_least_one(self, "objects", ("cluster_min_points",))
        sizes = ("min_area", "max_gap", "rest_min_area", "piece_step", "hidden_stand")
        _non_negative(self, "objects", (*sizes, "table_max_top", "table_min_top"))


@dataclass(frozen=True)
class FloorFillConfig:
    """The floor seen through holes in the fused surface (floorfill.py).

    Rays that pass through every surface and through no wall and cross the floor plane
    inside the room (the hole-filled footprint of the floor and walls, on cells of `cell`
    metres) are labelled floor at that crossing. The views then get their depth from this
    stage (depth/<stem>.npy). Figures: docs/figures.md#semantics-floor-fill."""

    enabled: bool = True
    cell: float = 0.05
    # a mesh with no floor plane is filled at z = 0 inside the convex hull of the surface and
    # the cameras, by rays at least min_drop_deg below the horizontal crossing within reach
    # (docs/figures.md#semantics-floor-fill-no-plane)
    no_plane: bool = True
    min_drop_deg: float = 30.0  # degrees below the horizontal
    reach: float = 3.0  # metres from the camera, along the floor
    # with a floor plane too, the room is that hull within that reach rather than the floor
    # and wall triangles' footprint (docs/figures.md#semantics-floor-fill-hull)
    hull: bool = False
    # with hull and a floor plane found, rays are bounded by that reach as without one
    # (docs/figures.md#semantics-floor-fill-hull-reach)
    hull_reach: bool = True
    # metres: a view's own reading on the floor plane this far or more beyond the surface its
    # ray hits is floor seen past the surface's fattened rim (floorfill.floor_past; needs the
    # readings input); 0 = off (docs/figures.md#semantics-floor-fill-past)
    past: float = 0.1

    def __post_init__(self) -> None:
        _positive(self, "floor_fill", ("cell", "reach"))
        _non_negative(self, "floor_fill", ("past",))
        if not 0 <= self.min_drop_deg < 90:
            raise BlunfError(
                f"semantics.floor_fill.min_drop_deg: must be in [0, 90), got {self.min_drop_deg}"
            )


@dataclass(frozen=True)
class PointWallsConfig:
    """Walls from the points the views saw (pointwalls.py), beside the mesh's.

    The SfM tracks and the depth readings fusion read (photos only). Along each of the
    room's four directions, the plane holding the most readings (over min_height x
    walls.min_length and min_area) with at most max_beyond of them beyond it and the cameras
    inside, extended along itself over the free space that did not see through it, up to at
    least planes.ceiling_min_z; mesh triangles within dist join it, rays that hit nothing
    and cross it are wall there (as walls.fill) and no floor is filled beyond it.
    On in configs/phone.yaml; off here (sensor depth has its walls). Figures:
    docs/figures.md#semantics-point-walls."""

    enabled: bool = False
    dist: float = 0.05  # metres: a reading this close to the plane lies on it
    min_height: float = 0.5  # metres in z (5-95 %) the readings span at least
    max_beyond: float = 0.2  # readings beyond the plane per reading on it
    # a reading is beyond the plane when past it by more than dist + beyond_rel x its range
    # from its camera (depth from photos errs in proportion to the range); 0: by dist
    # (docs/figures.md#semantics-point-walls-beyond-rel)
    beyond_rel: float = 0.0

    # m²: the 10 cm cells (along it x height) its readings cover at least
    # (docs/figures.md#semantics-point-walls-area)
    min_area: float = 1.0
    # the walls between rooms too: every face of readings, per plane and stretch, that no
    # ray from the cameras on its side crossed (innerwalls.py)
    # (docs/figures.md#semantics-point-walls-inner)
    inner: bool = True

    def __post_init__(self) -> None:
        _positive(self, "point_walls", ("dist", "min_height"))
        _non_negative(self, "point_walls", ("max_beyond", "min_area", "beyond_rel"))


@dataclass(frozen=True)
class SemanticsConfig:
    """How the fused mesh is split into floor, walls, ceiling and object instances."""

    impl: Literal["geometry", "height"] = "geometry"  # "geometry": planes and clusters of the
    #                         fused mesh; "height": no stage, the project stage labels points
    #                         by height bands
    seed: int = 0  # seed of the RANSAC sample and of its hypotheses
    planes: PlanesConfig = field(default_factory=PlanesConfig)
    walls: WallsConfig = field(default_factory=WallsConfig)
    objects: ObjectsConfig = field(default_factory=ObjectsConfig)
    floor_fill: FloorFillConfig = field(default_factory=FloorFillConfig)
    point_walls: PointWallsConfig = field(default_factory=PointWallsConfig)

    def __post_init__(self) -> None:
        known = typing.get_args(typing.get_type_hints(type(self))["impl"])
        if self.impl not in known:
            raise BlunfError(f"semantics.impl: {self.impl!r} unknown (known: {', '.join(known)})")

    # the flat keys of earlier versions -> their place now (an old key fails naming it)
    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"planes.{k}" for k in (
            "max_tilt_deg", "plane_dist", "ransac_iters", "ransac_points", "max_planes",
            "floor_max_z", "ceiling_min_z")},
        "plane_min_area": "planes.min_area",
        **{f"wall_{k}": f"walls.{k}" for k in ("min_height", "min_length", "min_area", "behind")},
        "wall_fill": "walls.fill",
        **{k: f"objects.{k}" for k in (
            "cluster_eps", "cluster_min_points", "table_max_top", "table_min_top", "piece_step",
            "piece_cell", "piece_min_width", "outside_unknown")},
        "object_min_area": "objects.min_area",
        "object_max_gap": "objects.max_gap",
        "floor_fill": "floor_fill.enabled",
        **{f"floor_fill_{k}": f"floor_fill.{k}" for k in (
            "cell", "no_plane", "min_drop_deg", "reach", "hull", "hull_reach")},
        "point_walls": "point_walls.enabled",
        **{f"point_wall_{k}": f"point_walls.{k}" for k in (
            "dist", "min_height", "max_beyond", "min_area")},
    }  # fmt: skip


def _positive(cfg: object, group: str, names: tuple[str, ...]) -> None:
    for name in names:
        if not getattr(cfg, name) > 0:
            raise BlunfError(f"semantics.{group}.{name}: must be > 0, got {getattr(cfg, name)}")


def _non_negative(cfg: object, group: str, names: tuple[str, ...]) -> None:
    for name in names:
        if not getattr(cfg, name) >= 0:
            raise BlunfError(f"semantics.{group}.{name}: must be >= 0, got {getattr(cfg, name)}")


def _at_least_one(cfg: object, group: str, names: tuple[str, ...]) -> None:
    for name in names:
        if getattr(cfg, name) < 1:
            raise BlunfError(f"semantics.{group}.{name}: must be >= 1, got {getattr(cfg, name)}")


@dataclass(frozen=True)
class SemanticsInputs:
    frames: Path  # frames.json of the fused capture (poses, intrinsics, ray-cast depth)
    mesh: Path  # mesh.ply: the fused surface, world frame (z up, floor at z = 0)
    evidence: tuple[Path, ...] = ()  # frames.json files (same world) whose depth readings
    #                                  the point walls are found in (when point_walls.enabled)
    readings: Path | None = None  # frames.json whose depth the fusion read (the sensor's or
    #                               stereo's), same views: the floor seen past the surface


@dataclass(frozen=True)
class SemanticsOutputs:
    STATS: ClassVar[str | None] = "semantics.json"  # its stats file: the report's facts
    frames: Path  # frames.json: the input frames with `label` at labels/<stem>.png and
    #               `instance` at instances/<stem>.png, classes
    #               {0: floor, 1: wall, 2: ceiling, 3: object}, ignore [2]
    labels: Path  # labels/<stem>.png: uint8 class per pixel (255 = unknown or no surface)
    instances: Path  # instances/<stem>.png: object instance id per pixel (0 = none; uint8,
    #                  uint16 beyond 255 objects), numbered by decreasing area
    stats: Path  # semantics.json: planes, objects, triangles and pixels per class, seconds
    depth: Path  # depth/<stem>.npy: the mesh's depth with the floor seen through it, float32
    #              metres (floor_fill only; else the frames keep the fusion stage's depth)

    @classmethod
    def at(cls, out: Path) -> SemanticsOutputs:
        """The outputs inside a finished out folder."""
        out = Path(out)
        return cls(
            frames=out / "frames.json",
            labels=out / "labels",
            instances=out / "instances",
            stats=out / "semantics.json",
            depth=out / "depth",
        )

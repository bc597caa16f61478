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
    #                          (photos only: 0.7 with min_area 0.5 found the plain walls
    #                          stereo leaves in patches; Replica office0 fwIoU 36.2 -> 44.9,
    #                          wall IoU 21.3 -> 32.9; README)
    min_length: float = 1.0  # ... and at least this along the floor (5-95 %, metres)
    min_area: float = 0.6  # ... and cover at least this many m²
    behind: float = 0.6  # metres: a wall plane with another facing the same way behind it,
    #                      this close, along half its length, is no wall (blinds, cubicle
    #                      panels, tall cabinets before the wall); 0 = off. Replica office0
    #                      (sensor depth): its blinds, 0.31 m before the window wall, were a
    #                      wall (fwIoU against its own classes, padded, 84.4 -> 84.5 with what
    #                      hangs left unknown)
    # what lies within hanger_slab metres of a surface that hangs before a wall (see behind),
    # inside its extent, at any height, is its frame or stand (a whiteboard's legs and bottom
    # bar): unknown, as the surface is, not object. Replica office0 (sensor depth): a
    # whiteboard on a stand 0.31 m before the wall painted that depth object along its 2.3 m.
    # 0 = off
    hanger_slab: float = 0.1
    # rays that hit no surface and cross a wall plane inside the wall's extent (its inliers'
    # box along the wall, down to the floor) and inside the room are labelled wall at that
    # crossing (wallfill.py): plain walls that stereo left as holes. Needs floor_fill (the
    # room's footprint and the depth written with it). Replica office0 from its photos (30
    # frames, 320 px): plan fwIoU 36.2 -> 36.0, and 44.9 -> 44.4 with the lower wall bounds
    # above (README): the rays it fills are few beside the noise behind the walls; off
    fill: bool = False

    def __post_init__(self) -> None:
        _positive(self, "walls", ("min_height", "min_length"))
        _non_negative(self, "walls", ("min_area", "behind", "hanger_slab"))


@dataclass(frozen=True)
class ObjectsConfig:
    """Object clusters of what is left (segment.py) and their pieces (pieces.py)."""

    cluster_eps: float = 0.08  # metres: DBSCAN radius joining object surfaces (run on voxels
    #                            of cluster_eps / 2, one point per occupied voxel)
    cluster_min_points: int = 3  # DBSCAN: voxels within cluster_eps for a core voxel; voxels
    #                              DBSCAN calls noise are labelled unknown (255)
    min_area: float = 0.01  # m²: smaller clusters are noise, labelled unknown (255)
    max_gap: float = 0.3  # metres: a cluster whose lowest point is higher above the floor
    #                       does not stand on it (wall cabinet, lamp, fused noise) and is
    #                       labelled unknown (255), unless it rests on an object that does,
    #                       as high above its top (a plant on its stand, a lamp on a desk).
    #                       Replica office0 (sensor depth), geometry classes against its own
    #                       (padded): fwIoU 85.7 -> 88.0, floor 86.0 -> 89.0, object 84.7 ->
    #                       87.2; the 7-Scenes kitchen: two wall cabinets over appliances
    #                       became objects, its plan's observation figures the same
    rest_min_area: float = 0.05  # m²: a cluster resting on an object covers at least this
    #                              (photos-only stereo leaves fragments of 0.01-0.03 m² over
    #                              furniture: the demo room from its photos has two)
    # a cluster above max_gap that faces up over at least table_min_top m² and a third its
    # area, at a median height of at most table_max_top, is an object all the same: a table
    # whose legs or pedestal no view fused. Replica office0 (sensor depth, its 81 frames):
    # two such tables (1.37 and 0.43 m²) were unknown and their plan cells floor. 0 = off
    table_max_top: float = 1.1  # metres above the floor
    table_min_top: float = 0.15  # m²
    # a cluster is split into pieces where its top steps (pieces.py): plan cells of piece_cell
    # metres whose tops differ by at most piece_step are one piece, and a piece no disk of
    # piece_min_width fits in (a chair back, a kettle, a bevel) joins its neighbour. 7-Scenes
    # kitchen (sensor depth, 100 frames): 3 clusters of over 0.1 m² (8.2, 4.1, 2.4 m²) -> 5
    # pieces (4.3, 4.1, 3.9, 2.1, 2.0), the island (top 0.72 m) its own, the counters one
    # piece per run. The procedural demo room from its photos (11 pieces of furniture): 7
    # objects without pieces, 9 with, 17 with a width of 0.25 m (sofa and chair backs, which
    # stereo thickens, stood alone); fwIoU the same (84.7). 0 = off: a cluster is one instance
    piece_step: float = 0.1  # metres
    piece_cell: float = 0.05  # metres
    piece_min_width: float = 0.4  # metres
    # object triangles whose centre lies outside the room's footprint (the floor fill's: floor
    # and wall cells, closed and hole-filled) are labelled unknown: what photos-only depth
    # puts behind the walls (stereo noise, the far side of a window) is not in the room.
    # Replica office0 from its photos, with the lower wall bounds: fwIoU 44.9 -> 45.1
    outside_unknown: bool = False

    def __post_init__(self) -> None:
        _positive(self, "objects", ("cluster_eps", "piece_cell", "piece_min_width"))
        _at_least_one(self, "objects", ("cluster_min_points",))
        sizes = ("min_area", "max_gap", "rest_min_area", "piece_step")
        _non_negative(self, "objects", (*sizes, "table_max_top", "table_min_top"))


@dataclass(frozen=True)
class FloorFillConfig:
    """The floor seen through holes in the fused surface (floorfill.py).

    Rays that pass through every surface and through no wall and cross the floor plane
    inside the room (the hole-filled footprint of the floor and walls, on cells of `cell`
    metres) are labelled floor at that crossing. The views then get their depth from this
    stage (depth/<stem>.npy). Photos-only synthetic rooms: fwIoU 85.3 -> 85.5 (default room),
    78.1 -> 84.6 (seed 3); with their exact depth 90.3 -> 90.4, 85.5 -> 86.0."""

    enabled: bool = True
    cell: float = 0.05
    # a mesh with no floor plane (photos alone: stereo finds nothing on a plain floor) is
    # filled at z = 0, the align stage's floor, inside the convex hull of the surface and the
    # cameras, by rays pointing at least min_drop_deg below the horizontal that cross within
    # reach metres of the camera along the floor. A mesh with a floor plane is filled as
    # above, unbounded by these. 7-Scenes kitchen from its photos (20 frames at 240 px, no
    # floor in its mesh; three runs): floor IoU 0 -> 35.4-40.8, fwIoU 29.5-30.8 -> 38.1-40.8,
    # object unchanged; in one run 10, 20 or 30 degrees and 3 m or more gave the same within
    # 0.1, 40 degrees -1.7, 2 m -1.0; the hull grown by 0.5 m +0.6 but painted floor beyond
    # the counters and walls (16 % of the object cells)
    no_plane: bool = True
    min_drop_deg: float = 30.0  # degrees below the horizontal
    reach: float = 3.0  # metres from the camera, along the floor
    # with a floor plane too, the room is that hull within that reach (the found walls still
    # stop rays) rather than the floor and wall triangles' footprint, which is small where
    # stereo found the floor in patches. Replica office0 from its photos (30 frames at 240 px,
    # 14 registered, rough): fwIoU 13.5 -> 22.3, floor IoU 13.9 -> 34.1, object 14.6 -> 14.3,
    # 27 % of the reference's object cells floor (2 % before); the procedural rooms are not
    # measured with it: off
    hull: bool = False
    # with hull and a floor plane found, rays are bounded by that reach as without one; off,
    # they are not (the floor's height is measured there, not the align stage's guess, and
    # the found walls stop rays). Photos alone, 20 frames at 240 px (configs/phone.yaml):
    # Replica office0 fwIoU 29.0 -> 36.6 with the hull unbounded (floor 28.7 -> 45.7, wall
    # 45.4 -> 45.4, object 26.3 -> 26.1; 36.3, floor 45.0, with the reach); the procedural
    # demo room (60 views, a floor plane) 84.3 -> 84.2 unbounded (floor 88.0 -> 88.1, wall
    # 79.0 -> 78.0), 83.5 with the reach (floor 87.1); the 7-Scenes kitchen has no floor
    # plane (unchanged). Off in phone.yaml
    hull_reach: bool = True

    def __post_init__(self) -> None:
        _positive(self, "floor_fill", ("cell", "reach"))
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
    Measured from photos alone (20 frames at 240 px, configs/phone.yaml, the slow real-photo
    test's settings; same SfM, stereo and fusion, semantics only changed), 7-Scenes kitchen,
    two SfM runs: fwIoU 37.6 -> 38.4 and 38.2 -> 39.8, wall IoU 0 -> 26.2 and 0 -> 39.2 (its
    wall behind the counters: readings 0.9 m tall over 2.2 m² of cells, where the mesh kept
    0.24 m² of triangles), floor 32.8 -> 32.9 and 33.9 -> 34.1, object 41.4 -> 41.0 and 41.9
    -> 41.8; Replica office0 29.0 -> 28.9 (its walls are the mesh's already); the procedural
    demo room (60 views) unchanged. On in configs/phone.yaml; off here (sensor depth has its
    walls)."""

    enabled: bool = False
    dist: float = 0.05  # metres: a reading this close to the plane lies on it
    min_height: float = 0.5  # metres in z (5-95 %) the readings span at least
    max_beyond: float = 0.2  # readings beyond the plane per reading on it
    min_area: float = 1.0  # m²: the 10 cm cells (along it x height) its readings cover at
    #                        least (a cell a few readings touch counts whole: more than
    #                        walls.min_area; the kitchen's wall covers 2.2, a cabinet side 0.5,
    #                        the office's 1.6-4)

    def __post_init__(self) -> None:
        _positive(self, "point_walls", ("dist", "min_height"))
        _non_negative(self, "point_walls", ("max_beyond", "min_area"))


@dataclass(frozen=True)
class SemanticsConfig:
    """How the fused mesh is split into floor, walls, ceiling and object instances."""

    impl: Literal["geometry", "height"] = "geometry"  # "geometry": planes and clusters of the
    #                         fused mesh; "height": no stage, the project stage labels points
    #                         by height bands
    seed: int = 0  # seed of the RANSAC sample and of Open3D's RANSAC
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

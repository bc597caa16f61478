"""The plane fill's settings (one frozen dataclass, every knob with its effect).

Figures in the comments: `python -m stages.depth.planes.evaluate RUN --sensor CAPTURE
--every K` on the photos-only runs of the 7-Scenes kitchen (every 5th of 100 views) and the
Replica office (every 4th of 81), each setting changed alone from the others' values then:
plane-filled pixels within 5 cm of the sensor and the coverage after the fill.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from stages.common.errors import BlunfError


@dataclass(frozen=True)
class PlanesConfig:
    """Plane fill: depth from the room's own planes where stereo reads nothing."""

    enabled: bool = True  # fill stereo's holes with plane depth (false: the maps pass
    #                      through); it runs under `below`, and stays under `max_dropped`
    below: float = 0.6  # runs only when stereo covers fewer than this share of the pixels:
    #                     the real kitchen (37 %) and office (32 %) run it (docs/depth.md);
    #                     the textured demo room (81 %) plans 84.6 with it and skips its CPU-s
    max_dropped: float = 0.3  # the fill is undone (the maps go on as the sweep left
    #                 them) when the multi-view check drops more than this share of its fills:
    #                 the views disagree on the room's planes. Photos-only, against the sensor
    #                 at SfM poses, the share dropped of all views (of one view in 3): office
    #                 14 % (18 %), plan fwIoU 59.6 -> 64.5 with the fill; honest procedural room
    #                 (60 views) 21 % (26 %), 52.8 -> 62.4; kitchen 34 % (41 %; glossy cabinet
    #                 fronts, counters), 67.8 with the field fill against 59.9 with the planes;
    #                 demo room: stereo covers 81 %, no fill (docs/depth.md#when-the-fill-runs)
    # what a fill over max_dropped undoes: "plane": first the planes whose fills the check
    # drops over max_dropped of (their other fills are no better), then the whole fill if
    # what is left still drops over it; "all": the whole fill. all -> plane against the
    # sensor at SfM poses (bench.real, phone.yaml): kitchen (its sample drops 41 %; 33 of its
    # 40 planes give none, the floor among them; the 7 left fill 11.9 % of the pixels, 94.1 %
    # within 5 cm) plan fwIoU 72.0 -> 75.1 (floor 60.2 -> 67.0, wall 27.7 -> 18.6), SfM seed
    # 1 71.1 -> 75.7 (fills 88.2 %); office, honest procedural room: under max_dropped, the
    # same; demo room:
    # stereo covers 81 %, no fill (docs/depth.md#when-the-fill-runs). Taking out the planes
    # over it where the fill is under it too: office 80.25 -> 79.7, honest room 88.3 -> 86.6
    undo: Literal["plane", "all"] = "plane"
    sample_every: int = 3  # one view in this many is labelled and checked first (among
    #                 themselves), and over max_dropped the fill is undone before the rest is
    #                 labelled; 0 or 1: all views, then the one decision. A sample checks
    #                 each fill against fewer views and drops more (figures above and in
    #                 docs/depth.md). At 3 the kitchen's fill stops after a third of its CPU-s
    # hypotheses (hypotheses.py)
    voxel: float = 0.02  # metres: points are thinned to one per voxel before voting
    bin: float = 0.01  # metres: offset histogram bin along each room axis
    smooth: float = 1.5  # bins: Gaussian smoothing of the offset histograms
    min_support: int = 120  # voxels within `band` of a plane for it to be kept (~0.05 m²)
    band: float = 0.02  # metres: inliers of a plane lie within this of it (refit window)
    max_tilt_deg: float = 2.0  # a refitted normal may leave its room axis by at most this
    max_planes: int = 40  # at most this many planes (the floor always among them)
    # and up to this many planes of any tilt and yaw (hypotheses.free_planes) among the
    # stereo points no room-axis plane explains. 0 -> 4 against the sensor at SfM poses:
    # office plan fwIoU 60.7 -> 65.7 (the sofa's leaning back gets its plane; plane fills
    # within 5 cm 76.8 -> 76.5 %), kitchen 65.37 either way (the fill is undone there), demo
    # room and honest procedural room unchanged (no fill runs; no such plane is found)
    free_planes: int = 4
    turned_deg: float = 8.0  # vertical surfaces turned about up by up to this many degrees
    #                 off a wall axis (beyond max_tilt_deg) get planes of their own, and the
    #                 peaks that were strips of them give way (hypotheses._turned); <=
    #                 max_tilt_deg: none. 0 -> 8 against the sensor at SfM poses: office plane
    #                 fills within 5 cm 79.0 -> 82.5 % (its whiteboard, turned 3.1 degrees:
    #                 245 k fills 91.7 %, where two fronts had 79 and 73 %), coverage 81.2 ->
    #                 82.7 %, plan 64.2 -> 63.5; honest procedural room 95.3 % (94.6 within
    #                 3 cm) either way, plan 80.30 -> 80.31 (against its gt/ 65.46 -> 65.58);
    #                 kitchen: fill undone either way, plan 65.37 the same; demo room: no fill
    bounding_walls: bool = False  # add a wall at the outermost points on each side of each
    #                 wall axis where no peak shows one (plain walls); on, all views: honest
    #                 procedural room 42.5 % of fills within 5 cm (41.9 off), AbsRel 0.059
    #                 (0.072); office 58.3 % (69.1 off): its outermost points lie beyond walls
    wall_feet: bool = True  # walls at the line where they meet the floor, seen in the
    #                photos' edges over the views (bases.py), where no wall stereo read stands
    #                (plain paint). Against the sensor at SfM poses, off -> on (walls_span on):
    #                honest procedural room plane fills within 5 cm 68.0 -> 95.3 %, within
    #                3 cm 66.1 -> 94.6 %, coverage 69.3 -> 81.8 %, plan 78.9 -> 80.3 (against
    #                its exact gt/ 60.3 -> 65.5); office: every foot set aside (its walls are
    #                read), the same; kitchen: fill undone either way, plan 65.37 the same,
    #                +10 CPU-s; demo room: no fill runs (docs/depth.md, "Plain walls")
    feet_views: float = 0.1  # ... that line holds edges of at least this share of the views
    walls_span: bool = True  # the outermost walls a foot or stereo's reading shows span the
    #                room (the box of all points, grown to the feet) up to WALL_TOP, upright on
    #                the floor; off -> on: office plan 63.5 -> 64.2, plane fills 79.5 -> 79.0 %
    #                within 5 cm; honest room (wall_feet on) coverage 75.5 -> 81.8 % at 95.1 ->
    #                95.3 % within 5 cm, (wall_feet off) the same; kitchen, demo: as above
    tracks: bool = False  # SfM track depths count as readings in the data term where stereo
    #                      has none (the merge keeps stereo's only); on: honest room the same
    support_cell: float = 0.1  # metres, > 0: a top's support is the cells of this side
    #                 its inliers fill (grown by furniture_margin), not their whole box; 0:
    #                 the box alone. 0 -> 0.1 (w_hidden 2): plan fwIoU kitchen 49.8 -> 55.6,
    #                 office 66.1 -> 64.0; plane fills within 5 cm kitchen 47.4 -> 57.8 %,
    #                 office 77.7 -> 77.0 % (docs/depth.md#planes-hidden-behind-furniture)
    cell_points: int = 3  # inlier voxels a support cell needs (a stray track is not a table)
    top_tile: float = 0.6  # metres, > 0: horizontal planes are also sought in square tiles of
    #                 the floor this wide (hypotheses._local_tops): a table read at its rim
    #                 only makes no peak among the whole room's points; 0: off. 0 -> 0.6
    #                 against the sensor at SfM poses (top_holes 2, top_grow 0): office plan
    #                 fwIoU 64.56 -> 73.67 (its table took the floor's plane), fills within 5 cm
    #                 83.6 -> 85.3 %; honest procedural room 81.53 -> 81.35 (fills 95.6 ->
    #                 95.7 %); kitchen: fill undone either way, 72.02 the same; demo room and
    #                 homes: no fill runs (docs/depth.md#local-tops)
    top_holes: float = 2.0  # m², > 0: a horizontal plane's support cells take in the holes
    #                 of up to this area they enclose (a table top read at its rim only); 0:
    #                 the cells its inliers fill alone. 0 -> 2 with the tiles: office 71.84 ->
    #                 73.67; without the tiles 64.56 either way (docs/depth.md#local-tops)
    top_grow: float = 0.5  # metres, > 0: a top's support cells grow this far into the cells
    #                 over which nothing was read on the floor or below the top (a sofa's
    #                 seat read at its front edge: its unread back took the floor's plane);
    #                 0: off. 0 -> 0.5 against the sensor at SfM poses: office plan fwIoU
    #                 73.67 -> 80.48 (1.0: 78.78), its floor's fills within 5 cm 83.6 -> 97.6 %;
    #                 honest procedural room 81.35 -> 81.10 (fills 95.7 % either way);
    #                 kitchen: fill undone either way (39 % dropped), 72.02 the same; demo
    #                 room and homes: no fill runs (docs/depth.md#local-tops)
    normal_cos: float = 0.9  # a stereo point votes on an axis its normal is within ~25° of
    axes_yaw_deg: float = 0.0  # the wall axes turn at most this far from the align stage's
    #                 to the peak of the readings' normals (hypotheses.room_axes); 0 keeps
    #                 the align stage's, whose Manhattan yaw (align/manhattan.py) lies nearer
    #                 the sensor's walls than that peak: office 0.55 against ~2.7 degrees,
    #                 honest room 0.05 against 2.2. 10 -> 0 against the sensor at SfM poses:
    #                 office plan 78.88 -> 79.62 (wall 33.3 -> 43.8; seed 1: 78.99 -> 79.35),
    #                 plane fills 86.0 -> 88.3 % within 5 cm (61.2 -> 66.4 within 3 cm);
    #                 honest room 89.02 -> 88.53, its fills 96.1 -> 94.3 % (95.6 -> 94.0);
    #                 kitchen: fill undone, 71.68 either way; demo room and homes: no fill
    #                 runs. 10 kept the 7-Scenes kitchen off its diagonals, where stereo's
    #                 normals spread over every direction (docs/figures.md#depth-planes-axes)
    # per view (view.py)
    width: int = 320  # pixels: working width of the superpixels and the data term
    superpixels: int = 800  # SLIC segments per view at `width`
    compactness: float = 10.0  # SLIC compactness (higher: rounder, less edge-hugging)
    neighbours: int = 4  # views whose photos and readings judge a plane in a region
    tol: float = 0.05  # relative depth within which a reading agrees with a plane; 0.03:
    #                    kitchen 19 % within 5 cm (42.6 % at 0.05), coverage 42 % (44 %)
    tex_std: float = 0.04  # grey-level spread (0-1) at which a region's ZNCC counts fully
    w_stereo: float = 2.0  # weight of disagreement with the region's own readings
    w_photo: float = 1.0  # weight of the warped neighbours' ZNCC (texture-weighted)
    w_free: float = 2.0  # weight of other views seeing through the plane
    w_hidden: float = 2.0  # weight of other views seeing something in front of the plane
    #                 (the floor under a sofa); 0 -> 2 (support_cell 0): office plane fills
    #                 within 5 cm 72.3 -> 77.7 %, plan 68.0 -> 66.1; the kitchen's figures:
    #                 docs/depth.md#planes-hidden-behind-furniture
    w_colour: float = 1.0  # weight of a region's colour unlike every colour on the plane's
    #                       inliers; 0.5: kitchen 43.1 %, office 71.2 % (1.0: 43.8, 72.6).
    #                       The colours are those of the inliers whose normals agree with the
    #                       plane (appearance.plane_colours): office plane fills within 5 cm
    #                       82.5 -> 83.9 %, its floor's 55.3 -> 69.6 %; honest room 95.3 ->
    #                       95.6 %; kitchen undone either way (docs/depth.md)
    w_valid: float = 5.0  # weight of invalid plane points (behind, below floor, off support)
    support_margin: float = 0.5  # metres: a floor, wall or ceiling reaches this far past its
    #                              inliers' box
    furniture_margin: float = 0.15  # metres: the same for a top or front; 0.5: kitchen 41.7 %,
    #                                office 70.5 % (0.15: 43.1, 71.2), coverage the same
    none_cost: float = 0.5  # cost of `none` (keep stereo) on a region whose readings fit a
    #                         plane; 0.3: kitchen coverage 45.8 % (0.5: 52.7), within 5 cm the
    #                         same (41.9 / 41.7 %)
    # smoothness and solver (label.py, solve.py)
    w_crease: float = 0.05  # two planes meeting along a region boundary (a room's corner)
    w_jump: float = 0.4  # a depth jump between neighbouring regions on a weak colour edge;
    #                      0.15: kitchen the same (coverage 46.0 %, 45.5 % within 5 cm)
    w_none_edge: float = 0.1  # a plane region beside a `none` one (its depth is stereo's);
    #                 as a jump (0.4), at tol 0.03: kitchen coverage 40.0 % (42.3), 14 % within
    #                 5 cm (19)
    edge_sigma: float = 0.1  # RGB distance of region means at which a jump costs 1/e as much
    cycles: int = 3  # alpha-expansion sweeps over all labels
    # merge (merge.py, __init__.py)
    margin: float = 0.1  # a region is filled when `none` costs this much more than its plane;
    #                      0.2: kitchen coverage 50.2 % (52.7), within 5 cm 41.7 % the same
    furniture_extra: float = 0.0  # ... plus this for a top or front plane; 0.3: office 64.2 %
    #                    within 5 cm (61.0) but coverage 71.5 % (79.2), kitchen 36.6 % (41.8)
    boundary_px: int = 2  # readings disagreeing with a plane this near a region edge drop
    snap: bool = True  # readings agreeing (tol) with their filled region's floor, wall or
    #                     ceiling take its depth (piecewise-planar stereo's output: a wall read
    #                     2-3 cm either side of its plane draws a band of plan cells). Off -> on
    #                     (axes_yaw_deg 0): office plan 79.62 -> 80.06 (wall 43.8 -> 48.6),
    #                     its stereo 73.6 -> 77.8 % within 5 cm; honest room 88.53 -> 88.78,
    #                     stereo 81.3 -> 82.5 %; kitchen: fill undone, no change; demo room and
    #                     homes: no fill runs (docs/figures.md#depth-planes-axes)
    check_tol: float = 0.05  # relative: a fill is kept where another view agrees within this;
    #                         0.02: kitchen coverage 44.1 % (45.8), within 5 cm 42.6 % (41.9)
    check_agree: int = 1  # ... this many other views must agree with a fill
    check_through: int = 0  # ... and at most this many may see through it; 1: kitchen
    #                        coverage 47.7 % (45.8), within 5 cm 37.8 % (41.9)
    check_views: int = 6  # views each fill is checked against (those overlapping it most)

    def __post_init__(self) -> None:
        for k in ("below", "max_dropped"):
            if not 0.0 <= getattr(self, k) <= 1.0:
                raise BlunfError(f"depth.planes.{k} must be in [0, 1], got {getattr(self, k)}")
        if self.undo not in ("plane", "all"):
            raise BlunfError(f"depth.planes.undo: {self.undo!r} is not one of 'plane', 'all'")
        pos = ("voxel", "bin", "band", "tol", "tex_std", "check_tol")
        for k in pos:
            if not getattr(self, k) > 0:
                raise BlunfError(f"depth.planes.{k} must be > 0, got {getattr(self, k)}")
        for k in ("top_tile", "top_holes", "top_grow"):
            if not 0.0 <= getattr(self, k) < float("inf"):
                raise BlunfError(
                    f"depth.planes.{k} must be a finite number >= 0, got {getattr(self, k)}"
                )
        if not 0.0 <= self.support_cell < float("inf") or self.cell_points < 1:
            raise BlunfError(
                "depth.planes.support_cell must be a finite number >= 0 and cell_points >= 1, "
                f"got {self.support_cell}, {self.cell_points}"
            )
        if self.width < 16 or self.superpixels < 4 or self.max_planes < 1:
            raise BlunfError(
                "depth.planes.width must be >= 16, superpixels >= 4 and max_planes >= 1, got "
                f"{self.width}, {self.superpixels}, {self.max_planes}"
            )
        if self.sample_every < 0:
            raise BlunfError(f"depth.planes.sample_every must be >= 0, got {self.sample_every}")
        if not 0.0 <= self.feet_views <= 1.0:
            raise BlunfError(f"depth.planes.feet_views must be in [0, 1], got {self.feet_views}")
        if not 0.0 <= self.axes_yaw_deg <= 45.0:
            raise BlunfError(
                f"depth.planes.axes_yaw_deg must be in [0, 45], got {self.axes_yaw_deg}"
            )
        if self.free_planes < 0:
            raise BlunfError(f"depth.planes.free_planes must be >= 0, got {self.free_planes}")
        if self.neighbours < 1 or self.cycles < 1 or self.check_views < 1:
            raise BlunfError(
                "depth.planes.neighbours, cycles and check_views must be >= 1, got "
                f"{self.neighbours}, {self.cycles}, {self.check_views}"
            )

"""Configuration, inputs and outputs of the poses stage (camera-to-world poses for every frame)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from stages.common.errors import BlunfError

MAPPERS = ("auto", "incremental", "global")
MATCHINGS = ("auto", "sequential", "exhaustive", "retrieval")
Matching = Literal["auto", "sequential", "exhaustive", "retrieval"]  # one of MATCHINGS
SCALE_FROM = ("auto", "depth", "distance", "camera_height", "priors", "none")


@dataclass(frozen=True)
class RetrievalConfig:
    """Loop pairs found without a downloaded vocabulary (matching.py): VLAD vectors of each
    image's SIFT descriptors over visual words trained on the capture's own descriptors."""

    neighbours: int = 5  # each image is also matched with this many most similar images
    #                      beyond its next `overlap` and sequential pairs (the loop pairs)
    words: int = 64  # visual words (seeded k-means of the capture's descriptors)
    sample: int = 20000  # at most this many descriptors train the words (spread over images)
    iterations: int = 15  # k-means iterations

    def __post_init__(self) -> None:
        for name in ("neighbours", "words", "sample", "iterations"):
            if getattr(self, name) < 1:
                raise BlunfError(
                    f"poses.matching.retrieval.{name}: must be >= 1, got {getattr(self, name)}"
                )
        if self.sample < self.words:
            raise BlunfError(
                f"poses.matching.retrieval.sample: must be >= words ({self.words}), "
                f"got {self.sample}"
            )


@dataclass(frozen=True)
class MatchingConfig:
    """Which image pairs SIFT matches are sought between (matching.py)."""

    kind: Matching = "auto"  # "auto" =
    #   exhaustive up to exhaustive_max_images, sequential up to retrieval_above, else
    #   retrieval; "sequential": the capture order's neighbours only (no loop closes);
    #   "retrieval": sequential plus each image's `retrieval.neighbours` most similar images
    #   (a walk that returns closes its loop)
    exhaustive_max_images: int = 40
    retrieval_above: int = 150  # auto: retrieval above this many images
    #                             (docs/figures.md#poses-retrieval-above)
    overlap: int = 10  # sequential: each image with those 1, 2, 4 ... 2^(overlap - 1) on
    #                    (pycolmap 4's quadratic overlap)

    retrieval: RetrievalConfig = dataclasses.field(default_factory=RetrievalConfig)

    def __post_init__(self) -> None:
        if self.kind not in MATCHINGS:
            raise BlunfError(f"poses.matching.kind: {self.kind!r} is not one of {MATCHINGS}")
        for name in ("exhaustive_max_images", "overlap", "retrieval_above"):
            if getattr(self, name) < 1:
                raise BlunfError(f"poses.matching.{name}: must be >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class BundleAdjustmentConfig:
    """The incremental mapper's bundle adjustments."""

    global_max_refinements: int = 5  # global adjustments rerun at most this often after
    #                                  filtering outliers
    local_max_refinements: int = 2  # ...and local ones (COLMAP's defaults: 5 and 2)
    global_growth: float = 1.4  # the next global adjustment once the model has this many
    #                             times the images or the points it had at the last
    #                             (COLMAP's 1.1; docs/figures.md#poses-ba-growth)

    def __post_init__(self) -> None:
        for name in ("global_max_refinements", "local_max_refinements"):
            if getattr(self, name) < 1:
                raise BlunfError(f"poses.ba.{name}: must be >= 1, got {getattr(self, name)}")
        if not 1.0 < self.global_growth < float("inf"):
            raise BlunfError(
                f"poses.ba.global_growth: must be a finite number > 1, got {self.global_growth}"
            )


MIN_MAPPED = 10  # views: a keyframe subset smaller than this is no model to register to


@dataclass(frozen=True)
class KeyframesConfig:
    """Long captures: the incremental mapper maps a subset, then registers the rest to it.

    The incremental mapper's cost grows faster than its views (each global bundle adjustment
    takes in every view so far, and they come each time the model grows by a ratio), while
    registering a view to a model whose poses are held costs about the same whatever the
    model's size. So a capture of at least twice `at_least` views maps one view in k first
    (k the largest power of two leaving at least `at_least` views: the sequential pairs'
    steps 1, 2, 4 ... still join them), then registers the others to that model with its
    poses held, and no global adjustment grows with them. When the subset's model holds fewer
    than `hold` of its views (too sparse to join), k halves, down to mapping every view.
    The 3-room home, 480 photos: mapping 238 CPU-s (its model misplaced a stretch, so mapper
    auto mapped again globally, 250 more) -> 119 (55 for 240 views, 64 registering the other
    240), every pair agreeing, ATE 1.8 mm; every 4th view held 106 of its 120
    (docs/scale.md#keyframes)."""

    at_least: int = 200  # views mapped first; 0 = always map every view
    hold: float = 0.95  # share of the subset its model must hold
    # sequential matching leaves out the pairs between two odd-numbered views (registered to
    # the subset's model, never mapped) more than 2 steps apart (matching.keyframe_pairs):
    # 3809 -> 2383 sequential pairs at 480 views; false: match them all
    skip_pairs: bool = True
    # the local bundle adjustments after each view registered to the held model: the view
    # moves alone against held poses, and one refinement of up to 10 iterations does what
    # two of up to 25 (the mapper's own) did. The 480-view home from photos, the poses stage
    # alone on one thread: mapping 83.9 -> 70.7 CPU-s, ATE 1.774 -> 1.770 mm, median
    # rotation 0.034 deg either way (docs/scale.md#keyframe-pairs)
    register_refinements: int = 1
    register_iterations: int = 10

    def __post_init__(self) -> None:
        if self.at_least != 0 and self.at_least < MIN_MAPPED:
            raise BlunfError(
                f"poses.keyframes.at_least: must be 0 or >= {MIN_MAPPED}, got {self.at_least}"
            )
        if not 0.0 < self.hold <= 1.0:
            raise BlunfError(f"poses.keyframes.hold: must be in (0, 1], got {self.hold}")
        for name in ("register_refinements", "register_iterations"):
            if getattr(self, name) < 1:
                raise BlunfError(f"poses.keyframes.{name}: must be >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class PosesConfig:
    """How poses are obtained. Fields other than `impl` only matter for `impl = "sfm"`."""

    impl: str = "auto"  # "given" (the capture's poses) | "sfm" (pycolmap from the photos) |
    #                     "auto" = given when the capture has poses, else sfm (the planner picks)
    mapper: Literal["auto", "incremental", "global"] = "auto"  # COLMAP's incremental mapper,
    #   the global one (GLOMAP), or "auto": incremental, then global when the incremental
    #   model contradicts its own verified pairs (agreement.py), the model that contradicts
    #   fewer kept (docs/figures.md#poses-mapper)
    matching: MatchingConfig = dataclasses.field(default_factory=MatchingConfig)
    ba: BundleAdjustmentConfig = dataclasses.field(default_factory=BundleAdjustmentConfig)
    keyframes: KeyframesConfig = dataclasses.field(default_factory=KeyframesConfig)
    max_features: int = 8192  # SIFT features kept per image
    max_image_size: int = 1600  # SIFT runs on images downscaled to this longest side (pixels)
    double_below: int = 640  # SIFT doubles the images first (COLMAP's default first octave
    #                          -1) when their longest side is below this many pixels; 0 = never
    #                          (docs/figures.md#poses-double-below)
    full_size_images: bool = True  # SIFT on the capture's own images when ingest downscaled
    #                                them; poses, intrinsics and the model are given at the
    #                                working size either way
    full_size_max_side: int = 480  # ...read at most this long (never below the working size;
    #                                0 = up to max_image_size; docs/figures.md#poses-full-size)
    self_calibrate: bool | Literal["auto"] = "auto"  # true: estimate the intrinsics even when
    #   stated (unreliable indoors); false: keep them as stated; "auto": keep them unless a
    #   bundle adjustment with the focal free moves it by more than stated_focal_tolerance,
    #   then estimate them (stated.py; photos whose intrinsics are a guess or EXIF are
    #   always estimated)
    stated_focal_tolerance: float = 0.03  # auto: relative focal change that counts as a
    #   disagreement. The refined focal moves by <= 0.08 % on the demo room and the Replica
    #   office (stated K exact), by -6 % on the 7-Scenes kitchen (the depth camera's K
    #   stated for the colour images; the estimate is -10 %): 3 % is ~40 x the first,
    #   half the second
    # true: the frames whose lens distortion SfM estimated take undistorted copies of their
    # photos and pinhole intrinsics, so that every later stage reads the same rays
    # (undistort.py: the sweep, the plane fill, fusion and the fields read a frame as
    # pinhole, the project stage through its distortion). Procedural room through a k1 -0.08
    # lens (10 px at the corners), photos only against exact ground truth: fwIoU 70.4 ->
    # 84.0 (85.7 without the lens). The 7-Scenes kitchen (k1 -0.029, 6.7 px) against its
    # sensor at SfM poses: 72.0 -> 68.8 (plan seed 1: 71.3 -> 68.9), its sensor's own lens
    # unmodelled; the office, the demo and honest rooms keep their stated K: unchanged
    # (docs/figures.md#poses-undistort)
    undistort: bool = False
    threads: int = 0  # CPU threads for extraction, matching and mapping; 0 = every core we may use
    min_registered_frac: float = 0.5  # fail when fewer than this fraction of the images register
    seed: int = 0  # random seed of pycolmap's RANSAC and mapper (same inputs -> same poses)
    deterministic: bool = True  # the same photos give the same poses, bit for bit: SIFT,
    #                             matching and mapping on one thread, every pair's two-view
    #                             RANSAC from `seed`; false: every part on `threads`
    #                             (docs/figures.md#poses-deterministic)
    scale_from: Literal["auto", "depth", "distance", "camera_height", "priors", "none"] = "auto"
    #   metric scale: "depth" | "distance" | "camera_height" | "priors" (camera height of a
    #   hand-held capture above the floor found in the sparse points, and the ceiling height
    #   when seen: scale.scale_from_priors) | "none"; "auto" = "depth" when every frame has
    #   depth, else camera_height or distance when given, else "priors"
    known_distance: float | None = None  # scale_from="distance": metres between the first and
    #                                      last frames' camera centres (capture order)
    camera_height: float | None = None  # scale_from="camera_height": metres from the camera
    #                                     centres down to the floor (lowest sparse points)

    # the flat keys of earlier versions -> their place now (an old key fails naming it)
    RENAMED: ClassVar[dict[str, str]] = {
        "matching": "matching.kind",
        "exhaustive_max_images": "matching.exhaustive_max_images",
        "sequential_overlap": "matching.overlap",
        "ba_global_max_refinements": "ba.global_max_refinements",
        "ba_local_max_refinements": "ba.local_max_refinements",
        "ba_global_growth": "ba.global_growth",
    }

    def __post_init__(self) -> None:
        if self.mapper not in MAPPERS:
            raise BlunfError(f"poses.mapper: {self.mapper!r} is not one of {MAPPERS}")
        if self.scale_from not in SCALE_FROM:
            raise BlunfError(f"poses.scale_from: {self.scale_from!r} is not one of {SCALE_FROM}")
        if self.scale_from == "distance" and not (self.known_distance or 0) > 0:
            raise BlunfError("poses.known_distance: must be > 0 metres when scale_from=distance")
        if self.scale_from == "camera_height" and not (self.camera_height or 0) > 0:
            raise BlunfError("poses.camera_height: must be > 0 m when scale_from=camera_height")
        if not 0.0 <= self.min_registered_frac <= 1.0:
            raise BlunfError(
                f"poses.min_registered_frac: must be in [0, 1], got {self.min_registered_frac}"
            )
        if self.max_features < 1:
            raise BlunfError(f"poses.max_features: must be >= 1, got {self.max_features}")
        if self.max_image_size < 64:
            raise BlunfError(f"poses.max_image_size: must be >= 64 px, got {self.max_image_size}")
        if self.full_size_max_side < 0:
            raise BlunfError(
                f"poses.full_size_max_side: must be >= 0, got {self.full_size_max_side}"
            )
        if self.double_below < 0:
            raise BlunfError(f"poses.double_below: must be >= 0 px, got {self.double_below}")
        if self.self_calibrate not in (True, False, "auto"):
            raise BlunfError(
                f"poses.self_calibrate: {self.self_calibrate!r} is not true, false or auto"
            )
        if not 0.0 < self.stated_focal_tolerance < 1.0:
            raise BlunfError(
                "poses.stated_focal_tolerance: must be in (0, 1), got "
                f"{self.stated_focal_tolerance}"
            )
        if self.threads < 0:
            raise BlunfError(f"poses.threads: must be >= 0, got {self.threads}")


@dataclass(frozen=True)
class PosesInputs:
    frames: Path  # frames.json of the capture (a `Capture`)


@dataclass(frozen=True)
class PosesOutputs:
    STATS: ClassVar[str | None] = "sfm.json"  # its stats file: the report's facts
    frames: Path  # frames.json with a camera-to-world pose on every frame kept
    sfm: Path  # sfm.json: what was registered, how the scale was found, timings

    @classmethod
    def at(cls, out: Path) -> PosesOutputs:
        """The outputs inside a finished out folder."""
        out = Path(out)
        return cls(frames=out / "frames.json", sfm=out / "sfm.json")

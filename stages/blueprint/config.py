"""Configuration and the input / output contract of the blueprint stage."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal, get_args

from stages.common.errors import BlunfError

Encoding = Literal["none", "pe", "hash", "siren"]  # as stages.common.encoding.ENCODINGS
ENCODINGS = get_args(Encoding)
WallFaceFill = Literal["floor", "nearest"]  # what the cells cut in front of a wall face become


@dataclass(frozen=True)
class BlunfConfig:
    """The BluNF field B(x, y) -> class logits and how it is trained (defaults: fast on CPU)."""

    encoding: Encoding = "pe"
    n_freqs: int = 0  # pe: octaves of sin / cos (2^0 .. 2^(n-1)) pi; 0 = auto, see blunf.py
    hash_levels: int = 8  # hash: resolution levels
    hash_features: int = 2  # hash: features per level
    hash_log2_size: int = 16  # hash: log2 of the table entries per level
    hash_base_res: int = 8  # hash: coarsest resolution (cells across the unit square [-1, 1]^2)
    hash_max_res: int = 0  # hash: finest resolution; 0 = half the plan grid's cells across
    siren_omega: float = 30.0  # siren: omega_0 of the sine layers (SIREN wants lr ~1e-3)
    width: int = 64  # hidden units per MLP layer
    layers: int = 2  # hidden layers (the MLP has layers + 1 linear maps)
    lr: float = 1e-2  # Adam learning rate, decayed exponentially to lr * lr_final
    lr_final: float = 0.1  # final learning rate as a fraction of lr (1 = constant)
    batch: int = 8192  # points per step
    steps: int = 1000  # optimisation steps
    # point sampling: "none" (as projected) | "sqrt" (class p ∝ sqrt(count)) | "cell" (every
    # occupied plan cell equally likely, then one of its points)
    balance: Literal["none", "sqrt", "cell"] = "cell"
    # plan cells beyond the points' bounds (grid.json): "clamp" = the field at the nearest point
    # of the bounds | "field" = the field's own extrapolation
    outside: Literal["clamp", "field"] = "clamp"
    seed: int = 0  # seeds the initialisation and the batch sampling
    # train on floor at the plan cells a view looked through (observed.npz "free") that hold
    # no point and that views looked past half the cameras' height above ("past"): the floor
    # no view saw round the cameras' own path, which the field would otherwise fill from the
    # nearest points (the wall faces beside the path); an object whose top no view saw is
    # crossed by rays too but never looked past. 3-room sensor home fwIoU 81.24 -> 85.81
    # (wall IoU 59.7 -> 72.4, cabinet 56.2 -> 65.9); demo room from photos 84.18 -> 84.32, its
    # edit run 90.75 -> 91.73 (cabinet 58.9 -> 46.8: its inside, never crossed by a ray, is
    # the field's guess); held-out pAcc kitchen 96.76 -> 96.79, office 94.80 -> 94.79. Off in
    # configs/phone.yaml: stereo's readings pass through walls (the home from photos 76.24 ->
    # 75.54 with it, the demo room from photos 84.18 -> 84.32). Opt-in: where the projected
    # points are sparse an object lower than the tested height has empty cells views looked
    # past, and the field gives it to the floor (the tests' 8-view room: fwIoU 69.9 -> 67.3,
    # its cabinet 47.0 and plant 45.4 -> 0, even with 0.16 m kept clear of object points)
    free_floor: bool = False
    # a cell is wall only where the views saw wall: the wall cells wholly in front of the
    # face of the nearest cell holding wall points become floor (faces.py), where the field
    # drew the wall thick from the face's points. Needs the project stage's observed.npz (its
    # free cells tell the room's side of a face). With wall_face_margin 0.5, off -> on: 3-room
    # sensor home fwIoU 81.24 -> 84.36 (wall 59.5 -> 73.2), with free_floor 85.84 -> 87.62;
    # the demo room's edit run 90.76 -> 91.96; held-out pixel accuracy (heldout.py) kitchen
    # 96.94 -> 96.59, office 95.37 -> 95.16. Off in configs/phone.yaml: from photos the
    # procedural rooms gain (the home 76.16 -> 77.65, the demo room 84.50 -> 86.34) but the
    # office against its sensor at SfM poses loses 61.95 -> 61.11 (wall 43.6 -> 29.1), the
    # kitchen 68.77 -> 68.74 (README "Where a wall cell ends")
    wall_face: bool = True
    # cells: a wall cell turns floor only when its centre lies more than this in front of
    # the face. 0 is the ground truth's convention exactly (a cell is wall when its centre lies
    # behind the face; the sensor home 85.54, the demo room from photos 87.09) but real views
    # disagree on a wall by 1-2 cm, a 2 cm cell: the held-out pixels of the office's walls lie
    # up to a cell in front of the face the other views fused (held-out pAcc 91.48, kitchen
    # 96.10); 0.5 keeps the cell the face crosses and cuts only the cells wholly in front of it
    wall_face_margin: float = 0.5
    # what the wall cells cut in front of a face become: "floor" (the strip between a wall
    # and a bed a little off it is floor: the sensor home 89.46 against 88.01 with
    # "nearest") or "nearest", the class of the nearest cell the field drew not wall (a sofa
    # standing against the wall keeps the cells up to it). From photos, on (margin 0.5),
    # floor -> nearest: office against its sensor at SfM poses 63.87 -> 65.98, kitchen 67.87
    # -> 68.66, honest room 80.53 -> 81.00 (against its gt/ 65.59 -> 65.60); the 3-room home
    # 83.13 -> 82.15, demo room 86.84 -> 86.11 (docs/figures.md#phone-wall-face)
    wall_face_fill: WallFaceFill = "floor"
    # the cells no view saw into and no ray crossed, closed round by one object's points (a
    # tall cabinet's inside, its top above the cameras) become that object (hidden.py).
    # Off -> on, 3-room sensor home seed 0: fwIoU 89.63 -> 90.52 (cabinet 64.6 -> 78.2),
    # seed 1 90.99 -> 91.59 (corner F1 0.85 -> 1.0), seed 2 92.63 -> 92.60; demo room's edit
    # run 91.96 -> 92.33, from photos 84.50 either way; kitchen from photos against its
    # sensor at SfM poses 68.58 -> 68.59, office 62.24 either way; held-out pAcc kitchen
    # 96.59 and office 95.16 either way (docs/figures.md#blunf-hidden-insides)
    hidden_insides: bool = True
    shrink: float = 0.0  # metres: object footprints (every class but floor, wall, ceiling)
    #                      shrunk by this where they meet the floor, in whole cells, after
    #                      the field is read (blunf.shrink_objects): for depth that fattens
    #                      objects (stereo). 0 = off; the saved field stays unshrunk
    # torch threads while training: a fixed count, not the free cores, so the plan does not
    # depend on how busy the machine is (2 threads against 1 sum the weight gradients in
    # another order: 62 of the synthetic room's cells differ; docs/figures.md#train-threads);
    # 0 = the stage's thread count
    threads: int = 1
    eval_chunk: int = 65536  # cell centres per forward pass when rendering the plan

    def __post_init__(self) -> None:  # checked when the config loads, before any stage runs
        c, w = self, "blueprint.blunf"
        if not (c.shrink >= 0 and math.isfinite(c.shrink)):
            raise BlunfError(f"{w}.shrink must be >= 0 metres, got {c.shrink}")
        if not (c.wall_face_margin >= 0 and math.isfinite(c.wall_face_margin)):
            raise BlunfError(f"{w}.wall_face_margin must be >= 0 cells, got {c.wall_face_margin}")
        if c.n_freqs < 0:
            raise BlunfError(f"{w}.n_freqs must be >= 0 (0 = auto), got {c.n_freqs}")
        for name in ("width", "batch", "hash_levels", "hash_features", "hash_base_res"):
            if getattr(c, name) < 1:
                raise BlunfError(f"{w}.{name} must be >= 1, got {getattr(c, name)}")
        if c.eval_chunk < 1:
            raise BlunfError(f"{w}.eval_chunk must be >= 1, got {c.eval_chunk}")
        if c.steps < 0:
            raise BlunfError(f"{w}.steps must be >= 0, got {c.steps}")
        if c.layers < (1 if c.encoding == "siren" else 0):
            raise BlunfError(f"{w}.layers must be >= 1 with siren (>= 0 else), got {c.layers}")
        if not 4 <= c.hash_log2_size <= 26:
            raise BlunfError(f"{w}.hash_log2_size must be in [4, 26], got {c.hash_log2_size}")
        if not (c.lr > 0 and 0 < c.lr_final <= 1 and c.siren_omega > 0):
            raise BlunfError(
                f"{w}: lr {c.lr}, lr_final {c.lr_final} and siren_omega "
                f"{c.siren_omega} must be > 0 (lr_final <= 1)"
            )


def paper_recipe() -> BlunfConfig:
    """The paper's recipe: PE with 12 frequencies, one hidden layer of 64 ReLU units (tcnn
    "n_hidden_layers = num_layers - 1" with num_layers 2), Adam 5e-3, 50k points per step,
    50k steps, plain (unbalanced) sampling, no learning-rate decay, the field read as it is
    beyond the points."""
    return BlunfConfig(
        encoding="pe",
        n_freqs=12,
        width=64,
        layers=1,
        lr=5e-3,
        lr_final=1.0,
        batch=50_000,
        steps=50_000,
        balance="none",
        outside="field",
    )


@dataclass(frozen=True)
class MvrConfig:
    """Multi-view reconstruction: per-cell majority vote of the projected labels."""

    min_votes: int = 1  # cells with fewer projected points stay unknown (255)

    def __post_init__(self) -> None:
        if self.min_votes < 1:
            raise BlunfError(f"blueprint.mvr.min_votes must be >= 1, got {self.min_votes}")


@dataclass(frozen=True)
class NerfTopConfig:
    """The NeRF top-view baseline: vertical rays through the semantic NeRF."""

    # heights (metres above the floor) the rays start from; the best by fwIoU is kept
    heights: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5)
    chunk: int = 16384  # rays per forward pass


@dataclass(frozen=True)
class BlueprintConfig:
    """Which plan builder, and the settings of each."""

    impl: str = "blunf"  # registry key in stages.blueprint.IMPLS: "blunf" | "mvr"
    blunf: BlunfConfig = field(default_factory=BlunfConfig)  # used when impl = "blunf"
    mvr: MvrConfig = field(default_factory=MvrConfig)  # used when impl = "mvr"
    nerf_top: NerfTopConfig = field(default_factory=NerfTopConfig)  # impl = "nerf_top"


# the stats file each implementation writes (the report's facts)
STATS_FILES = {"blunf": "train.json", "mvr": "mvr.json", "nerf_top": "nerf_top.json"}


@dataclass(frozen=True)
class BlueprintInputs:
    points: Path  # points.npz of the project stage
    grid: Path  # grid.json of the project stage
    # observed.npz of the project stage (near, inside on the grid): BluNF labels the room's
    # extent only and the plan carries seen / inside; None: every cell of the grid is labelled
    observed: Path | None = None


@dataclass(frozen=True)
class NerfTopInputs:
    model: Path  # model.pt of the nerf stage (with a semantic head)
    points: Path  # points.npz of the project stage (the reference without ground truth)
    grid: Path  # grid.json of the project stage
    reference: Path | None = None  # ground-truth blueprint.npz, when the capture has one
    frames: Path | None = None  # frames.json the points were projected from (their poses)
    gt_poses: Path | None = None  # the capture's gt/poses.json, when it has one
    poses_estimated: bool = False  # the poses of `frames` were estimated (SfM): the GT plan
    #                                is read through the camera-centre similarity, as the
    #                                evaluate stage reads it


@dataclass(frozen=True)
class BlueprintOutputs:
    STATS: ClassVar[dict[str, str]] = STATS_FILES  # by implementation
    blueprint: Path  # blueprint.npz (Blueprint.save)
    stats: Path  # train.json (blunf) or mvr.json (mvr): counts and timings

    @classmethod
    def at(cls, out: Path) -> BlueprintOutputs:
        """The outputs inside a finished blueprint folder (stats named by the impl that ran)."""
        out = Path(out)
        names = list(STATS_FILES.values())
        stats = next((out / n for n in names if (out / n).exists()), out / names[0])
        return cls(blueprint=out / "blueprint.npz", stats=stats)

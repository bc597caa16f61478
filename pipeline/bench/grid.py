"""The bench grid: which captures, and which variants run on them, one line per variant.

A variant is a real pipeline run (`pipeline.run.run`) of one capture with `--set` style
overrides and a frame budget. Each variant studies one stage (`group`): the stages before
`fresh_from` are reused from the capture's warm cache, that stage and everything after it
run afresh on every repeat, and the plot of the group puts the seconds of `timed` (x) against
`error` (y). To add a variant, add one `Variant(...)` line to a grid below; to add a group
(e.g. NeRF budgets once the NeRF stage is wired), add its lines and, if it needs one, its
capture to `captures()`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.config import stage_configs
from stages.blueprint.config import BlunfConfig, paper_recipe

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
# the pipeline's stages in run order (pipeline/run.py); a stage the list lacks sorts last
STAGE_ORDER = tuple(stage_configs())  # pipeline order: what `fresh_from` / `upstream` rank
ENCODINGS = ("pe", "hash", "siren", "none")
SIZES = ((160, 120), (320, 240), (640, 480))  # the resolution sweep (18-view rooms)
# per-encoding settings beyond `encoding=` (the config comment: SIREN wants lr ~1e-3)
ENCODING_SETS = {"siren": ("blueprint.blunf.lr=0.001",)}


@dataclass(frozen=True)
class Variant:
    """One point of the bench: a pipeline run, repeated, with what to read from it."""

    name: str  # unique label (plots, tables, the CSV's `variant`)
    group: str  # the stage it studies: one time-vs-error plot per (group, capture)
    capture: str  # a key of captures()
    sets: tuple[str, ...] = ()  # --set overrides, "stage.key=value"
    frames: int = 0  # ingest.frames (0 = every frame)
    fresh_from: str = "blueprint"  # first stage rerun on every repeat (earlier ones cached)
    timed: tuple[str, ...] = ("blueprint",)  # stages whose seconds make the x axis
    error: str = "100-blueprint.blunf.fwiou"  # y axis: a flattened metric, "100-" = 100 minus
    reference: bool = False  # a reference point (the paper's recipe): ratios are taken to it
    cost: str = ""  # "frames" | "pixels": also a point of that cost-against-size sweep

    def __post_init__(self) -> None:
        if self.fresh_from not in STAGE_ORDER:
            raise ValueError(f"variant {self.name}: fresh_from {self.fresh_from!r} is no stage")


@dataclass(frozen=True)
class CaptureSpec:
    """A capture of the bench: made on demand (synthetic) or read in place (real)."""

    name: str
    make: Callable[[Path], Path]  # out folder of the bench -> the capture folder
    real: bool = False  # read from SHARED_DATA: skipped with a message when absent


def synthetic(
    views: int, size: tuple[int, int], seed: int = 0, photos: bool = False, realism: str = "none"
) -> Callable[[Path], Path]:
    """A maker of the procedural room (rendered once into <out>/captures/); `photos`: images
    and intrinsics only; `realism`: `blunf synth --realism` (plain walls, blur, noise...)."""

    def make(out: Path) -> Path:
        from stages.synth import make_room
        from stages.synth.realism import Realism

        tag = ("" if realism == "none" else f"-{realism}") + ("-photos" if photos else "")
        cap = Path(out) / "captures" / f"room-s{seed}-v{views}-{size[0]}x{size[1]}{tag}"
        if cap.is_dir():
            return cap
        look = Realism.parse(realism)
        return make_room(cap, views=views, seed=seed, size=size, photos_only=photos, realism=look)

    return make


def shared(name: str) -> Callable[[Path], Path]:
    """A real capture of SHARED_DATA, read in place."""

    def make(out: Path) -> Path:
        return SHARED_DATA / name

    return make


def captures(quick: bool) -> dict[str, CaptureSpec]:
    """The bench's captures. `room` is the main synthetic room; `room-WxH` the resolution sweep."""
    main = (160, 120) if quick else (320, 240)
    specs = [
        CaptureSpec("room", synthetic(45 if quick else 90, main)),
        *(CaptureSpec(f"room-{w}x{h}", synthetic(18, (w, h))) for w, h in SIZES),
        # photos only, textured and honest (plain walls, smooth floor, exposure, blur, noise):
        # a change that helps only the textured room shows up as such
        CaptureSpec("room-photos", synthetic(60, (320, 240), photos=True)),
        CaptureSpec("honest-photos", synthetic(60, (320, 240), photos=True, realism="honest")),
        CaptureSpec("7scenes", shared("7scenes-redkitchen"), real=True),
        CaptureSpec("replica", shared("replica-office0"), real=True),
    ]
    return {c.name: c for c in specs}


def blunf_sets(cfg: BlunfConfig) -> tuple[str, ...]:
    """--set overrides turning the default BluNF config into `cfg` (fields that differ)."""
    base = BlunfConfig()
    return tuple(
        f"blueprint.blunf.{f.name}={getattr(cfg, f.name)}"
        for f in dataclasses.fields(cfg)
        if getattr(cfg, f.name) != getattr(base, f.name)
    )


def _named(name: str, capture: str) -> str:
    """Variant names carry the capture unless it is the main room."""
    return name if capture == "room" else f"{name}-{capture}"


def paper(steps: int, frames: int, capture: str = "room") -> Variant:
    """The paper's BluNF recipe cut to `steps` (its 50k steps take hours on a CPU)."""
    return Variant(
        _named(f"paper-{steps}-f{frames}", capture),
        "blueprint",
        capture,
        ("run.methods=blunf", *blunf_sets(dataclasses.replace(paper_recipe(), steps=steps))),
        frames,
        reference=True,
    )


def encoding(enc: str, frames: int, capture: str = "room") -> Variant:
    """BluNF with the project's defaults and encoding `enc`."""
    sets = ("run.methods=blunf", f"blueprint.blunf.encoding={enc}", *ENCODING_SETS.get(enc, ()))
    return Variant(_named(f"blunf-{enc}-f{frames}", capture), "blueprint", capture, sets, frames)


def mvr(frames: int, capture: str = "room") -> Variant:
    return Variant(
        _named(f"mvr-f{frames}", capture),
        "blueprint",
        capture,
        ("run.methods=mvr",),
        frames,
        error="100-blueprint.mvr.fwiou",
    )


def sfm(mapper: str, matching: str, frames: int, capture: str = "room") -> Variant:
    """SfM poses (pycolmap) instead of the capture's; error = ATE after a similarity."""
    return Variant(
        _named(f"sfm-{mapper[:3]}-{matching[:3]}-f{frames}", capture),
        "poses",
        capture,
        (
            "run.methods=mvr",
            "poses.impl=sfm",
            f"poses.mapper={mapper}",
            f"poses.matching.kind={matching}",
        ),
        frames,
        fresh_from="poses",
        timed=("poses",),
        error="poses.ate_rmse_m",
    )


def depth(source: str, frames: int, capture: str = "room", cost: str = "") -> Variant:
    """Where the projected depth comes from: "fusion" (the fused surface ray-cast into every
    view, the default) or "sensor" (the capture's own depth, fusion.raycast=false)."""
    sets = ("run.methods=blunf",) + (("fusion.raycast=false",) if source == "sensor" else ())
    return Variant(
        _named(f"depth-{source}-f{frames}", capture),
        "depth",
        capture,
        sets,
        frames,
        fresh_from="fusion",
        timed=("fusion", "project"),
        cost=cost,
    )


def nerf(field: str, budget: float, frames: int = 40, capture: str = "room") -> Variant:
    """The NeRF stage alone (sensor depth): hash grid at several time budgets, and the plain
    positional-encoding MLP NeRF (same losses, sampler and budget) as the reference; error =
    40 - held-out PSNR (dB), so lower is better like every other axis."""
    return Variant(
        _named(f"nerf-{field}-{int(budget)}s-f{frames}", capture),
        "nerf",
        capture,
        (
            "run.methods=[mvr,nerf_top]",
            f"nerf.field.kind={field}",
            f"nerf.train.time_budget={budget}",
            "nerf.threads=1",
        ),
        frames,
        fresh_from="nerf",
        timed=("nerf",),
        error="40-nerf.psnr_heldout",
        reference=field == "pe",
    )


NERF: tuple[Variant, ...] = (
    *(nerf("hash", b) for b in (30.0, 60.0, 120.0)),
    nerf("pe", 120.0),
)


def phone_sets() -> tuple[str, ...]:
    """configs/phone.yaml as --set overrides (the bench's runs take overrides only)."""
    import yaml

    def flat(d: dict, prefix: str) -> list[str]:
        out: list[str] = []
        for k, v in d.items():
            out += flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}={v}"]
        return out

    path = Path(__file__).resolve().parents[2] / "configs" / "phone.yaml"
    return tuple(flat(yaml.safe_load(path.read_text()), ""))


def phone(capture: str, frames: int = 0) -> Variant:
    """The whole photos-only path (configs/phone.yaml; the depth stage's field fill stops at a
    fixed 300 steps so the figure does not depend on the machine's load) from SfM on; error =
    100 - BluNF fwIoU."""
    return Variant(
        f"phone-{capture}" + (f"-f{frames}" if frames else ""),
        "phone",
        capture,
        (*phone_sets(), "depth.field.train.time_budget=0", "depth.field.train.max_steps=300"),
        frames,
        fresh_from="poses",
        timed=("poses", "depth", "fusion", "semantics", "project", "blueprint"),
    )


MAPPINGS = tuple((m, g) for m in ("incremental", "global") for g in ("sequential", "exhaustive"))


def quick_grid() -> list[Variant]:
    """~8 minutes on an idle machine: 160x120 images, one frame budget for the encodings."""
    return [
        *(encoding(e, 45) for e in ENCODINGS),
        mvr(45),
        paper(250, 45),
        depth("sensor", 45),
        *(depth("fusion", f, cost="frames") for f in (9, 18, 45)),
        *(depth("fusion", 9, f"room-{w}x{h}", "pixels") for w, h in SIZES),
        *(sfm(m, g, 18) for m, g in MAPPINGS),
        depth("fusion", 9, "7scenes"),
        *NERF,
    ]


def full_grid() -> list[Variant]:
    """Every variant of the issue: ~20 minutes a repeat on one thread of an idle machine."""
    frames = (90, 45, 9)
    return [
        *(encoding(e, f) for f in frames for e in ENCODINGS),
        *(mvr(f) for f in frames),
        *(paper(250, f) for f in frames),
        paper(1000, 90),
        depth("sensor", 45),
        *(depth("fusion", f, cost="frames") for f in (9, 18, 45, 90)),
        *(depth("fusion", 18, f"room-{w}x{h}", "pixels") for w, h in SIZES),
        *(sfm(m, g, 30) for m, g in MAPPINGS),
        depth("sensor", 20, "7scenes"),
        depth("fusion", 20, "7scenes"),
        *(sfm(m, g, 20, "7scenes") for m, g in MAPPINGS),
        # no poses and no ground truth: SfM and the whole pipeline timed on real photos
        Variant(
            "replica-sfm-f20",
            "poses",
            "replica",
            ("run.methods=blunf",),
            20,
            fresh_from="poses",
            timed=("poses",),
            error="poses.ate_rmse_m",
        ),
        *NERF,
        phone("room-photos"),
        phone("honest-photos"),
    ]

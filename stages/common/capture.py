"""The capture: frames (image, optional depth / labels / pose) with intrinsics and a label table.

`Capture` is what every stage passes along as `frames.json`: paths point into the capture
folder (read in place, never written), poses are camera-to-world 4x4 in the current world.
The project's own layout (DESIGN.md) is read by `read_layout` and written by `write_layout`.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics, check_pose
from stages.common.checks import check_intrinsics, check_unique_stems
from stages.common.classes import UNKNOWN as UNKNOWN  # (re-exported: its home is classes)
from stages.common.errors import BlunfError
from stages.common.io import read_depth, read_json, write_json

IMAGE_EXTS = (".jpg", ".jpeg", ".png")
DEPTH_EXTS = (".png", ".npy")
# intrinsics of images without any given: (intrinsics, calib, camera) per image
GuessIntrinsics = Callable[[list[Path]], list[tuple[Intrinsics, str, str]]]


@dataclass(frozen=True)
class Frame:
    """One view. `pose` is camera-to-world [4, 4] or None when not known yet."""

    stem: str
    image: Path
    intrinsics: Intrinsics
    depth: Path | None = None
    label: Path | None = None
    pose: np.ndarray | None = None
    instance: Path | None = None  # object instance id per pixel (0 = none), beside the label
    calib: str = "given"  # where the intrinsics came from: given | exif | prior (a guess SfM
    #                       refines) | self-calibrated (estimated by SfM)
    camera: str = ""  # frames sharing one physical camera (device and image size), for SfM
    original: Path | None = None  # the full-size image `image` was downscaled from (ingest's
    #                               max_side): SfM may read it; `intrinsics` are `image`'s


@dataclass(frozen=True)
class Capture:
    """Frames plus what applies to all of them."""

    root: Path
    frames: tuple[Frame, ...]
    classes: dict[int, str] = field(default_factory=dict)  # label id -> class name
    ignore: tuple[int, ...] = ()  # label ids never projected (e.g. ceiling)
    gravity: tuple[float, float, float] | None = None  # world direction of gravity (unit)
    depth_scale: float = 1000.0  # PNG depth units per metre
    depth_invalid: tuple[int, ...] = (65535,)  # PNG codes meaning "no reading"
    gt: Path | None = None  # ground-truth folder, when the capture has one
    kind: str = "blunf"  # layout it was read from
    # metres: where the frames' world origin lies in the capture's own world (its poses were
    # far from their origin: ingest moved them near it, float32 geometry keeps its precision
    # there); a point x of the frames is x + origin in the capture's world (after align:
    # its aligned world). Exports add it back.
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def has_poses(self) -> bool:
        return bool(self.frames) and all(f.pose is not None for f in self.frames)

    @property
    def has_depth(self) -> bool:
        return bool(self.frames) and all(f.depth is not None for f in self.frames)

    @property
    def has_labels(self) -> bool:
        return bool(self.frames) and all(f.label is not None for f in self.frames)

    def with_frames(self, frames: list[Frame] | tuple[Frame, ...]) -> Capture:
        return replace(self, frames=tuple(frames))

    def poses(self) -> np.ndarray:
        """[C, 4, 4] camera-to-world poses (all must be known)."""
        missing = [f.stem for f in self.frames if f.pose is None]
        if missing:
            raise BlunfError(f"{self.root}: no pose for frame {missing[0]!r}")
        return np.stack([np.asarray(f.pose) for f in self.frames])

    # ---- frames.json: how stages hand a capture to each other --------------------------
    def to_json(self) -> dict:
        return {
            "root": str(self.root),
            "kind": self.kind,
            "classes": {str(k): v for k, v in sorted(self.classes.items())},
            "ignore": list(self.ignore),
            "gravity": list(self.gravity) if self.gravity is not None else None,
            "depth_scale": self.depth_scale,
            "depth_invalid": list(self.depth_invalid),
            "gt": str(self.gt) if self.gt else None,
            **({"origin": list(self.origin)} if any(self.origin) else {}),
            "frames": [
                {
                    "stem": f.stem,
                    "image": str(f.image),
                    "depth": str(f.depth) if f.depth else None,
                    "label": str(f.label) if f.label else None,
                    "instance": str(f.instance) if f.instance else None,
                    "intrinsics": f.intrinsics.to_json(),
                    "pose": np.asarray(f.pose).tolist() if f.pose is not None else None,
                }
                | ({"calib": f.calib, "camera": f.camera} if f.calib != "given" else {})
                | ({"original": str(f.original)} if f.original else {})
                for f in self.frames
            ],
        }

    @staticmethod
    def from_json(d: dict) -> Capture:
        frames = tuple(
            Frame(
                stem=f["stem"],
                image=Path(f["image"]),
                intrinsics=Intrinsics.from_json(f["intrinsics"]),
                depth=Path(f["depth"]) if f.get("depth") else None,
                label=Path(f["label"]) if f.get("label") else None,
                pose=np.asarray(f["pose"], np.float64) if f.get("pose") is not None else None,
                instance=Path(f["instance"]) if f.get("instance") else None,
                calib=f.get("calib", "given"),
                camera=f.get("camera", ""),
                original=Path(f["original"]) if f.get("original") else None,
            )
            for f in d["frames"]
        )
        g = d.get("gravity")
        return Capture(
            root=Path(d["root"]),
            frames=frames,
            classes={int(k): v for k, v in d.get("classes", {}).items()},
            ignore=tuple(d.get("ignore", ())),
            gravity=tuple(g) if g is not None else None,  # type: ignore[arg-type]
            depth_scale=float(d.get("depth_scale", 1000.0)),
            depth_invalid=tuple(d.get("depth_invalid", (65535,))),
            gt=Path(d["gt"]) if d.get("gt") else None,
            kind=d.get("kind", "blunf"),
            origin=tuple(float(x) for x in d.get("origin", (0.0, 0.0, 0.0))),  # type: ignore[arg-type]
        )

    def save(self, path: Path) -> None:
        """Write frames.json. Paths inside its own folder are stored relative to it, so a
        stage folder written under a temp name stays valid once renamed into place."""
        base = Path(path).parent.resolve()

        def rel(p: str | None) -> str | None:
            if p is None:
                return None
            rp = Path(p).resolve()
            return str(rp.relative_to(base)) if rp.is_relative_to(base) else str(rp)

        d = self.to_json()
        for f in d["frames"]:
            for k in ("image", "depth", "label", "instance", "original"):
                if k in f:
                    f[k] = rel(f[k])
        d["gt"] = rel(d["gt"])
        write_json(path, d)

    @staticmethod
    def load(path: Path) -> Capture:
        """Read frames.json; relative paths are taken from its folder."""
        base = Path(path).parent.resolve()
        d = read_json(path)

        def absp(p: str | None) -> str | None:
            return None if p is None else str(base / p)

        for f in d["frames"]:
            for k in ("image", "depth", "label", "instance", "original"):
                f[k] = absp(f.get(k))
        d["gt"] = absp(d.get("gt"))
        return Capture.from_json(d)

    @staticmethod
    def load_posed(path: Path, who: str) -> Capture:
        """Read frames.json and refuse it unless it has frames, each with a pose (`who` names
        the step that needs them in the error)."""
        cap = Capture.load(path)
        if not cap.frames:
            raise BlunfError(f"{path}: no frames")
        if not cap.has_poses:
            raise BlunfError(f"{path}: {who} needs a pose for every frame")
        return cap


def _find(folder: Path, stem: str, exts: tuple[str, ...]) -> Path | None:
    """The file of this stem in folder, None when there is none; two (0003.png and
    0003.npy) are an error: which one is meant is not known."""
    found = [p for p in (folder / f"{stem}{e}" for e in exts) if p.exists()]
    if len(found) > 1:
        raise BlunfError(f"{found[0]} and {found[1]}: two files for frame {stem!r}; keep one")
    return found[0] if found else None


def _inside(root: Path, p: Path) -> Path:
    """Resolve p and refuse it when it leaves the capture folder (e.g. a symlink outside)."""
    rp = p.resolve()
    if not rp.is_relative_to(root.resolve()):
        raise BlunfError(f"{p}: points outside the capture folder {root}")
    return p


def read_layout(root: Path, guess: GuessIntrinsics | None = None) -> Capture:
    """Read a capture in the project's own layout (DESIGN.md). Without intrinsics in
    cameras.json, `guess` (when given) gives every image's from its file (EXIF or a prior)."""
    root = Path(root)
    img_dir = root / "images"
    if not img_dir.is_dir():
        raise BlunfError(f"{root}: not a capture (no images/ folder)")
    images = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    if not images:
        raise BlunfError(f"{img_dir}: no .jpg or .png images")
    check_unique_stems([(p.stem, p) for p in images])
    where = str(root / "cameras.json")
    if not (root / "cameras.json").exists() and guess is None:
        raise BlunfError(f"{where}: not found (it gives the camera intrinsics, see DESIGN.md)")
    cams = read_json(root / "cameras.json") if (root / "cameras.json").exists() else {}
    if not isinstance(cams, dict):
        raise BlunfError(f"{where}: must be a JSON object (intrinsics, frames, ...)")
    shared = cams.get("intrinsics")
    per_frame = cams.get("frames", {})
    if not isinstance(per_frame, dict):
        raise BlunfError(f"{where}: 'frames' must map image stems to entries")
    frames = []
    guessed = None
    if (
        guess is not None
        and shared is None
        and not any("intrinsics" in e for e in per_frame.values() if isinstance(e, dict))
    ):
        if any(isinstance(e, dict) and "pose" in e for e in per_frame.values()):
            raise BlunfError(f"{where}: poses given but no intrinsics (give 'intrinsics' too)")
        guessed = dict(zip(images, guess(images), strict=True))
    for img in images:
        _inside(root, img)
        stem = img.stem
        entry = per_frame.get(stem, {})
        if not isinstance(entry, dict):
            raise BlunfError(f"{where}: the entry of frame {stem!r} must be an object")
        intr_d = entry.get("intrinsics", shared)
        if guessed is not None:
            intr, calib, camera = guessed[img]
        elif intr_d is None:
            raise BlunfError(
                f"{where}: no intrinsics for {img.name} (give 'intrinsics' in cameras.json)"
            )
        else:
            intr = Intrinsics.from_json(intr_d, f"{where} intrinsics of {stem}")
            check_intrinsics(
                intr, f"{where} intrinsics" + ("" if intr_d is shared else f" of {stem}")
            )
            calib, camera = "given", ""
        pose = entry.get("pose")
        pose_a = check_pose(pose, f"{where} pose of {stem}") if pose is not None else None
        depth = _find(root / "depth", stem, DEPTH_EXTS)
        label = _find(root / "labels", stem, (".png",))
        frames.append(
            Frame(
                stem=stem,
                image=img,
                intrinsics=intr,
                depth=_inside(root, depth) if depth else None,
                label=_inside(root, label) if label else None,
                pose=pose_a,
                calib=calib,
                camera=camera,
            )
        )
    has_pose = [f.pose is not None for f in frames]
    if any(has_pose) and not all(has_pose):
        missing = next(f.stem for f in frames if f.pose is None)
        raise BlunfError(f"{where}: poses given for some frames but not for {missing!r}")
    classes: dict[int, str] = {}
    ignore: tuple[int, ...] = ()
    if (root / "labels.json").exists():
        lj = read_json(root / "labels.json")
        try:
            classes = {int(k): str(v) for k, v in lj.get("classes", {}).items()}
            ignore = tuple(int(i) for i in lj.get("ignore", []))
        except (TypeError, ValueError, AttributeError) as e:
            raise BlunfError(f"{root / 'labels.json'}: bad class table ({e})") from None
    g = cams.get("gravity")
    gravity = _unit(g, f"{where} gravity") if g is not None else None
    return Capture(
        root=root,
        frames=tuple(frames),
        classes=classes,
        ignore=ignore,
        gravity=gravity,
        depth_scale=_depth_scale(cams.get("depth_scale", 1000.0), f"{where} depth_scale"),
        depth_invalid=_codes(cams.get("depth_invalid", [65535]), f"{where} depth_invalid"),
        gt=root / "gt" if (root / "gt").is_dir() else None,
        kind="blunf",
    )


def _depth_scale(v: object, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < float("inf"):
        raise BlunfError(f"{where}: must be a positive number (depth units per metre), got {v!r}")
    return float(v)


def _codes(v: object, where: str) -> tuple[int, ...]:
    if not isinstance(v, list) or not all(isinstance(x, int) and 0 <= x <= 65535 for x in v):
        raise BlunfError(f"{where}: must be a list of integer depth codes, got {v!r}")
    return tuple(v)


def _unit(v: object, where: str) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        raise BlunfError(f"{where}: must be a finite non-zero 3-vector, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-9:
        raise BlunfError(f"{where}: must be a finite non-zero 3-vector, got {v}")
    a = a / np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


def write_layout(cap: Capture, out: Path, with_poses: bool = True) -> Path:
    """Write a capture in the project's layout (copying files). Returns `out`.

    Frames' intrinsics go to cameras.json (shared when all equal; left out when only guessed
    from EXIF or a prior, which a reader makes again). Writes into a temp
    folder and renames it into place, so a failure leaves nothing half-written.
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise BlunfError(f"{out}: output folder exists and is not empty")
    tmp = out.parent / f".{out.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    intr = {f.intrinsics for f in cap.frames}
    known = all(f.calib in ("given", "self-calibrated") for f in cap.frames)  # else guesses,
    shared = len(intr) == 1 or not known  # which a reader makes again from the images
    cams: dict = {"intrinsics": next(iter(intr)).to_json()} if shared and known else {}
    cams["frames"] = {}
    for f in cap.frames:
        shutil.copyfile(f.image, tmp / "images" / f"{f.stem}{f.image.suffix.lower()}")
        if f.depth is not None:
            (tmp / "depth").mkdir(exist_ok=True)
            shutil.copyfile(f.depth, tmp / "depth" / f"{f.stem}{f.depth.suffix.lower()}")
        if f.label is not None:
            (tmp / "labels").mkdir(exist_ok=True)
            shutil.copyfile(f.label, tmp / "labels" / f"{f.stem}.png")
        entry: dict = {}
        if not shared:
            entry["intrinsics"] = f.intrinsics.to_json()
        if with_poses and f.pose is not None:
            entry["pose"] = np.asarray(f.pose).tolist()
        cams["frames"][f.stem] = entry
    if cap.gravity is not None:
        cams["gravity"] = list(cap.gravity)
    cams["depth_scale"] = cap.depth_scale
    cams["depth_invalid"] = list(cap.depth_invalid)
    write_json(tmp / "cameras.json", cams)
    if cap.classes:
        write_json(
            tmp / "labels.json",
            {
                "classes": {str(k): v for k, v in sorted(cap.classes.items())},
                "ignore": list(cap.ignore),
            },
        )
    if cap.gt is not None and Path(cap.gt).is_dir():
        shutil.copytree(cap.gt, tmp / "gt")
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():
        out.rmdir()
    tmp.rename(out)
    return out


def readings_of(path: Path | None) -> Callable[[str], np.ndarray | None]:
    """The depth reading (metres, [h, w]) of each view by its stem, from frames.json `path`
    (the depth the fusion read); None for a view without one, or for every view without
    `path`."""
    if path is None:
        return lambda stem: None
    cap = Capture.load(path)
    by = {f.stem: f for f in cap.frames}

    def reading(stem: str) -> np.ndarray | None:
        f = by.get(stem)
        if f is None or f.depth is None:
            return None
        return read_depth(f.depth, cap.depth_scale, cap.depth_invalid)

    return reading


def heldout_views(n: int, every: int) -> list[int]:
    """Indices of the views held out of training and scored instead (the project and NeRF
    stages share the rule): index % every == every // 2; none when every = 0 or n < 2."""
    return [i for i in range(n) if every > 0 and n > 1 and i % every == every // 2]

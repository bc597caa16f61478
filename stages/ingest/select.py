"""The ingest stage: read a capture, choose its frames, check them, optionally downscale.

out/frames.json          the chosen frames (Capture.save), what later stages read
out/ingest.json          facts for the report: layout, counts, chosen indices, timings
out/import/              files a reader derived (label maps, ground truth), if any
out/resized/             downscaled images / depth / labels / instances, when max_side asks
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from PIL import Image

from stages.common.capture import Capture, Frame
from stages.common.checks import check_intrinsics, check_unique_stems
from stages.common.errors import BlunfError
from stages.common.io import (
    depth_size,
    image_size,
    read_depth,
    read_image,
    read_json,
    read_label,
    write_json,
    write_label_png,
)
from stages.ingest.config import IngestConfig, IngestInputs, IngestOutputs
from stages.ingest.photos import intrinsics_facts
from stages.ingest.recentre import recentred
from stages.ingest.video import VideoOptions

log = logging.getLogger(__name__)


def select_indices(count: int, n: int) -> list[int]:
    """Indices of n views spread evenly over count, first and last included.

    n = 0 or n >= count gives all; n = 1 gives the middle view ((count - 1) // 2).
    """
    if count <= 0:
        return []
    if n <= 0 or n >= count:
        return list(range(count))
    if n == 1:
        return [(count - 1) // 2]
    # Steps of (count - 1) / (n - 1) >= 1 stay distinct after rounding half up.
    return [int(np.floor(i * (count - 1) / (n - 1) + 0.5)) for i in range(n)]


def _check_config(cfg: IngestConfig) -> None:
    from stages.ingest import IMPLS, READERS

    if cfg.impl not in IMPLS:
        raise BlunfError(f"ingest.impl: {cfg.impl!r} unknown (known: {', '.join(IMPLS)})")
    if cfg.kind != "auto" and cfg.kind not in READERS:
        raise BlunfError(f"ingest.kind: {cfg.kind!r} unknown (known: auto, {', '.join(READERS)})")
    if cfg.frames < 0:
        raise BlunfError(f"ingest.frames: must be >= 0, got {cfg.frames}")
    for name in ("max_side", "photo_max_side", "video_frames"):
        if getattr(cfg, name) < 0:
            raise BlunfError(f"ingest.{name}: must be >= 0, got {getattr(cfg, name)}")


def check_structure(cap: Capture, allowed: tuple[Path, ...]) -> None:
    """Checks on paths only, over all frames: non-empty, depth / labels / poses given for
    all frames or none, and no file inside the allowed folders that is a symlink to
    outside them (paths a layout states explicitly, e.g. nerfstudio's, may lie anywhere)."""
    if not cap.frames:
        raise BlunfError(f"{cap.root}: capture has no frames")
    check_unique_stems([(f.stem, f.image) for f in cap.frames])
    for attr, what in (("depth", "depth"), ("label", "labels"), ("pose", "poses")):
        given = [getattr(f, attr) is not None for f in cap.frames]
        if any(given) and not all(given):
            miss = next(f for f, g in zip(cap.frames, given, strict=True) if not g)
            raise BlunfError(f"{miss.image}: no {what} for this frame ({what} given for others)")
    plain = [Path(os.path.abspath(a)) for a in allowed]
    real = [a.resolve() for a in allowed]
    for f in cap.frames:
        for p in (f.image, f.depth, f.label, f.instance):
            if p is None or not any(Path(os.path.abspath(p)).is_relative_to(r) for r in plain):
                continue
            if not any(Path(p).resolve().is_relative_to(r) for r in real):
                raise BlunfError(f"{p}: points outside the capture folder {cap.root}")


def _size(p: Path, full: bool, kind: str) -> tuple[int, int]:
    """(width, height) of an image, depth or label file; full = decode it all (not depth)."""
    if kind == "image":
        return read_image(p).shape[1::-1] if full else image_size(p)
    if kind == "depth":  # (full: check_frames decodes depth itself)
        if p.suffix == ".npy":
            try:
                a = np.load(p, mmap_mode="r")
            except (OSError, ValueError) as e:
                raise BlunfError(f"{p}: not a readable .npy depth map ({e})") from None
            if a.ndim != 2:
                raise BlunfError(f"{p}: depth must be 2-D, got shape {a.shape}")
            return a.shape[::-1]
        return depth_size(p)
    return read_label(p).shape[::-1] if full else image_size(p)


def check_frames(cap: Capture, full: bool) -> list[str]:
    """Each image readable and of its intrinsics' size, the intrinsics those of a camera;
    depth, labels and instance maps of the image's size. With full = True, also refuses a
    capture whose depth maps hold no reading at all. Returns the stems of the frames whose
    depth map is empty (full = True only)."""
    for intr in sorted({f.intrinsics for f in cap.frames}, key=str):
        user = next(f for f in cap.frames if f.intrinsics == intr)
        check_intrinsics(intr, f"{cap.root}: intrinsics of {user.image.name}")
    empty = []
    for f in cap.frames:
        w, h = _size(f.image, full, "image")
        iw, ih = f.intrinsics.width, f.intrinsics.height
        if (w, h) != (iw, ih):
            raise BlunfError(f"{f.image}: image is {w}x{h} but its intrinsics say {iw}x{ih}")
        for p, kind in ((f.depth, "depth"), (f.label, "label"), (f.instance, "instance map")):
            if p is None:
                continue
            if kind == "depth" and full:
                d = read_depth(Path(p), cap.depth_scale, cap.depth_invalid)  # [H, W] metres
                if not (d > 0).any():
                    empty.append(f.stem)
                ph, pw = d.shape
            else:
                pw, ph = _size(Path(p), full, kind)
            if (pw, ph) != (w, h):
                raise BlunfError(f"{p}: {kind} is {pw}x{ph} but its image is {w}x{h}")
    if cap.has_depth and empty and len(empty) == len(cap.frames):
        folders = sorted({str(Path(f.depth).parent) for f in cap.frames if f.depth is not None})
        raise BlunfError(
            f"{', '.join(folders)}: the capture's depth is empty (no reading in any of the "
            f"{len(empty)} depth maps: all 0 or invalid codes {list(cap.depth_invalid)}); "
            "fix them, or remove them to work from the photos alone"
        )
    if empty:
        log.warning("ingest: %d depth maps hold no reading: %s", len(empty), empty)
    return empty


def _nearest(a: np.ndarray, w: int, h: int) -> np.ndarray:
    """Nearest-neighbour resize of [H, W] to [h, w], pixel centres aligned like PIL."""
    H, W = a.shape
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)  # [h]
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)  # [w]
    return a[rows[:, None], cols[None, :]]


def _raw_depth(p: Path) -> np.ndarray:
    """A depth PNG's stored integers (scale and invalid codes untouched). [H, W]"""
    with Image.open(p) as img:
        a = np.asarray(img)
    if a.dtype != np.uint16 and a.size and a.min() >= 0 and a.max() <= 65535:
        a = a.astype(np.uint16)
    return a


def resize_frame(f: Frame, max_side: int, dst: Path) -> Frame:
    """Downscale a frame so its longer side is max_side; depth, labels, instances by nearest.
    The full-size image stays named in `original` (SfM reads it)."""
    W, H = f.intrinsics.width, f.intrinsics.height
    s = max_side / max(W, H)
    if s >= 1.0:
        return f
    w, h = max(1, round(W * s)), max(1, round(H * s))
    img_dir = dst / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    ext = f.image.suffix.lower()
    image = img_dir / f"{f.stem}{ext}"
    with Image.open(f.image) as im:
        small = im.convert("RGB").resize((w, h), Image.Resampling.LANCZOS)
    if ext in (".jpg", ".jpeg"):
        small.save(image, quality=95)
    else:
        small.save(image)
    depth = label = instance = None
    if f.depth is not None:
        (dst / "depth").mkdir(exist_ok=True)
        depth = dst / "depth" / f"{f.stem}{f.depth.suffix.lower()}"
        if f.depth.suffix.lower() == ".npy":
            np.save(depth, _nearest(np.load(f.depth), w, h))
        else:
            Image.fromarray(_nearest(_raw_depth(f.depth), w, h)).save(depth)
    if f.label is not None:
        (dst / "labels").mkdir(exist_ok=True)
        label = dst / "labels" / f"{f.stem}.png"
        write_label_png(label, _nearest(read_label(f.label), w, h))
    if f.instance is not None:
        (dst / "instances").mkdir(exist_ok=True)
        instance = dst / "instances" / f"{f.stem}.png"
        write_label_png(instance, _nearest(read_label(f.instance), w, h))
    intr = f.intrinsics.scaled(w, h)
    full = f.original or f.image
    return replace(
        f, image=image, depth=depth, label=label, instance=instance, intrinsics=intr, original=full
    )


def run(cfg: IngestConfig, inputs: IngestInputs, out: Path) -> IngestOutputs:
    """Read the capture, keep cfg.frames views, check them, downscale to cfg.max_side."""
    from stages.ingest import load  # the package imports this module for its registry

    log.debug("ingest: %s on %s", cfg, inputs.capture)
    _check_config(cfg)
    check_not_a_run(Path(inputs.capture))
    out = Path(out)
    work = out / "import"
    t0 = time.perf_counter()
    side = cfg.max_side or cfg.photo_max_side
    cap = load(Path(inputs.capture), work, cfg.kind, VideoOptions(cfg.video_frames, side))
    t_read = time.perf_counter() - t0

    t0 = time.perf_counter()
    check_structure(cap, (Path(cap.root), work))
    total = len(cap.frames)
    idx = select_indices(len(cap.frames), cfg.frames)
    cap = cap.with_frames([cap.frames[i] for i in idx])
    empty_depth = check_frames(cap, full=cfg.check == "full")
    t_check = time.perf_counter() - t0

    t0 = time.perf_counter()
    if cfg.max_side > 0:
        cap = cap.with_frames([resize_frame(f, cfg.max_side, out / "resized") for f in cap.frames])
    elif cfg.photo_max_side > 0:  # photos without given intrinsics: to the working size
        cap = cap.with_frames(
            [
                resize_frame(f, cfg.photo_max_side, out / "resized") if f.calib != "given" else f
                for f in cap.frames
            ]
        )
    t_resize = time.perf_counter() - t0

    cap = recentred(cap)  # poses far from the origin: moved near it, the offset kept
    outputs = IngestOutputs.at(out)
    cap.save(outputs.frames)
    f0 = cap.frames[0].intrinsics
    facts = {
        "config": asdict(cfg),
        "kind": cap.kind,
        "frames_total": total,
        "frames_selected": len(cap.frames),
        "indices": idx,
        "has_depth": cap.has_depth,
        "has_labels": cap.has_labels,
        "has_poses": cap.has_poses,
        "has_gravity": cap.gravity is not None,
        "empty_depth": empty_depth,
        "size": [f0.width, f0.height],
        "resized": (out / "resized").is_dir(),
        "seconds": {"read": t_read, "check": t_check, "resize": t_resize},
        "intrinsics": intrinsics_facts(cap),
    }
    if (work / "video" / "video.json").is_file():
        facts["video"] = read_json(work / "video" / "video.json")
    write_json(out / "ingest.json", facts)
    log.info(
        "ingest: %d of %d frames (%s), %dx%d, depth=%s labels=%s poses=%s",
        facts["frames_selected"],
        facts["frames_total"],
        cap.kind,
        f0.width,
        f0.height,
        cap.has_depth,
        cap.has_labels,
        cap.has_poses,
    )
    return outputs


def check_not_a_run(folder: Path) -> None:
    """A run folder given as a capture (its report.json and .runs/): one line saying so."""
    if (folder / ".runs").is_dir() and (folder / "report.json").exists():
        raise BlunfError(
            f"{folder}: a run folder, not a capture (its capture: the 'capture' of its report.json)"
        )

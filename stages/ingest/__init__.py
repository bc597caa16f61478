"""Ingest: read a capture in any known layout, then pick and check its frames.

Readers (`read(src, work) -> Capture`) read a layout in place and write derived files (label
maps, ground truth) into `work` only. `load` picks one by name or detects the layout;
`import_capture` converts a capture to the project's own layout (`blunf import`).
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Callable
from pathlib import Path

from stages.common.capture import Capture, read_layout, write_layout
from stages.common.errors import BlunfError
from stages.common.io import check_exists
from stages.common.registry import LazyImpls
from stages.ingest import colmap, exif, nerfstudio, photos, replica, sevenscenes, video

log = logging.getLogger(__name__)


def _read_blunf(src: Path, work: Path) -> Capture:
    """The project's own layout, read in place (`work` is not used); without intrinsics in
    cameras.json they come from the photos' EXIF or a prior, for SfM to refine."""
    return read_layout(src, exif.guess_all)


READERS: dict[str, Callable[[Path, Path], Capture]] = {
    "blunf": _read_blunf,
    "7scenes": sevenscenes.read,
    "replica-vmap": replica.read,
    "nerfstudio": nerfstudio.read,
    "colmap": colmap.read,
    "photos": photos.read,
    "video": video.read,
}

IMPLS = LazyImpls({"auto": "stages.ingest.select:run"})


def detect(src: Path) -> str:
    """Name of the layout of a capture folder (a key of READERS)."""
    src = Path(src)
    if src.is_file() and src.suffix == ".json":
        return "nerfstudio"
    if src.suffix.lower() in video.VIDEO_EXTS and not src.is_dir():
        check_exists(src, "video file")
        return "video"
    check_exists(src, "capture folder")
    if not src.is_dir():
        raise BlunfError(f"{src}: not a capture folder")
    if not any(src.iterdir()):
        raise BlunfError(f"{src}: capture folder is empty")
    if (src / "transforms.json").is_file():
        return "nerfstudio"
    if (src / "camera-intrinsics.txt").is_file() and (src / "frames").is_dir():
        return "7scenes"
    if (src / "info_semantic.json").is_file() and (src / "rgb").is_dir():
        return "replica-vmap"
    if (src / "cameras.json").is_file() and (src / "images").is_dir():
        return "blunf"
    if colmap.find_model(src) is not None:
        return "colmap"
    if (src / "sparse").is_dir() and not (src / "cameras.json").is_file():
        return "colmap"  # a COLMAP project whose model is missing: its reader says so
    if (src / "images").is_dir():
        return "blunf"
    if photos.image_files(src):
        return "photos"
    raise BlunfError(
        f"{src}: not a known capture layout (known: {', '.join(READERS)}) and no .jpg or "
        f".png photos in it (a video: {', '.join(video.VIDEO_EXTS)})"
    )


def load(
    src: Path, work: Path, kind: str = "auto", opts: video.VideoOptions | None = None
) -> Capture:
    """Read the capture at src with the reader for `kind` ("auto" = detect it); `opts`:
    how a video's frames are taken."""
    src, work = Path(src), Path(work)
    if kind == "auto":
        kind = detect(src)
    if kind not in READERS:
        raise BlunfError(f"capture kind {kind!r} unknown (known: auto, {', '.join(READERS)})")
    check_exists(src, "video file" if kind == "video" else "capture folder")
    folder = src if src.is_dir() or kind == "video" else src.parent
    if work.resolve().is_relative_to(folder.resolve()):
        raise BlunfError(f"{work}: work folder inside the capture {src}, which is never written")
    cap = video.read(src, work, opts) if kind == "video" else READERS[kind](src, work)
    log.info("read %s capture %s: %d frames", kind, src, len(cap.frames))
    return cap


def import_capture(kind: str, src: Path, out: Path, opts: video.VideoOptions | None = None) -> Path:
    """Read a capture of layout `kind` and write it in the project's layout at out."""
    with tempfile.TemporaryDirectory(prefix="blunf-import-") as tmp:
        cap = load(src, Path(tmp), kind, opts)
        return write_layout(cap, Path(out))

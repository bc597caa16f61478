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
from stages.ingest import colmap, nerfstudio, replica, select, sevenscenes

log = logging.getLogger(__name__)


def _read_blunf(src: Path, work: Path) -> Capture:
    """The project's own layout, read in place (`work` is not used)."""
    return read_layout(src)


READERS: dict[str, Callable[[Path, Path], Capture]] = {
    "blunf": _read_blunf,
    "7scenes": sevenscenes.read,
    "replica-vmap": replica.read,
    "nerfstudio": nerfstudio.read,
    "colmap": colmap.read,
}

IMPLS = {"auto": select.run}


def detect(src: Path) -> str:
    """Name of the layout of a capture folder (a key of READERS)."""
    src = Path(src)
    if src.is_file() and src.suffix == ".json":
        return "nerfstudio"
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
    raise BlunfError(f"{src}: not a known capture layout (known: {', '.join(READERS)})")


def load(src: Path, work: Path, kind: str = "auto") -> Capture:
    """Read the capture at src with the reader for `kind` ("auto" = detect it)."""
    src, work = Path(src), Path(work)
    if kind == "auto":
        kind = detect(src)
    if kind not in READERS:
        raise BlunfError(f"capture kind {kind!r} unknown (known: auto, {', '.join(READERS)})")
    check_exists(src, "capture folder")
    folder = src if src.is_dir() else src.parent
    if work.resolve().is_relative_to(folder.resolve()):
        raise BlunfError(f"{work}: work folder inside the capture {src}, which is never written")
    cap = READERS[kind](src, work)
    log.info("read %s capture %s: %d frames", kind, src, len(cap.frames))
    return cap


def import_capture(kind: str, src: Path, out: Path) -> Path:
    """Read a capture of layout `kind` and write it in the project's layout at out."""
    with tempfile.TemporaryDirectory(prefix="blunf-import-") as tmp:
        cap = load(src, Path(tmp), kind)
        return write_layout(cap, Path(out))

"""Reading a capture from a nerfstudio `transforms.json`, in place. The format (OpenGL camera
axes, pixel centres at 0.5) and its writer are in `stages.common.nerfstudio`."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics, check_pose
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import image_size, read_json
from stages.common.nerfstudio import DIST_KEYS, GL_CV, PIXEL_OFFSET

log = logging.getLogger(__name__)

# Perspective models whose distortion is OpenCV's (k1, k2, p1, p2[, k3]).
MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def _resolve(base: Path, rel: str, where: str) -> Path:
    p = base / rel
    if p.suffix == "" and not p.exists():  # Blender-style paths leave out the extension
        for ext in (".png", ".jpg"):
            if p.with_suffix(ext).exists():
                return p.with_suffix(ext)
    if not p.exists():
        raise BlunfError(f"{where}: file {rel!r} not found (looked for {p})")
    return p


def _intrinsics(meta: dict, frame: dict, image: Path, where: str) -> Intrinsics:
    """Per-frame keys override the top-level ones; w and h default to the image's size."""

    def get(key: str):
        return frame.get(key, meta.get(key))

    model = get("camera_model") or "OPENCV"
    if model not in MODELS:
        raise BlunfError(f"{where}: camera_model {model!r} not supported (use one of {MODELS})")
    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = image_size(image)
    try:
        w, h = int(w), int(h)
        fx = get("fl_x")
        if fx is None and get("camera_angle_x") is not None:
            fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
        if fx is None:
            raise BlunfError(f"{where}: no focal length (fl_x) for {image.name}")
        fx = float(fx)
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
        cx = float(get("cx") if get("cx") is not None else w / 2) - PIXEL_OFFSET
        cy = float(get("cy") if get("cy") is not None else h / 2) - PIXEL_OFFSET
        dist = [float(get(k) or 0.0) for k in DIST_KEYS]
    except (TypeError, ValueError) as e:
        raise BlunfError(f"{where}: bad intrinsics for {image.name} ({e})") from None
    if get("k4"):
        raise BlunfError(f"{where}: k4 (fisheye) distortion not supported for {image.name}")
    dist_t = tuple(dist if dist[4] else dist[:4]) if any(dist) else ()
    return Intrinsics(fx, fy, cx, cy, w, h, dist_t)


def read(src: Path, work: Path) -> Capture:
    """Read a nerfstudio folder (or its transforms.json) in place. `work` is not used."""
    src = Path(src)
    path = src if src.is_file() else src / "transforms.json"
    meta = read_json(path)
    where = str(path)
    raw = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(raw, list) or not raw:
        raise BlunfError(f"{where}: no 'frames' list")
    base = path.parent
    try:  # in file name order, as nerfstudio's own parser does
        raw = sorted(raw, key=lambda f: str(base / str(f["file_path"])))
    except (KeyError, TypeError):
        raise BlunfError(f"{where}: every frame needs a 'file_path'") from None
    frames, seen = [], set()
    for fr in raw:
        fw = f"{where} frame {fr['file_path']!r}"
        image = _resolve(base, str(fr["file_path"]), where)
        if image.stem in seen:
            raise BlunfError(f"{where}: two frames share the image name {image.stem!r}")
        seen.add(image.stem)
        if "transform_matrix" not in fr:
            raise BlunfError(f"{fw}: no transform_matrix")
        try:
            m = np.asarray(fr["transform_matrix"], np.float64)
        except (TypeError, ValueError):
            raise BlunfError(f"{fw}: transform_matrix is not numeric") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        pose = check_pose(m, fw) @ GL_CV  # [4, 4] c2w, OpenCV axes
        depth = fr.get("depth_file_path")
        frames.append(
            Frame(
                stem=image.stem,
                image=image,
                intrinsics=_intrinsics(meta, fr, image, fw),
                depth=_resolve(base, str(depth), fw) if depth else None,
                pose=pose,
            )
        )
    try:
        depth_scale = 1.0 / float(meta.get("depth_unit_scale_factor", 1e-3))
    except (TypeError, ValueError, ZeroDivisionError):
        raise BlunfError(f"{where}: bad depth_unit_scale_factor") from None
    log.info("nerfstudio %s: %d frames", path, len(frames))
    return Capture(
        root=base,
        frames=tuple(frames),
        depth_scale=depth_scale,
        depth_invalid=(),
        kind="nerfstudio",
    )

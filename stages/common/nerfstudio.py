"""nerfstudio `transforms.json`: its conventions, and writing one for other tools (the
ingest stage reads them).

Format: intrinsics `fl_x fl_y cx cy w h` (+ optional `k1 k2 p1 p2 k3`) at the top level or
per frame; `frames: [{file_path, transform_matrix, depth_file_path?}]`, paths relative to
the file's folder. `transform_matrix` is camera-to-world with OpenGL camera axes (x right,
y up, z back); the project uses OpenCV axes (x right, y down, z forward), so the camera's
y and z columns are negated both ways. nerfstudio (like COLMAP) puts the centre of the
top-left pixel at (0.5, 0.5) while the project puts it at (0, 0): cx and cy move by 0.5.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics
from stages.common.capture import Capture
from stages.common.errors import BlunfError
from stages.common.io import write_json

# Camera-axes change between OpenGL and OpenCV (its own inverse): c2w_cv = c2w_gl @ GL_CV.
GL_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# nerfstudio pixel coordinate of the top-left pixel's centre.
PIXEL_OFFSET = 0.5
DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")


def _intr_json(intr: Intrinsics) -> dict:
    d = {
        "fl_x": intr.fx,
        "fl_y": intr.fy,
        "cx": intr.cx + PIXEL_OFFSET,
        "cy": intr.cy + PIXEL_OFFSET,
        "w": intr.width,
        "h": intr.height,
    }
    d.update(zip(DIST_KEYS, intr.dist, strict=False))
    return d


def _rel(p: Path, base: Path) -> str:
    """Path relative to base when p lies under it, else absolute."""
    a, b = Path(os.path.abspath(p)), Path(os.path.abspath(base))
    return a.relative_to(b).as_posix() if a.is_relative_to(b) else str(a)


def write_transforms(capture: Capture, path: Path) -> Path:
    """Write the capture's frames (all posed) as a nerfstudio transforms.json. Returns path.

    Image paths are relative to the file's folder when the images lie under it. Depth is
    written for PNG depth maps only (nerfstudio reads .npy depth with the PNG scale).
    """
    path = Path(path)
    if not capture.frames:
        raise BlunfError(f"{path}: no frames to write")
    base = path.parent
    intrs = {f.intrinsics for f in capture.frames}
    shared = len(intrs) == 1
    meta: dict = {
        "camera_model": "OPENCV" if any(i.dist for i in intrs) else "PINHOLE",
    }
    if shared:
        meta.update(_intr_json(next(iter(intrs))))
    meta["depth_unit_scale_factor"] = 1.0 / capture.depth_scale
    out_frames = []
    for f in capture.frames:
        if f.pose is None:
            raise BlunfError(f"{path}: frame {f.stem!r} has no pose")
        entry: dict = {
            "file_path": _rel(f.image, base),
            "transform_matrix": (_put_back(f.pose, capture.origin) @ GL_CV).tolist(),
        }
        if not shared:
            entry.update(_intr_json(f.intrinsics))
        if f.depth is not None and f.depth.suffix.lower() == ".png":
            entry["depth_file_path"] = _rel(f.depth, base)
        out_frames.append(entry)
    meta["frames"] = out_frames
    base.mkdir(parents=True, exist_ok=True)
    write_json(path, meta)
    return path


def _put_back(pose: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """The pose in the capture's own (aligned) world: the recentring's offset added back."""
    p = np.array(pose, np.float64)
    p[:3, 3] += np.asarray(origin, np.float64)
    return p

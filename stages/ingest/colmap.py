"""Reader for a COLMAP sparse model (cameras/images/points3D as .bin or .txt) and its images.

Accepted layouts (src is the project folder or the model folder itself):
    src/sparse/0/cameras.bin  src/sparse/cameras.bin  src/cameras.bin   (or .txt)
    images in src/images, or in images/ one or two levels above the model folder.
Only registered images become frames. COLMAP stores world-to-camera (`cam_from_world`,
OpenCV axes); frames get its inverse. COLMAP puts the centre of the top-left pixel at
(0.5, 0.5) while the project puts it at (0, 0): cx and cy move by 0.5.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics, check_pose
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError

log = logging.getLogger(__name__)

PIXEL_OFFSET = 0.5  # COLMAP pixel coordinate of the top-left pixel's centre


def find_model(src: Path) -> Path | None:
    """The sparse model folder under src (src itself, sparse/0 or sparse), or None."""
    for d in (src, src / "sparse" / "0", src / "sparse"):
        if (d / "cameras.bin").exists() or (d / "cameras.txt").exists():
            return d
    return None


def _find_images(src: Path, model: Path) -> Path:
    for d in (src / "images", model.parent / "images", model.parent.parent / "images"):
        if d.is_dir():
            return d
    raise BlunfError(f"{model}: COLMAP model found but no images/ folder next to it")


def intrinsics_from_colmap(
    model_name: str, params: np.ndarray, width: int, height: int, where: str
) -> Intrinsics:
    """Project intrinsics of a COLMAP perspective camera (params in COLMAP's order)."""
    p = [float(x) for x in params]
    dist: tuple[float, ...]
    if model_name == "SIMPLE_PINHOLE":  # f, cx, cy
        fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], ()
    elif model_name == "PINHOLE":  # fx, fy, cx, cy
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], ()
    elif model_name == "SIMPLE_RADIAL":  # f, cx, cy, k
        fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0)
    elif model_name == "RADIAL":  # f, cx, cy, k1, k2
        fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0)
    elif model_name == "OPENCV":  # fx, fy, cx, cy, k1, k2, p1, p2
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], tuple(p[4:8])
    else:
        raise BlunfError(
            f"{where}: camera model {model_name} not supported "
            "(use PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV)"
        )
    if not any(dist):
        dist = ()
    return Intrinsics(fx, fy, cx - PIXEL_OFFSET, cy - PIXEL_OFFSET, width, height, dist)


def read(src: Path, work: Path) -> Capture:
    """Read a COLMAP model and its images in place. `work` is not used."""
    import pycolmap  # numpy is already imported (stages/__init__.py): the order matters

    src = Path(src)
    model = find_model(src)
    if model is None:
        sparse = src / "sparse" / "0" if (src / "sparse" / "0").is_dir() else src / "sparse"
        if sparse.is_dir():
            raise BlunfError(
                f"{sparse}: COLMAP model folder holds no model (no cameras.bin or cameras.txt);"
                " did the reconstruction finish?"
            )
        raise BlunfError(f"{src}: no COLMAP model (cameras.bin|txt in ., sparse/0 or sparse)")
    images_dir = _find_images(src, model)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError) as e:
        msg = str(e).splitlines()[0] if str(e) else e.__class__.__name__
        raise BlunfError(f"{model}: not a readable COLMAP model ({msg})") from None

    intr: dict[int, Intrinsics] = {}
    for cid, cam in rec.cameras.items():
        intr[cid] = intrinsics_from_colmap(
            cam.model.name,
            np.asarray(cam.params),
            int(cam.width),
            int(cam.height),
            f"{model} camera {cid}",
        )
    images = sorted(rec.images.values(), key=lambda im: im.name)
    posed = [im for im in images if im.has_pose]
    if not posed:
        raise BlunfError(f"{model}: no registered images")
    if len(posed) < len(images):
        log.info(
            "colmap %s: %d of %d images unregistered, left out",
            model,
            len(images) - len(posed),
            len(images),
        )
    frames, seen = [], set()
    for im in posed:
        path = images_dir / im.name
        if not path.exists():
            raise BlunfError(f"{path}: image of the COLMAP model not found")
        stem = Path(im.name).with_suffix("").as_posix().replace("/", "_")
        if stem in seen:
            raise BlunfError(f"{model}: two images share the name {stem!r}")
        seen.add(stem)
        w2c = np.eye(4)
        w2c[:3] = np.asarray(im.cam_from_world().matrix(), np.float64)  # [3, 4]
        pose = check_pose(np.linalg.inv(w2c), f"{model} image {im.name}")  # [4, 4] c2w
        frames.append(Frame(stem=stem, image=path, intrinsics=intr[im.camera_id], pose=pose))
    root = Path(os.path.commonpath([model.resolve(), images_dir.resolve()]))
    log.info("colmap %s: %d frames, %d cameras", model, len(frames), len(intr))
    return Capture(root=root, frames=tuple(frames), kind="colmap")

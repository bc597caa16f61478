"""Reader for Microsoft 7-Scenes sequences (the layout of data/7scenes-redkitchen).

    frames/frame-NNNNNN.color.jpg|png   RGB
    frames/frame-NNNNNN.depth.png       uint16 mm; 0 and 65535 mean no reading
    frames/frame-NNNNNN.pose.txt        4x4 camera-to-world, OpenCV camera axes, metres
    camera-intrinsics.txt               3x3 K (colour and depth share it)
    gravity-direction.txt               world gravity vector (optional)

The capture is read in place; the poses are also written to `work/gt/poses.json` so that a
structure-from-motion run on the same frames can be scored against them.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics, check_pose
from stages.common.capture import IMAGE_EXTS, Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import image_size, write_json

log = logging.getLogger(__name__)

COLOR_SUFFIX = ".color"  # frame-NNNNNN.color.jpg -> stem frame-NNNNNN


def read_matrix(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    """A whitespace-separated numeric text file of the given shape. Returns float64."""
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except FileNotFoundError:
        raise BlunfError(f"{path}: file not found") from None
    except (OSError, ValueError) as e:
        msg = str(e).splitlines()[0] if str(e) else e.__class__.__name__
        raise BlunfError(f"{path}: not a readable numeric matrix ({msg})") from None
    if a.size != int(np.prod(shape)):
        raise BlunfError(f"{path}: expected {'x'.join(map(str, shape))} numbers, got {a.shape}")
    return a.reshape(shape)


def read(src: Path, work: Path) -> Capture:
    """Read a 7-Scenes sequence folder in place; ground-truth poses go to work/gt/poses.json."""
    src = Path(src)
    frames_dir = src / "frames"
    if not frames_dir.is_dir():
        raise BlunfError(f"{src}: not a 7-Scenes sequence (no frames/ folder)")
    colors = sorted(
        p
        for p in frames_dir.iterdir()
        if p.suffix.lower() in IMAGE_EXTS and p.stem.endswith(COLOR_SUFFIX)
    )
    if not colors:
        raise BlunfError(f"{frames_dir}: no frame-*.color.jpg|png images")
    k_path = src / "camera-intrinsics.txt"
    K = read_matrix(k_path, (3, 3))  # [3, 3]
    width, height = image_size(colors[0])
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    intr = Intrinsics(fx, fy, cx, cy, width, height)

    frames = []
    for c in colors:
        stem = c.stem[: -len(COLOR_SUFFIX)]
        pose_path = frames_dir / f"{stem}.pose.txt"
        pose = check_pose(read_matrix(pose_path, (4, 4)), str(pose_path))  # [4, 4] c2w
        depth = frames_dir / f"{stem}.depth.png"
        frames.append(
            Frame(
                stem=stem,
                image=c,
                intrinsics=intr,
                depth=depth if depth.exists() else None,
                pose=pose,
            )
        )

    g_path = src / "gravity-direction.txt"
    gravity = None
    if g_path.exists():
        g = read_matrix(g_path, (3,))
        norm = float(np.linalg.norm(g))
        if not np.isfinite(norm) or norm < 1e-9:
            raise BlunfError(f"{g_path}: gravity must be a finite non-zero 3-vector")
        gravity = tuple(float(x) for x in g / norm)
    else:
        log.info("%s: no gravity-direction.txt; gravity left unknown", src)

    gt = Path(work) / "gt"
    gt.mkdir(parents=True, exist_ok=True)
    write_json(gt / "poses.json", {f.stem: np.asarray(f.pose).tolist() for f in frames})
    log.info("7scenes %s: %d frames, %dx%d", src, len(frames), width, height)
    return Capture(
        root=src,
        frames=tuple(frames),
        gravity=gravity,  # type: ignore[arg-type]
        depth_scale=1000.0,
        depth_invalid=(65535,),
        gt=gt,
        kind="7scenes",
    )

"""Reader for a video file: the sharpest frame of each of N equal windows becomes a photo.

Frames are decoded with PyAV, downscaled to the working size, turned upright by the video's
rotation metadata (its display matrix), scored by the variance of their Laplacian (higher =
sharper) and the best of each window written as JPEG into the work folder, which the ingest
stage's cache keeps (a rerun decodes nothing). Chosen frames much blurrier than the others
are reported. Intrinsics: the prior of exif.py (videos carry no focal length), one camera.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from stages.common.camera import Intrinsics
from stages.common.capture import Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import write_json
from stages.ingest import exif

log = logging.getLogger(__name__)

VIDEO_EXTS = (".mp4", ".mov", ".m4v")
PER_SECOND = 2.0  # frames kept per second of video when none are asked
AUTO_RANGE = (20, 100)  # ... but no fewer and no more than these
BLUR_FRACTION = 0.35  # a chosen frame under this fraction of the median sharpness is blurred
SHARPNESS_SIDE = 320  # sharpness is measured on the frame downscaled to this longer side


@dataclass(frozen=True)
class VideoOptions:
    frames: int = 0  # frames kept; 0 = by the video's length (PER_SECOND, within AUTO_RANGE)
    max_side: int = 0  # longer side of the frames written (pixels); 0 = the video's own


def auto_frames(seconds: float, total: int) -> int:
    """Frames kept when none are asked: PER_SECOND of video, within AUTO_RANGE."""
    lo, hi = AUTO_RANGE
    return min(total, max(lo, min(hi, round(PER_SECOND * seconds))))


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of a grey image [H, W] (higher = sharper)."""
    return float(np.var(ndimage.laplace(gray.astype(np.float32))))


def _open(src: Path):  # -> av.container.InputContainer
    import av

    try:
        c = av.open(str(src))
    except (av.FFmpegError, OSError, UnicodeDecodeError) as e:
        raise BlunfError(f"{src}: cannot decode the video ({_first_line(e)})") from None
    if not c.streams.video:
        c.close()
        raise BlunfError(f"{src}: no video stream in the file")
    return c


def _first_line(e: BaseException) -> str:
    return (str(e).splitlines() or [e.__class__.__name__])[0]


def _count(src: Path) -> int:
    """Number of video frames (from the header, else by reading the packets, not decoding)."""
    with _open(src) as c:
        s = c.streams.video[0]
        if s.frames and s.frames > 0:
            return int(s.frames)
        return sum(1 for p in c.demux(s) if p.size)


def _size(w: int, h: int, max_side: int) -> tuple[int, int]:
    s = max_side / max(w, h) if max_side > 0 else 1.0
    return (w, h) if s >= 1.0 else (max(1, round(w * s)), max(1, round(h * s)))


def read(src: Path, work: Path, opts: VideoOptions | None = None) -> Capture:
    """Decode the video at src, keep opts.frames sharp frames, write them into work/video."""
    import av

    opts = opts or VideoOptions()
    src = Path(src)
    if not src.is_file():
        raise BlunfError(f"{src}: video file not found")
    total = _count(src)
    if total == 0:
        raise BlunfError(f"{src}: the video has no frames")
    best: list[tuple[float, int, np.ndarray | None]] = []
    rotation = 0
    decoded = 0
    with _open(src) as c:
        s = c.streams.video[0]
        s.thread_type = "AUTO"
        rate = float(s.average_rate or s.guessed_rate or 0) or 30.0
        seconds = total / rate
        n = opts.frames if opts.frames > 0 else auto_frames(seconds, total)
        n = min(n, total)
        window = np.floor(np.arange(total) * n / total).astype(int)  # frame index -> window
        best = [(-1.0, -1, None)] * n
        try:
            for frame in c.decode(s):
                if decoded >= total:
                    break
                i, decoded = decoded, decoded + 1
                w, h = _size(frame.width, frame.height, opts.max_side)
                rotation = int(frame.rotation or 0)
                sw, sh = _size(frame.width, frame.height, SHARPNESS_SIDE)
                gray = frame.reformat(sw, sh, format="gray").to_ndarray()
                score = sharpness(gray)
                k = window[i]
                if score > best[k][0]:
                    rgb = frame.reformat(w, h, format="rgb24").to_ndarray()  # [h, w, 3]
                    best[k] = (score, i, rgb)
        except (av.FFmpegError, OSError) as e:
            raise BlunfError(f"{src}: cannot decode the video ({_first_line(e)})") from None
    picked = [(sc, i, a) for sc, i, a in best if a is not None]
    if not picked:
        raise BlunfError(f"{src}: no frame of the video could be decoded")
    k = (round(rotation / 90) % 4) if rotation % 90 == 0 else 0  # turns counterclockwise
    if rotation % 90:
        log.warning("video %s: rotation %d degrees not a multiple of 90: ignored", src, rotation)
    out = Path(work) / "video"
    out.mkdir(parents=True, exist_ok=True)
    frames = []
    med = float(np.median([sc for sc, _, _ in picked]))
    blurred = []
    for sc, i, a in picked:
        img = np.ascontiguousarray(np.rot90(a, k)) if k else a
        stem = f"frame-{i:06d}"
        path = out / f"{stem}.jpg"
        Image.fromarray(img).save(path, quality=95)
        h, w = img.shape[:2]
        f = exif.PRIOR_FACTOR * max(w, h)
        intr = Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
        frames.append(Frame(stem, path, intr, calib="prior", camera=f"video {w}x{h}"))
        if sc < BLUR_FRACTION * med:
            blurred.append(stem)
    if blurred:
        log.warning(
            "video %s: %d of %d chosen frames are blurred (sharpness < %.2f x the median): %s",
            src,
            len(blurred),
            len(frames),
            BLUR_FRACTION,
            ", ".join(blurred),
        )
    facts = {
        "file": str(src),
        "frames_total": total,
        "frames_decoded": decoded,
        "fps": rate,
        "seconds": seconds,
        "rotation_deg": rotation,
        "windows": n,
        "picked": [i for _, i, _ in picked],
        "sharpness": [round(sc, 3) for sc, _, _ in picked],
        "sharpness_median": med,
        "blurred": blurred,
    }
    write_json(out / "video.json", facts)
    log.info(
        "video %s: %d frames, %.1f s at %.3g fps, rotation %d; kept the sharpest of %d windows",
        src,
        total,
        seconds,
        rate,
        rotation,
        len(frames),
    )
    if not math.isfinite(med):
        raise BlunfError(f"{src}: the frames' sharpness is not a number")
    return Capture(root=out, frames=tuple(frames), kind="video")

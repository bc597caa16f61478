"""Reading and writing images, depth maps and label maps, with errors that name the file."""

from __future__ import annotations

import errno
import io
import json
import math
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from stages.common.errors import BlunfError

# Depth readings at or beyond this multiple of the map's median valid reading are treated as
# invalid (garbage far values; a scale-free cut, so kilometre or millimetre worlds read alike).
MAX_DEPTH_RATIO = 20.0
# PIL modes of a depth image: 16-bit integers (PNG) or 32-bit integers / floats (TIFF)
DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I;16N", "I", "F")


# what PIL raises on a file that is not a readable image; DecompressionBombError (a header
# claiming more pixels than PIL opens) is neither an OSError nor a ValueError
IMAGE_ERRORS = (
    UnidentifiedImageError,
    OSError,
    SyntaxError,
    ValueError,
    Image.DecompressionBombError,
)


def check_exists(path: Path, what: str) -> Path:
    """`path` as given, once it is known to lead somewhere; else a one-line error that says
    why not: not found, a symlink whose target is missing, a symlink loop, no permission.
    (Path.exists() answers False for all of these alike.) `what` names it ("capture folder")."""
    path = Path(path)
    try:
        os.stat(path)
        return path
    except FileNotFoundError:
        if path.is_symlink():
            raise BlunfError(
                f"{path}: {what} is a symlink to {os.readlink(path)}, which does not exist"
            ) from None
        raise BlunfError(f"{path}: {what} not found") from None
    except OSError as e:
        if e.errno == errno.ELOOP:
            loop = f"{path}: {what} is a symlink loop (it leads back to itself)"
            raise BlunfError(loop) from None
        raise BlunfError(f"{path}: cannot reach the {what} ({e.strerror})") from None


def _open(path: Path) -> Image.Image:
    try:
        img = Image.open(path)
        img.load()
        return img
    except FileNotFoundError:
        raise BlunfError(f"{path}: file not found") from None
    except IMAGE_ERRORS as e:
        raise BlunfError(f"{path}: not a readable image ({e.__class__.__name__})") from None


LUMA = (0.299, 0.587, 0.114)  # grey = these weights of R, G, B (ITU-R BT.601 luma)


def gray(rgb: np.ndarray) -> np.ndarray:
    """float32 [..., 3] (or anything that casts to it) -> float32 [...]: the LUMA-weighted
    grey the photos are matched and read in (stereo's sweep, the plane fill, the edges)."""
    return np.asarray(rgb, np.float32) @ np.asarray(LUMA, np.float32)


def read_image(path: Path) -> np.ndarray:
    """Read an RGB image. Returns uint8 [H, W, 3]."""
    return np.asarray(_open(Path(path)).convert("RGB"))


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    try:
        with Image.open(path) as img:
            return img.size
    except FileNotFoundError:
        raise BlunfError(f"{path}: file not found") from None
    except IMAGE_ERRORS as e:
        raise BlunfError(f"{path}: not a readable image ({e.__class__.__name__})") from None


def _check_depth_mode(img: Image.Image, path: Path) -> None:
    """Refuse a depth image that is not one channel of 16-bit (or wider) values: an 8-bit map
    holds at most 255 mm, and a colour one is not depth at all."""
    if img.mode in DEPTH_MODES:
        return
    what = "8-bit" if img.mode in ("1", "L", "P") else f"{len(img.getbands())}-channel"
    raise BlunfError(
        f"{path}: depth image is {what} (mode {img.mode}); depth must be a single-channel "
        "16-bit PNG in millimetres (or depth_scale units per metre) or a float .npy in metres"
    )


def depth_size(path: Path) -> tuple[int, int]:
    """(width, height) of a depth PNG from its header, refusing one that is not 16-bit."""
    path = Path(path)
    try:
        with Image.open(path) as img:
            _check_depth_mode(img, path)
            return img.size
    except FileNotFoundError:
        raise BlunfError(f"{path}: file not found") from None
    except IMAGE_ERRORS as e:
        raise BlunfError(f"{path}: not a readable image ({e.__class__.__name__})") from None


def read_depth(
    path: Path,
    scale: float = 1000.0,
    invalid: tuple[int, ...] = (65535,),
    max_ratio: float = MAX_DEPTH_RATIO,
) -> np.ndarray:
    """Read a depth map in metres. Returns float32 [H, W]; invalid readings are 0.

    PNG depth (16-bit; an 8-bit or colour map is an error) is divided by `scale` (units
    per metre). Zero, the `invalid` codes, NaN, inf,
    negative values and readings at or beyond `max_ratio` times the median of the map's
    positive finite readings all become 0 (missing). The cut scales with the map, so a world
    in millimetres or kilometres reads the same as one in metres.
    """
    path = Path(path)
    if path.suffix == ".npy":
        try:
            d = np.load(path).astype(np.float32)
        except (OSError, ValueError) as e:
            raise BlunfError(f"{path}: not a readable .npy depth map ({e})") from None
        if d.ndim != 2:
            raise BlunfError(f"{path}: depth must be 2-D, got shape {d.shape}")
    else:
        img = _open(path)
        _check_depth_mode(img, path)
        raw = np.asarray(img)
        bad = (
            np.isin(raw, np.asarray(invalid, dtype=raw.dtype))
            if invalid
            else np.zeros(raw.shape, bool)
        )
        d = raw.astype(np.float32) / np.float32(scale)
        d[bad] = 0.0
    d[~np.isfinite(d) | (d < 0)] = 0.0
    pos = d[d > 0]  # [M]
    if pos.size:
        cut = max_ratio * float(np.median(pos.astype(np.float64)))  # float64: no overflow
        d[d >= cut] = 0.0
    return d


def write_depth_npy(path: Path, depth_m: np.ndarray) -> None:
    """Write float metres [H, W] as float32 .npy (NaN, inf and negatives become 0 = missing).

    Unlike write_depth_png's millimetres, keeps ~7 significant digits at any scale.
    """
    d = np.asarray(depth_m, np.float32)
    d = np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0))
    np.save(path, d)


def write_depth_png(path: Path, depth_m: np.ndarray) -> None:
    """Write float metres [H, W] as uint16 millimetres (0 = missing).

    Fast deflate (level 1): ~0.03 s instead of ~0.13 s for a 640x480 view at the default
    level, for files a few percent larger; the pixels are the same.
    """
    d = np.nan_to_num(np.asarray(depth_m, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.clip(np.round(d * 1000.0), 0, 65534).astype(np.uint16)
    Image.fromarray(mm).save(path, compress_level=1)


def read_label(path: Path) -> np.ndarray:
    """Read a per-pixel id map (class or instance). Returns int32 [H, W]."""
    img = _open(Path(path))
    a = np.asarray(img)
    if a.ndim == 3:
        raise BlunfError(f"{path}: label map must be single-channel ids, got a colour image")
    return a.astype(np.int32)


def write_label_png(path: Path, labels: np.ndarray) -> None:
    """Write ids [H, W] as uint8 PNG (uint16 when an id exceeds 255)."""
    a = np.asarray(labels)
    dtype = np.uint8 if a.max(initial=0) <= 255 else np.uint16
    Image.fromarray(a.astype(dtype)).save(path)


def write_image(path: Path, rgb: np.ndarray) -> None:
    """Write uint8 [H, W, 3] RGB, atomically (a temp file beside it, then renamed): a write
    that fails or is killed leaves no half picture. The format follows the suffix."""
    path = Path(path)
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None:
        raise BlunfError(f"{path}: not an image file name (.png, .jpg)")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            Image.fromarray(np.asarray(rgb, np.uint8)).save(f, format=fmt)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_yaml(path: Path, what: str) -> Any:
    """The parsed YAML document at `path` (None when empty); `what` names the file in the
    one-line errors ("config file", "edit spec")."""
    import yaml

    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise BlunfError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise BlunfError(f"{path}: cannot read the {what} ({e})") from None
    except yaml.YAMLError as e:
        raise BlunfError(f"{path}: invalid YAML ({str(e).splitlines()[0]})") from None


def read_json(path: Path) -> Any:
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise BlunfError(f"{path}: file not found") from None
    except json.JSONDecodeError as e:
        raise BlunfError(f"{path}: invalid JSON at line {e.lineno}: {e.msg}") from None


def finite_json(v: Any) -> Any:
    """`v` with every non-finite float (NaN, inf; numpy's too) replaced by None."""
    if isinstance(v, dict):
        return {k: finite_json(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [finite_json(x) for x in v]
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(v) else None
    return v


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (temp file in the same folder, then rename), mode 0644."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        # strict JSON: a NaN or inf (an undefined metric) is written as null, never as the
        # NaN / Infinity tokens strict parsers refuse
        json.dump(finite_json(data), f, indent=1, default=_json_default, allow_nan=False)
        f.write("\n")
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def save_npz(path: Path, **arrays: Any) -> None:
    """np.savez_compressed with fixed member timestamps: equal contents give equal bytes
    (numpy stamps the current time, which would make cached outputs differ run to run)."""
    with zipfile.ZipFile(path, "w") as z:
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(a), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, buf.getvalue())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return finite_json(o.tolist())
    if isinstance(o, np.generic):
        return finite_json(o.item())
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")

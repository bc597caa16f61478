"""Reader for a plain folder of photos (no capture layout, no intrinsics).

Every .jpg / .png directly in the folder (or in its images/ folder) is a frame, in name
order. Intrinsics come from each photo's EXIF or a prior (exif.py); frames carry where from
(`Frame.calib`) and which camera (device and size) took them (`Frame.camera`), so the poses
stage estimates one camera each.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from stages.common.capture import IMAGE_EXTS, Capture, Frame
from stages.common.errors import BlunfError
from stages.ingest import exif


def image_files(folder: Path) -> list[Path]:
    """The images directly in folder (hidden files left out), in name order."""
    return sorted(
        p
        for p in Path(folder).iterdir()
        if p.suffix.lower() in IMAGE_EXTS and p.is_file() and not p.name.startswith(".")
    )


def read(src: Path, work: Path) -> Capture:
    """Read the photos of a flat folder in place. `work` is not used."""
    src = Path(src)
    if not src.is_dir():
        raise BlunfError(f"{src}: not a folder of photos")
    images = image_files(src)
    if not images and (src / "images").is_dir():  # the photos in an images/ folder
        images = image_files(src / "images")
    if not images:
        raise BlunfError(f"{src}: no .jpg or .png images in the folder")
    stems = Counter(p.stem for p in images)
    dup = next((p for p in images if stems[p.stem] > 1), None)
    if dup is not None:
        raise BlunfError(f"{dup}: two images share the name {dup.stem!r} (rename one)")
    frames = tuple(
        Frame(stem=p.stem, image=p, intrinsics=intr, calib=calib, camera=camera)
        for p, (intr, calib, camera) in zip(images, exif.guess_all(images), strict=True)
    )
    return Capture(root=src, frames=frames, kind="photos")


def intrinsics_facts(cap: Capture) -> dict:
    """Where the capture's intrinsics came from and their values, one entry per camera."""
    cams: dict[tuple[str, str], dict] = {}
    for f in cap.frames:
        i = f.intrinsics
        key = (f.camera, f.calib) if f.calib != "given" else ("", "given")
        c = cams.setdefault(
            key,
            {
                "camera": f.camera or None,
                "source": f.calib,
                "fx": i.fx,
                "fy": i.fy,
                "cx": i.cx,
                "cy": i.cy,
                "size": [i.width, i.height],
                "images": 0,
            },
        )
        c["images"] += 1
    sources = sorted({f.calib for f in cap.frames})
    return {"source": "/".join(sources), "cameras": list(cams.values())}

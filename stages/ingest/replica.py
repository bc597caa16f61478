"""Reader for Replica scenes as rendered for vMAP (the layout of data/replica-office0).

    rgb/NNNN.png            RGB
    depth/NNNN.png          uint16 mm
    instance/NNNN.png       instance id per pixel, 0 = unlabelled
    info_semantic.json      classes (id, name), objects (instance id -> class, oriented box)

Images, depth and instance maps are read in place (the frames name their instance map, so
the plan keeps objects of one class apart). Derived files go to `work`:
    labels/<stem>.png       CLASS ids (instance -> class through `objects`; 255 = unknown)
    gt/instances/<stem>.png the instance maps, for editing and evaluation
    gt/objects.json         {instance id: {class_id, class_name, oriented_bbox}}
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from stages.common.camera import Intrinsics
from stages.common.capture import IMAGE_EXTS, UNKNOWN, Capture, Frame
from stages.common.classes import CEILING_NAME
from stages.common.errors import BlunfError
from stages.common.io import image_size, read_json, read_label, write_json, write_label_png

log = logging.getLogger(__name__)

# vMAP's Replica renders: pinhole camera at 600x340 (after the 2x downscale of data/).
BASE_INTRINSICS = Intrinsics(fx=300.0, fy=300.0, cx=300.0, cy=170.0, width=600, height=340)


def class_table(info: dict, where: str) -> tuple[dict[int, str], dict[int, int]]:
    """Class table from info_semantic `classes`, with ids fitting 0..254.

    Returns ({capture id: name}, {Replica class id: capture id}). Ids are kept when they all
    fit; otherwise they are renumbered 0..K-1 in Replica id order (names kept).
    """
    try:
        pairs = sorted((int(c["id"]), str(c["name"])) for c in info["classes"])
        pairs = [(i, name) for i, name in pairs if i >= 0]  # negative ids mean "no class"
    except (KeyError, TypeError, ValueError) as e:
        raise BlunfError(f"{where}: bad 'classes' list ({e.__class__.__name__}: {e})") from None
    ids = [i for i, _ in pairs]
    if len(set(ids)) != len(ids):
        raise BlunfError(f"{where}: duplicate class ids in 'classes'")
    if len(pairs) > UNKNOWN:
        raise BlunfError(f"{where}: {len(pairs)} classes, at most {UNKNOWN} fit in uint8 labels")
    if all(0 <= i < UNKNOWN for i in ids):
        remap = {i: i for i in ids}
    else:
        remap = {i: n for n, i in enumerate(ids)}
        log.info("%s: class ids renumbered 0..%d to fit uint8 labels", where, len(ids) - 1)
    return {remap[i]: name for i, name in pairs}, remap


def instance_lut(info: dict, remap: dict[int, int], where: str) -> tuple[np.ndarray, dict]:
    """Instance id -> capture class id lookup table, and the gt objects table.

    Unlabelled (0), unknown instances and class_id < 0 map to 255. Instances missing from
    `objects` fall back to `id_to_label` when the file has it.
    Returns (lut [M] uint8, {instance id: {class_id, class_name, oriented_bbox}}).
    """
    objects: dict[int, dict] = {}
    try:
        for o in info.get("objects", []):
            cid = int(o["class_id"])
            objects[int(o["id"])] = {
                "class_id": remap.get(cid, UNKNOWN) if cid >= 0 else UNKNOWN,
                "class_name": str(o.get("class_name", "")),
                "oriented_bbox": o.get("oriented_bbox"),
            }
    except (KeyError, TypeError, ValueError) as e:
        raise BlunfError(f"{where}: bad 'objects' entry ({e.__class__.__name__}: {e})") from None
    id_to_label = info.get("id_to_label", [])
    size = max([256, len(id_to_label), *(i + 1 for i in objects)])
    lut = np.full(size, UNKNOWN, np.uint8)  # [M]
    for inst, cid in enumerate(id_to_label):
        if isinstance(cid, int) and cid >= 0 and inst > 0:
            lut[inst] = remap.get(cid, UNKNOWN)
    for inst, o in objects.items():
        lut[inst] = o["class_id"]
    lut[0] = UNKNOWN
    return lut, objects


def read(src: Path, work: Path) -> Capture:
    """Read a vMAP Replica folder: class label maps and instance ground truth go to work."""
    src, work = Path(src), Path(work)
    info_path = src / "info_semantic.json"
    info = read_json(info_path)
    if not isinstance(info, dict):
        raise BlunfError(f"{info_path}: expected a JSON object")
    classes, remap = class_table(info, str(info_path))
    lut, objects = instance_lut(info, remap, str(info_path))
    ignore = tuple(i for i, name in sorted(classes.items()) if CEILING_NAME in name.lower())

    rgb_dir = src / "rgb"
    images = (
        sorted(p for p in rgb_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        if rgb_dir.is_dir()
        else []
    )
    if not images:
        raise BlunfError(f"{rgb_dir}: no .png or .jpg images")
    width, height = image_size(images[0])
    intr = BASE_INTRINSICS
    if (width, height) != (intr.width, intr.height):
        log.info("replica: images are %dx%d, intrinsics scaled from 600x340", width, height)
        intr = intr.scaled(width, height)

    labels_dir, inst_dir = work / "labels", work / "gt" / "instances"
    labels_dir.mkdir(parents=True, exist_ok=True)
    inst_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for img in images:
        stem = img.stem
        depth = src / "depth" / f"{stem}.png"
        inst_path = src / "instance" / f"{stem}.png"
        label = None
        if inst_path.exists():
            inst = read_label(inst_path)  # [H, W] instance ids
            if inst.min() < 0:
                raise BlunfError(f"{inst_path}: negative instance ids")
            cls = lut[np.minimum(inst, len(lut) - 1)]  # [H, W] class ids
            cls[inst >= len(lut)] = UNKNOWN
            label = labels_dir / f"{stem}.png"
            write_label_png(label, cls)
            shutil.copyfile(inst_path, inst_dir / f"{stem}.png")
        frames.append(
            Frame(
                stem=stem,
                image=img,
                intrinsics=intr,
                depth=depth if depth.exists() else None,
                label=label,
                instance=inst_path if label is not None else None,  # objects kept apart
            )
        )
    write_json(work / "gt" / "objects.json", {str(k): v for k, v in sorted(objects.items())})
    n_frames, n_classes, n_objects = len(frames), len(classes), len(objects)
    log.info("replica %s: %d frames, %d classes, %d objects", src, n_frames, n_classes, n_objects)
    return Capture(
        root=src,
        frames=tuple(frames),
        classes=classes,
        ignore=ignore,
        # info_semantic's gravity_dir is in Replica's world frame; without poses the frames
        # are not in that frame (SfM picks its own), so the vector cannot be used here.
        gravity=None,
        depth_scale=1000.0,
        depth_invalid=(65535,),
        gt=work / "gt",
        kind="replica-vmap",
    )

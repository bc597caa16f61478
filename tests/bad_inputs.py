"""The cases of the bad-input table (tests/test_bad_input.py runs them): each breaks a private
copy of the tiny room, or passes a bad argument, and says what the error line must name.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from stages.common.io import write_depth_png
from tests.bomb import bomb_png

STEM = "0003"  # the frame each case breaks


# ---- what a case does to the capture ------------------------------------------------------
def _cams(cap: Path) -> dict:
    return json.loads((cap / "cameras.json").read_text())


def _set_cams(cap: Path, d: dict) -> None:
    (cap / "cameras.json").write_text(json.dumps(d))  # NaN is written as the JSON token NaN


def _edit_cams(fn: Callable[[dict], None]) -> Callable[[Path, Path], None]:
    def edit(cap: Path, tmp: Path) -> None:
        d = _cams(cap)
        fn(d)
        _set_cams(cap, d)

    return edit


def _img(cap: Path) -> Path:
    return cap / "images" / f"{STEM}.png"


def _truncate(cap: Path, tmp: Path) -> None:
    p = _img(cap)
    p.write_bytes(p.read_bytes()[:100])  # a valid PNG header, then nothing


def _garbage(cap: Path, tmp: Path) -> None:
    _img(cap).write_bytes(np.random.default_rng(0).bytes(777))


def _bomb(cap: Path, tmp: Path) -> None:
    _img(cap).write_bytes(bomb_png())  # claims 30000x30000: PIL's DecompressionBombError


def _photos_bomb(cap: Path, tmp: Path) -> None:
    """A plain photo folder (the capture's images alone), one of them a decompression bomb."""
    shutil.copytree(cap / "images", tmp / "photos")
    (tmp / "photos" / f"{STEM}.png").write_bytes(bomb_png())


def _run_folder(cap: Path, tmp: Path) -> None:
    """A finished run folder (its report.json, its .runs/) beside the capture."""
    (tmp / "runf" / ".runs").mkdir(parents=True)
    (tmp / "runf" / "report.json").write_text("{}")
    shutil.copytree(cap / "images", tmp / "runf" / "images")


def _empty_file(cap: Path, tmp: Path) -> None:
    _img(cap).write_bytes(b"")


def _mixed_sizes(cap: Path, tmp: Path) -> None:
    p = _img(cap)
    Image.open(p).resize((48, 36)).save(p)


def _depth_missing(cap: Path, tmp: Path) -> None:
    (cap / "depth" / f"{STEM}.png").unlink()


def _depth_size(cap: Path, tmp: Path) -> None:
    write_depth_png(cap / "depth" / f"{STEM}.png", np.full((36, 48), 2.0))


def _depth_rgb(cap: Path, tmp: Path) -> None:
    Image.new("RGB", (96, 72), (1, 2, 3)).save(cap / "depth" / f"{STEM}.png")


def _depth_npy_3d(cap: Path, tmp: Path) -> None:
    (cap / "depth" / f"{STEM}.png").unlink()
    np.save(cap / "depth" / f"{STEM}.npy", np.ones((72, 96, 3), np.float32))


def _depth_npy_garbage(cap: Path, tmp: Path) -> None:
    (cap / "depth" / f"{STEM}.png").unlink()
    (cap / "depth" / f"{STEM}.npy").write_bytes(b"\x93NUMPY garbage")


def _depth_8bit(cap: Path, tmp: Path) -> None:
    # an 8-bit grey map of the right size (values up to 255 "millimetres")
    Image.fromarray(np.full((72, 96), 200, np.uint8)).save(cap / "depth" / f"{STEM}.png")


def _depth_all_zero(cap: Path, tmp: Path) -> None:
    for p in (cap / "depth").iterdir():
        write_depth_png(p, np.zeros((72, 96)))


def _same_stem_jpg(cap: Path, tmp: Path) -> None:
    Image.open(_img(cap)).convert("RGB").save(cap / "images" / f"{STEM}.jpg", quality=95)


def _colmap_empty_model(cap: Path, tmp: Path) -> None:
    # a COLMAP project whose reconstruction never finished: images and an empty sparse/0
    (cap / "cameras.json").unlink()
    (cap / "sparse" / "0").mkdir(parents=True)


def _symlink_loop(cap: Path, tmp: Path) -> None:
    (tmp / "loop").symlink_to(tmp / "loop")


def _symlink_dangling(cap: Path, tmp: Path) -> None:
    (tmp / "dangling").symlink_to(tmp / "gone")


def _label_size(cap: Path, tmp: Path) -> None:
    Image.fromarray(np.zeros((36, 48), np.uint8)).save(cap / "labels" / f"{STEM}.png")


def _label_colour(cap: Path, tmp: Path) -> None:
    Image.new("RGB", (96, 72), (1, 2, 3)).save(cap / "labels" / f"{STEM}.png")


def _label_id_300(cap: Path, tmp: Path) -> None:
    a = np.asarray(Image.open(cap / "labels" / f"{STEM}.png")).astype(np.uint16)
    a[10:20, 10:20] = 300  # a class id beyond uint8 (caught by the project stage)
    Image.fromarray(a).save(cap / "labels" / f"{STEM}.png")


def _outside_file(cap: Path, tmp: Path, rel: str) -> None:
    outside = tmp / "outside" / Path(rel).name
    outside.parent.mkdir(exist_ok=True)
    shutil.copyfile(cap / rel, outside)
    (cap / rel).unlink()
    (cap / rel).symlink_to(outside)


def _symlink_image(cap: Path, tmp: Path) -> None:
    _outside_file(cap, tmp, f"images/{STEM}.png")


def _symlink_depth(cap: Path, tmp: Path) -> None:
    _outside_file(cap, tmp, f"depth/{STEM}.png")


def _symlink_images_dir(cap: Path, tmp: Path) -> None:
    shutil.move(cap / "images", tmp / "outside_images")
    (cap / "images").symlink_to(tmp / "outside_images")


def _no_images(cap: Path, tmp: Path) -> None:
    for p in (cap / "images").iterdir():
        p.unlink()


def _only_cameras(cap: Path, tmp: Path) -> None:
    shutil.rmtree(cap / "images")


def _text(name: str, text: str) -> Callable[[Path, Path], None]:
    def write(cap: Path, tmp: Path) -> None:
        (cap / name).write_text(text)

    return write


def _pose(value: object) -> Callable[[Path, Path], None]:
    def f(d: dict) -> None:
        d["frames"][STEM]["pose"] = value

    return _edit_cams(f)


def _nan_pose(d: dict) -> None:
    d["frames"][STEM]["pose"][0][3] = float("nan")


def _sheared_pose(d: dict) -> None:
    d["frames"][STEM]["pose"][0][1] += 0.5


def _no_intrinsics(d: dict) -> None:
    del d["intrinsics"]


def _no_fx(d: dict) -> None:
    del d["intrinsics"]["fx"]


def _negative_fx(d: dict) -> None:
    d["intrinsics"]["fx"] = -75.0


def _huge_focal(d: dict) -> None:
    d["intrinsics"]["fx"] = d["intrinsics"]["fy"] = 1e308  # finite and > 0, FOV ~0 degrees


def _wide_fov(d: dict) -> None:
    d["intrinsics"]["fx"] = d["intrinsics"]["fy"] = 2.0  # a 175-degree view at 96 px


def _far_principal_point(d: dict) -> None:
    d["intrinsics"]["cx"] = 5000.0


def _frame_tiny_focal(d: dict) -> None:
    d["frames"][STEM]["intrinsics"] = {**d["intrinsics"], "fx": 1e-3}


def _frame_entry(d: dict) -> None:
    d["frames"][STEM] = 5


def _depth_scale(value: object) -> Callable[[Path, Path], None]:
    def f(d: dict) -> None:
        d["depth_scale"] = value

    return _edit_cams(f)


def _gravity_zero(d: dict) -> None:
    d["gravity"] = [0, 0, 0]


def _blank_images(cap: Path, tmp: Path) -> None:
    for p in (cap / "images").iterdir():
        Image.new("RGB", (96, 72), (128, 128, 128)).save(p)


# ---- the table ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    name: str
    edit: Callable[[Path, Path], None] | None = None  # breaks the capture copy
    args: tuple[str, ...] = ()  # extra arguments; "{cap}" and "{tmp}" are substituted
    names: str = ""  # the error line must contain this ("{cap}"/"{tmp}" substituted)
    capture: str = "{cap}"  # the CAPTURE argument
    out: str = "{tmp}/run"  # the --out argument


CASES = [
    Case("image_truncated", _truncate, names=f"images/{STEM}.png"),
    Case("image_garbage", _garbage, names=f"images/{STEM}.png"),
    Case("image_empty_file", _empty_file, names=f"images/{STEM}.png"),
    Case("image_decompression_bomb", _bomb, names=f"images/{STEM}.png"),
    Case("photos_decompression_bomb", _photos_bomb, capture="{tmp}/photos", names=f"{STEM}.png"),
    Case("image_sizes_mixed", _mixed_sizes, names=f"images/{STEM}.png"),
    Case("depth_missing_for_one", _depth_missing, names=f"{STEM}.png"),
    Case("depth_wrong_size", _depth_size, names=f"depth/{STEM}.png"),
    Case("depth_png_rgb", _depth_rgb, names=f"depth/{STEM}.png"),
    Case("depth_npy_3d", _depth_npy_3d, names=f"depth/{STEM}.npy"),
    Case("depth_npy_garbage", _depth_npy_garbage, names=f"depth/{STEM}.npy"),
    Case("depth_png_8bit", _depth_8bit, names=f"depth/{STEM}.png: depth image is 8-bit"),
    Case("depth_all_zero", _depth_all_zero, names="{cap}/depth: the capture's depth is empty"),
    Case("label_wrong_size", _label_size, names=f"labels/{STEM}.png"),
    Case("label_colour", _label_colour, names=f"labels/{STEM}.png"),
    Case("label_id_300", _label_id_300, names=f"labels/{STEM}.png"),
    Case("symlink_image_outside", _symlink_image, names=f"images/{STEM}.png"),
    Case("symlink_depth_outside", _symlink_depth, names=f"depth/{STEM}.png"),
    Case("symlink_images_dir_outside", _symlink_images_dir, names="images"),
    Case("capture_empty", names="{tmp}/empty", capture="{tmp}/empty"),
    Case("capture_missing", names="{tmp}/missing", capture="{tmp}/missing"),
    Case("capture_is_a_file", names="{tmp}/file.txt", capture="{tmp}/file.txt"),
    Case(
        "capture_symlink_loop",
        _symlink_loop,
        capture="{tmp}/loop",
        names="{tmp}/loop: capture folder is a symlink loop",
    ),
    Case(
        "capture_symlink_dangling",
        _symlink_dangling,
        capture="{tmp}/dangling",
        names="{tmp}/dangling: capture folder is a symlink to {tmp}/gone, which does not exist",
    ),
    Case(
        "colmap_empty_sparse",
        _colmap_empty_model,
        names="{cap}/sparse/0: COLMAP model folder holds no model",
    ),
    Case(
        "image_same_stem_two_kinds",
        _same_stem_jpg,
        names=f"{{cap}}/images/{STEM}.jpg and {{cap}}/images/{STEM}.png",
    ),
    Case("capture_no_images", _no_images, names="images"),
    Case("capture_only_cameras_json", _only_cameras, names="{cap}"),
    Case("cameras_invalid_json", _text("cameras.json", '{"intrinsics": '), names="cameras.json"),
    Case("cameras_not_object", _text("cameras.json", "[1, 2]"), names="cameras.json"),
    Case("pose_3x4", _pose([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]), names=STEM),
    Case("pose_string", _pose("identity"), names=STEM),
    Case("pose_nan", _edit_cams(_nan_pose), names=STEM),
    Case("pose_sheared", _edit_cams(_sheared_pose), names=STEM),
    Case("intrinsics_missing", _edit_cams(_no_intrinsics), names="cameras.json"),
    Case("intrinsics_no_fx", _edit_cams(_no_fx), names="fx"),
    Case("intrinsics_negative_fx", _edit_cams(_negative_fx), names="cameras.json"),
    Case(
        "intrinsics_focal_1e308",
        _edit_cams(_huge_focal),
        names="cameras.json intrinsics: horizontal field of view",
    ),
    Case(
        "intrinsics_fov_175",
        _edit_cams(_wide_fov),
        names="cameras.json intrinsics: horizontal field of view 175 degrees",
    ),
    Case(
        "intrinsics_principal_point_far",
        _edit_cams(_far_principal_point),
        names="cameras.json intrinsics: principal point cx = 5000",
    ),
    Case(
        "intrinsics_of_one_frame_tiny_focal",
        _edit_cams(_frame_tiny_focal),
        names=f"cameras.json intrinsics of {STEM}: horizontal field of view 180 degrees",
    ),
    Case("cameras_frame_entry_not_object", _edit_cams(_frame_entry), names=STEM),
    Case("depth_scale_string", _depth_scale("mm"), names="depth_scale"),
    Case("depth_scale_zero", _depth_scale(0), names="depth_scale"),
    Case("gravity_zero", _edit_cams(_gravity_zero), names="gravity"),
    Case("gravity_string", _edit_cams(lambda d: d.update(gravity="down")), names="gravity"),
    Case(
        "depth_invalid_codes",
        _edit_cams(lambda d: d.update(depth_invalid="x")),
        names="depth_invalid",
    ),
    Case("labels_json_invalid", _text("labels.json", "{classes"), names="labels.json"),
    Case("labels_json_list", _text("labels.json", '{"classes": ["floor"]}'), names="labels.json"),
    Case(
        "labels_json_bad_id", _text("labels.json", '{"classes": {"x": "a"}}'), names="labels.json"
    ),
    Case("set_unknown_key", args=("--set", "fusion.voxell=0.1"), names="fusion.voxell"),
    Case("set_unknown_section", args=("--set", "fuson.voxel=0.1"), names="fuson"),
    Case("set_wrong_type_float", args=("--set", "fusion.voxel=abc"), names="fusion.voxel"),
    Case("set_wrong_type_int", args=("--set", "blueprint.blunf.steps=1.5"), names="steps"),
    Case("set_no_equals", args=("--set", "fusion.voxel"), names="fusion.voxel"),
    Case("set_out_of_range", args=("--set", "fusion.voxel=-1"), names="fusion.voxel"),
    Case("set_unknown_impl", args=("--set", "fusion.impl=nope"), names="nope"),
    # every numeric setting finite (a `> 0` check lets inf through): refused at config load
    Case("set_voxel_inf", args=("--set", "fusion.voxel=.inf"), names="fusion.voxel"),
    Case("set_lr_inf", args=("--set", "blueprint.blunf.lr=.inf"), names="blueprint.blunf.lr"),
    Case("set_lr_nan", args=("--set", "blueprint.blunf.lr=.nan"), names="blueprint.blunf.lr"),
    Case("set_depth_max_inf", args=("--set", "fusion.depth_max=.inf"), names="fusion.depth_max"),
    Case("set_cell_nan", args=("--set", "project.cell=.nan"), names="project.cell"),
    Case("set_cell_zero", args=("--set", "project.cell=0"), names="project.cell"),
    Case("set_cell_negative", args=("--set", "project.cell=-0.02"), names="project.cell"),
    Case("set_threads_negative", args=("--set", "run.threads=-1"), names="run.threads"),
    # sizes that would take more memory than the machine has: refused in one line
    Case(  # the plan field's loss turns NaN: the run fails, no all-floor plan published
        "blunf_diverges",
        args=("--set", "blueprint.blunf.lr=1e30"),
        names="blueprint.blunf: the training diverged",
    ),
    Case(
        "set_block_resolution_huge",
        args=("--set", "fusion.block_resolution=1000"),
        names="fusion.block_resolution=1000",
    ),
    Case(
        "set_planes_huge",
        args=("--set", "depth.stereo.planes=10000000"),
        names="depth.stereo.planes=10000000",
    ),
    Case("set_unknown_method", args=("--set", "run.methods=blunf,nope"), names="nope"),
    Case("config_missing", args=("--config", "{tmp}/nope.yaml"), names="{tmp}/nope.yaml"),
    Case("config_is_a_folder", args=("--config", "{tmp}/empty"), names="{tmp}/empty"),
    Case(
        "config_invalid_yaml",
        _text("../bad.yaml", "fusion: [\n"),
        ("--config", "{tmp}/bad.yaml"),
        names="{tmp}/bad.yaml",
    ),
    Case(
        "config_not_mapping",
        _text("../bad.yaml", "- 1\n"),
        ("--config", "{tmp}/bad.yaml"),
        names="{tmp}/bad.yaml",
    ),
    Case(
        "config_unknown_key",
        _text("../bad.yaml", "fusion: {voxell: 1}\n"),
        ("--config", "{tmp}/bad.yaml"),
        names="fusion.voxell",
    ),
    Case(
        "config_section_scalar",
        _text("../bad.yaml", "fusion: 3\n"),
        ("--config", "{tmp}/bad.yaml"),
        names="fusion",
    ),
    Case("frames_0", args=("--frames", "0"), names="'0'"),
    Case("frames_negative", args=("--frames", "-1"), names="'-1'"),
    Case("frames_abc", args=("--frames", "abc"), names="'abc'"),
    Case("edits_missing", args=("--edits", "{tmp}/nope.yaml"), names="{tmp}/nope.yaml"),
    Case(
        "edits_unknown_op",
        _text("../edits.yaml", "edits:\n  - select: {class: chair}\n    op: explode\n"),
        ("--edits", "{tmp}/edits.yaml"),
        names="edits[0].op",
    ),
    Case(
        "edits_texture_outside",
        _text(
            "../edits.yaml",
            "edits:\n  - select: {class: chair}\n    op: retexture\n"
            "    texture: ../../etc/passwd\n",
        ),
        ("--edits", "{tmp}/edits.yaml"),
        names="edits[0].texture",
    ),
    Case("capture_is_a_run_folder", _run_folder, capture="{tmp}/runf", names="a run folder"),
    Case(  # known at ingest (the class table), not after the NeRF trained
        "edits_class_not_in_table",
        _text("../edits.yaml", "edits:\n  - select: {class: piano}\n    op: remove\n"),
        ("--edits", "{tmp}/edits.yaml"),
        names="no class 'piano' in the capture's classes",
    ),
    Case("out_inside_capture", out="{cap}/run", names="{cap}/run"),
    Case("out_is_capture", out="{cap}", names="{cap}"),
    Case("out_is_a_file", out="{tmp}/file.txt", names="{tmp}/file.txt"),
    Case("sfm_blank_images", _blank_images, ("--set", "poses.impl=sfm"), names="registered"),
]

# Run again through `python -m pipeline` (fresh interpreter, real argv, real stderr).
SUBPROCESS = ("image_truncated", "frames_abc", "config_invalid_yaml", "depth_png_8bit")

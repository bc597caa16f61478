"""The bad-spec table: every broken edit spec fails before any work, in one line naming the
entry at fault, with nothing written to the stage's output folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from stages.common.blueprint import Blueprint, Grid
from stages.common.camera import Intrinsics
from stages.common.capture import UNKNOWN, Capture, Frame
from stages.common.errors import BlunfError
from stages.common.io import write_image
from stages.edit import IMPLS, EditConfig, EditInputs, load_spec, spec_textures

ROOT = Path(__file__).resolve().parents[2]
OK_EDIT = "  - {select: {click: [0.6, 0.6]}, op: remove}\n"

# (id, spec text, the start of the expected message after "<spec path>: ")
CASES = [
    ("yaml_syntax", "edits: [\n", "invalid YAML"),
    ("not_a_mapping", "- 1\n- 2\n", "an edit spec is a mapping"),
    ("unknown_top_key", f"edits:\n{OK_EDIT}view: [0]\n", "unknown key 'view'"),
    ("no_edits", "views: [0]\n", "edits: must be a non-empty list"),
    ("empty_edits", "edits: []\n", "edits: must be a non-empty list"),
    ("edit_not_mapping", "edits: [remove]\n", "edits[0]: must be a mapping"),
    ("missing_op", "edits:\n  - {select: {click: [0.6, 0.6]}}\n", "edits[0]: missing 'op'"),
    (
        "unknown_op",
        f"edits:\n{OK_EDIT}  - {{select: {{click: [0.6, 0.6]}}, op: explode}}\n",
        "edits[1].op: unknown op 'explode'",
    ),
    ("missing_select", "edits:\n  - {op: remove}\n", "edits[0]: missing 'select'"),
    (
        "two_selectors",
        "edits:\n  - {select: {click: [0.6, 0.6], class: chair}, op: remove}\n",
        "edits[0].select: give exactly one of",
    ),
    ("unknown_selector", "edits:\n  - {select: {lasso: 1}, op: remove}\n", "edits[0].select"),
    (
        "click_not_xy",
        "edits:\n  - {select: {click: [0.6]}, op: remove}\n",
        "edits[0].select.click: must be [x, y]",
    ),
    (
        "click_outside_plan",
        "edits:\n  - {select: {click: [5, 1]}, op: remove}\n",
        "edits[0].select.click: (5, 1) lies outside the plan",
    ),
    (
        "click_on_unknown_cell",
        "edits:\n  - {select: {click: [0.05, 1.95]}, op: remove}\n",
        "edits[0].select.click: lands on an unknown",
    ),
    (
        "pixel_outside_plan",
        "edits:\n  - {select: {pixel: [20, 3]}, op: remove}\n",
        "edits[0].select.pixel: [20, 3] lies outside the plan (20 x 20 cells)",
    ),
    (
        "pixel_negative",
        "edits:\n  - {select: {pixel: [-1, 3]}, op: remove}\n",
        "edits[0].select.pixel: must be [u, v]",
    ),
    (
        "class_not_in_table",
        "edits:\n  - {select: {class: chiar}, op: remove}\n",
        "edits[0].select.class: no class 'chiar' in the plan",
    ),
    (
        "class_not_on_plan",
        "edits:\n  - {select: {class: sofa}, op: remove}\n",
        "edits[0].select.class: no cell of class 'sofa'",
    ),
    (
        "polygon_two_points",
        "edits:\n  - {select: {polygon: [[0, 0], [1, 1]]}, op: remove}\n",
        "edits[0].select.polygon: must be a list of at least 3 points",
    ),
    (
        "polygon_no_area",
        "edits:\n  - {select: {polygon: [[0, 0], [1, 1], [2, 2]]}, op: remove}\n",
        "edits[0].select.polygon: the polygon encloses no area",
    ),
    (
        "polygon_off_plan",
        "edits:\n  - {select: {polygon: [[5, 5], [6, 5], [6, 6]]}, op: remove}\n",
        "edits[0].select.polygon: covers no known cell",
    ),
    (
        "stroke_without_width",
        "edits:\n  - {select: {stroke: [[0, 1], [2, 1]]}, op: sketch, color: [0, 0, 0]}\n",
        "edits[0].select: a stroke needs 'width'",
    ),
    (
        "stroke_zero_width",
        "edits:\n  - {select: {stroke: [[0, 1], [2, 1]], width: 0}, op: mask}\n",
        "edits[0].select.width: must be > 0",
    ),
    (
        "recolor_without_color",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: recolor}\n",
        "edits[0]: recolor needs 'color'",
    ),
    (
        "color_out_of_range",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: recolor, color: [300, 0, 0]}\n",
        "edits[0].color: must be [r, g, b] with values in 0..255",
    ),
    (
        "strength_out_of_range",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: recolor, color: [9, 9, 9], strength: 1.5}\n",
        "edits[0].strength: must be in [0, 1]",
    ),
    (
        "misspelt_key",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: recolor, colour: [9, 9, 9]}\n",
        "edits[0]: unknown key 'colour'",
    ),
    (
        "key_of_another_op",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: remove, color: [9, 9, 9]}\n",
        "edits[0]: unknown key 'color' (remove takes no settings)",
    ),
    (
        "texture_outside_folder",
        f"edits:\n{OK_EDIT}  - {{select: {{pixel: [5, 13]}}, op: retexture, texture: ../x.png}}\n",
        "edits[1].texture: ../x.png lies outside the spec's folder",
    ),
    (
        "texture_absolute_outside",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: retexture, texture: /etc/hostname}\n",
        "edits[0].texture: /etc/hostname lies outside the spec's folder",
    ),
    (
        "texture_missing",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: retexture, texture: textures/no.png}\n",
        "edits[0].texture: textures/no.png not found",
    ),
    (
        "texture_not_an_image",
        "edits:\n  - {select: {click: [0.6, 0.6]}, op: retexture, texture: textures/notes.txt}\n",
        "edits[0].texture: textures/notes.txt is not a readable image",
    ),
    ("view_out_of_range", f"edits:\n{OK_EDIT}views: [0, 7]\n", "views[1]: frame 7 does not exist"),
    ("view_negative", f"edits:\n{OK_EDIT}views: [-1]\n", "views: must be a non-empty list"),
    (
        "orbit_missing_field",
        f"edits:\n{OK_EDIT}views: {{orbit: {{center: [1, 1, 0], height: 1, frames: 4}}}}\n",
        "views.orbit: missing 'radius'",
    ),
    (
        "orbit_zero_radius",
        f"edits:\n{OK_EDIT}views: {{orbit: {{center: [1,1,0], radius: 0, height: 1, frames: 2}}}}",
        "views.orbit.radius: must be > 0",
    ),
]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    """A 20 x 20 plan (0.1 m cells): floor, one chair on columns 4..7 / rows 12..15, cell (0, 0)
    unknown, and a `sofa` class with no cell; 3 posed frames; a mesh; a 2 x 2 texture."""
    tmp = tmp_path_factory.mktemp("edit_spec")
    lab = np.zeros((20, 20), np.uint8)
    lab[12:16, 4:8] = 4
    lab[0, 0] = UNKNOWN
    Blueprint(lab, Grid((0.0, 0.0), 0.1, (20, 20)), {0: "floor", 4: "chair", 5: "sofa"}).save(
        tmp / "blueprint.npz"
    )
    intr = Intrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    frames = tuple(Frame(f"{i:04d}", tmp / f"{i:04d}.png", intr, pose=np.eye(4)) for i in range(3))
    Capture(tmp, frames).save(tmp / "frames.json")
    trimesh.creation.box(bounds=[[0.45, 0.45, 0.0], [0.75, 0.75, 0.5]]).export(tmp / "mesh.ply")
    (tmp / "model.pt").write_bytes(b"not a model")
    spec_dir = tmp / "spec"
    (spec_dir / "textures").mkdir(parents=True)
    write_image(spec_dir / "textures" / "wood.png", np.zeros((2, 2, 3), np.uint8))
    (spec_dir / "textures" / "notes.txt").write_text("not an image")
    (tmp / "x.png").write_bytes((spec_dir / "textures" / "wood.png").read_bytes())
    return {"tmp": tmp, "spec_dir": spec_dir}


def _inputs(scene: dict, spec: Path, textures: tuple[Path, ...] = ()) -> EditInputs:
    t = scene["tmp"]
    return EditInputs(
        spec=spec,
        blueprint=t / "blueprint.npz",
        model=t / "model.pt",
        mesh=t / "mesh.ply",
        frames=t / "frames.json",
        textures=textures,
    )


@pytest.mark.parametrize(("text", "expect"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_spec_fails_before_any_work(scene, tmp_path, text, expect):
    spec = scene["spec_dir"] / "edits.yaml"
    spec.write_text(text)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(BlunfError) as err:
        IMPLS["nerf"](EditConfig(), _inputs(scene, spec), out)
    msg = str(err.value)
    assert msg.startswith(f"{spec}: {expect}"), msg
    assert "\n" not in msg
    assert list(out.iterdir()) == []


def test_table_is_large():
    assert len(CASES) >= 10


def test_a_good_spec_passes_every_check(scene, tmp_path):
    # every selector and op, a texture, frame views: the checks pass and the stage goes on
    # to load the model, which here is garbage -- still with nothing written
    spec = scene["spec_dir"] / "good.yaml"
    spec.write_text(
        "edits:\n"
        "  - {select: {click: [0.6, 0.6]}, op: remove}\n"
        "  - {select: {pixel: [5, 13]}, op: recolor, color: [200, 40, 40], strength: 0.7}\n"
        "  - {select: {class: chair}, op: mask}\n"
        "  - {select: {polygon: [[0, 0], [1, 0], [1, 1]]}, op: retexture,"
        " texture: textures/wood.png}\n"
        "  - {select: {stroke: [[0, 1], [2, 1]], width: 0.1}, op: sketch, color: [0, 0, 0]}\n"
        "views: [0, 2]\n"
    )
    tex = spec_textures(spec)
    assert tex == ((scene["spec_dir"] / "textures" / "wood.png").resolve(),)
    s = load_spec(spec)
    assert [e.op for e in s.edits] == ["remove", "recolor", "mask", "retexture", "sketch"]
    assert s.views == (0, 2) and s.orbit is None
    out = tmp_path / "out"
    out.mkdir()
    # the texture must be listed in the inputs (the pipeline's cache key depends on it)
    with pytest.raises(BlunfError, match="is not in EditInputs.textures"):
        IMPLS["nerf"](EditConfig(), _inputs(scene, spec), out)
    with pytest.raises(BlunfError, match="not a NeRF model"):
        IMPLS["nerf"](EditConfig(), _inputs(scene, spec, tex), out)
    assert list(out.iterdir()) == []


def test_orbit_views_parse(scene):
    spec = scene["spec_dir"] / "orbit.yaml"
    spec.write_text(
        f"edits:\n{OK_EDIT}views:\n  orbit: {{center: [1, 1, 0.5], radius: 2, height: 1.5,"
        " frames: 8}"
    )
    s = load_spec(spec)
    assert s.views == () and s.orbit is not None
    assert (s.orbit.center, s.orbit.radius, s.orbit.height, s.orbit.frames) == (
        (1.0, 1.0, 0.5),
        2.0,
        1.5,
        8,
    )


def test_demo_spec_is_valid():
    s = load_spec(ROOT / "configs" / "edits" / "demo.yaml")
    ops = [e.op for e in s.edits]
    assert "remove" in ops and "recolor" in ops and "retexture" in ops
    for t in s.textures:
        assert t.is_relative_to((ROOT / "configs" / "edits").resolve()) and t.stat().st_size < 4096

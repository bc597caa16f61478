"""The edit stage's nested settings: their keys, the flat keys of earlier versions, the
choices typed as Literal, and a run's recorded settings read back by this version."""

from __future__ import annotations

import json

import pytest

from pipeline.config import default_config, load_config, recorded_sections
from pipeline.render import edit_config
from stages.common.errors import BlunfError
from stages.edit.config import EditConfig


@pytest.mark.parametrize(
    "old, new",
    [
        ("edit.floor_class=floor", "edit.select.floor_class"),
        ("edit.floor_band=0.1", "edit.select.floor_band"),
        ("edit.floor_clear=0.01", "edit.select.floor_clear"),
        ("edit.gap=0.2", "edit.select.gap"),
        ("edit.min_run=0.1", "edit.select.min_run"),
        ("edit.top_margin=0.1", "edit.select.top_margin"),
        ("edit.pad=0.1", "edit.select.pad"),
        ("edit.render=surface", "edit.render.path"),
        ("edit.render_scale=0.5", "edit.render.scale"),
        ("edit.mask_threshold=0.4", "edit.render.mask_threshold"),
        ("edit.chunk=4096", "edit.render.chunk"),
        ("edit.threads=1", "edit.render.threads"),
        ("edit.refine_voxel=0.01", "edit.refine.voxel"),
        ("edit.refine_trunc=3", "edit.refine.trunc"),
        ("edit.refine_margin=0.1", "edit.refine.margin"),
        ("edit.gif_frames=2", "edit.gif.frames"),
        ("edit.gif_scale=0.25", "edit.gif.scale"),
        ("edit.gif_ms=50", "edit.gif.ms"),
    ],
)
def test_a_flat_key_of_earlier_versions_fails_naming_its_new_place(old, new):
    key = old.partition("=")[0]
    with pytest.raises(BlunfError, match=rf"{key}: renamed to {new}$") as e:
        load_config(None, [old])
    assert "\n" not in str(e.value)


def test_a_flat_key_in_a_yaml_file_names_the_file(tmp_path):
    p = tmp_path / "old.yaml"
    p.write_text("edit:\n  render: surface\n  refine_voxel: 0.01\n")
    with pytest.raises(BlunfError, match=r"old.yaml: edit.render: renamed to edit.render.path$"):
        load_config(p)


def test_every_nested_key_is_set_where_it_says():
    cfg = load_config(
        None,
        [
            "edit.select.pad=0.1",
            "edit.render.path=surface",
            "edit.render.scale=0.5",
            "edit.refine.voxel=0.01",
            "edit.gif.frames=3",
        ],
    )["edit"]
    assert cfg.select.pad == 0.1 and cfg.render.path == "surface" and cfg.render.scale == 0.5
    assert cfg.refine.voxel == 0.01 and cfg.gif.frames == 3
    assert default_config()["edit"] == EditConfig()


@pytest.mark.parametrize(
    "bad, named",
    [
        ("edit.render.path=raster", "edit.render.path"),
        ("edit.impl=splat", "edit.impl"),
        ("edit.removed_label=wall", "edit.removed_label"),
        ("edit.select.pad=-1", "edit.select.pad"),
        ("edit.refine.trunc=0.5", "edit.refine.trunc"),
        ("edit.gif.scale=5", "edit.gif.scale"),
        ("edit.render.chunk=0", "edit.render.chunk"),
        ("edit.render.mask_threshold=2", "edit.render.mask_threshold"),
        ("edit.change_threshold=-0.1", "edit.change_threshold"),
    ],
)
def test_a_bad_value_fails_at_load_naming_its_key(bad, named):
    with pytest.raises(BlunfError, match=named.replace(".", r"\.")) as e:
        load_config(None, [bad])
    assert "\n" not in str(e.value)


def test_settings_a_run_of_an_earlier_version_recorded_are_read_in_their_new_place():
    # report.json's `config.edit` as the flat version wrote it (json round trip: lists, floats)
    old = json.loads(
        json.dumps(
            {
                "impl": "nerf",
                "render": "surface",
                "refine_voxel": 0.01,
                "floor_clear": 0.01,
                "gif_frames": 5,
                "threads": 2,
                "retired_knob": 3,  # a key this version does not know: dropped
            }
        )
    )
    cfg = edit_config(old)
    assert cfg.render.path == "surface" and cfg.refine.voxel == 0.01
    assert cfg.select.floor_clear == 0.01 and cfg.gif.frames == 5 and cfg.render.threads == 2
    # the nested form this version records reads back to the same config
    new = json.loads(json.dumps(default_config().to_dict()["edit"]))
    assert edit_config(new) == EditConfig()
    # the studio's trainer loads a whole recorded config the same way
    sections = recorded_sections({"edit": old, "nerf": {"threads": 1}, "gone": {}})
    assert sections["edit"]["render"] == {"path": "surface", "threads": 2}
    assert "gone" not in sections


def test_a_recorded_config_leaves_the_plan_cell_to_its_one_place(tmp_path):
    # a run records depth.stereo.cell (passed from project.cell); read back, it is not a
    # second setting of the plan cell
    rec = default_config().to_dict()
    rec["project"]["cell"] = 0.04
    rec["depth"]["stereo"]["cell"] = 0.04
    sections = recorded_sections(json.loads(json.dumps(rec)))
    assert "cell" not in sections["depth"]["stereo"]
    p = tmp_path / "recorded.yaml"
    p.write_text(json.dumps(sections))  # JSON is YAML
    cfg = load_config(p)
    assert cfg["project"].cell == 0.04 and cfg["depth"].stereo.cell == 0.04

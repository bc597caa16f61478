"""Typed config: YAML and --set override defaults; unknown keys and bad types are errors;
every field of every stage config reaches that stage's cache key (STYLE.md 4)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from pipeline.cache import stage_key
from pipeline.config import default_config, load_config, stage_view
from stages.common.errors import BlunfError

ROOT = Path(__file__).resolve().parents[2]


def test_set_overrides_nested_and_coerces():
    cfg = load_config(None, ["fusion.voxel=0.05", "blueprint.blunf.steps=123", "run.methods=mvr"])
    assert cfg["fusion"].voxel == 0.05
    assert cfg["blueprint"].blunf.steps == 123
    assert cfg.run.methods == ("mvr",)


def test_yaml_file_and_unknown_keys(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("fusion:\n  voxel: 0.03\n")
    assert load_config(p)["fusion"].voxel == 0.03
    p.write_text("fusion:\n  voxle: 0.03\n")
    with pytest.raises(BlunfError, match=r"c.yaml.*fusion.voxle"):
        load_config(p)
    p.write_text("fusio:\n  voxel: 0.03\n")
    with pytest.raises(BlunfError, match="unknown section 'fusio'"):
        load_config(p)
    with pytest.raises(BlunfError, match="expected a number"):
        load_config(None, ["fusion.voxel=abc"])
    with pytest.raises(BlunfError, match="config file not found"):
        load_config(tmp_path / "missing.yaml")


def _leaves(obj, prefix=""):
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _leaves(v, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", v


def _changed(v):
    if isinstance(v, bool):
        return not v
    if isinstance(v, int):
        return v + 1
    if isinstance(v, float):
        return v * 1.5 + 0.1
    if isinstance(v, str):
        return v + "x"
    if isinstance(v, tuple):
        return (*v, v[0]) if v else ("x",)
    if v is None:
        return 1.0
    raise AssertionError(f"no change rule for {v!r}")


def _valid_other(cfg, name, value):
    """A different value the config accepts (for fields checked in __post_init__)."""
    for cand in (
        value * 2 if isinstance(value, int | float) and value else 1,
        value + 2 if isinstance(value, int) and not isinstance(value, bool) else 1,  # odd stays odd
        "none",
        "sequential",
        "global",
        "exhaustive",
        "depth",
        "floor",
        "top",
        "pe",
        "unknown",
        "field",
        "surface",
        "sqrt",
        "rays",
        "height",
        "all",
        "normals",
    ):
        if cand == value:
            continue
        try:
            _with(cfg, name, cand)
            return cand
        except (BlunfError, TypeError):
            continue
    raise AssertionError(f"no accepted change for {name}={value!r}")


def _with(obj, dotted, value):
    head, _, rest = dotted.partition(".")
    if rest:
        return dataclasses.replace(obj, **{head: _with(getattr(obj, head), rest, value)})
    return dataclasses.replace(obj, **{head: value})


@pytest.mark.parametrize("stage", list(default_config().stages))
def test_every_config_field_changes_the_cache_key(stage):
    cfg = default_config()[stage]
    impl = cfg.impl
    base = stage_key(stage, impl, stage_view(cfg, impl), {})
    for name, value in _leaves(cfg):
        if name == "impl":
            continue
        try:
            changed = _with(cfg, name, _changed(value))
        except BlunfError:  # validated field: the arbitrary change is refused, try another
            changed = _with(cfg, name, _valid_other(cfg, name, value))
        view = stage_view(changed, impl)
        if name.split(".")[0] != impl and name.split(".")[0] in _other_impl_sections(cfg, impl):
            continue  # another implementation's section: must NOT change this key (below)
        assert stage_key(stage, impl, view, {}) != base, f"{stage}.{name} does not reach the key"


def _other_impl_sections(cfg, impl):
    import importlib

    reg = importlib.import_module(type(cfg).__module__.rsplit(".", 1)[0]).IMPLS
    return {n for n in reg if n != impl}


def test_other_methods_settings_do_not_change_a_methods_key():
    cfg = default_config()["blueprint"]
    mvr_key = stage_key("blueprint", "mvr", stage_view(cfg, "mvr"), {})
    changed = dataclasses.replace(
        cfg, blunf=dataclasses.replace(cfg.blunf, steps=cfg.blunf.steps + 1)
    )
    assert stage_key("blueprint", "mvr", stage_view(changed, "mvr"), {}) == mvr_key
    assert stage_key("blueprint", "blunf", stage_view(changed, "blunf"), {}) != stage_key(
        "blueprint", "blunf", stage_view(cfg, "blunf"), {}
    )


@pytest.mark.parametrize(
    "name", ["default.yaml", "fast.yaml", "phone.yaml", "edit.yaml", "edit-fast.yaml"]
)
def test_shipped_configs_load(name):
    # make demo and the README use these: each is valid, and says something
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "configs" / name
    assert path.is_file()
    cfg = load_config(path)
    if name == "edit.yaml":
        assert cfg["nerf"].train.edge_batch == 0.5
        assert default_config()["nerf"].train.edge_batch == 0.0
        assert cfg["nerf"].train.max_steps == 1000 and cfg["nerf"].train.time_budget == 0
    if name == "edit-fast.yaml":
        assert cfg["edit"].render.path == "surface"
        assert default_config()["edit"].render.path == "volume"
        assert cfg["nerf"].train.max_steps == 200


@pytest.mark.parametrize(
    "sets, named",
    [
        (["run.methods=[]"], "run.methods"),
        (["run.methods=blunf,blunf"], "run.methods"),
        (["blueprint.blunf.steps=-5"], "blueprint.blunf.steps"),
        (["blueprint.blunf.encoding=fourier"], "blueprint.blunf.encoding"),
        (["blueprint.blunf.balance=even"], "blueprint.blunf.balance"),
        (["blueprint.blunf.outside=wrap"], "blueprint.blunf.outside"),
        (["nerf.field.kind=mlp"], "nerf.field.kind"),
        (["ingest.check=thorough"], "ingest.check"),
        (["blueprint.mvr.min_votes=0"], "blueprint.mvr.min_votes"),
        (["edit.render.path=raster"], "edit.render.path"),
    ],
)
def test_settings_no_stage_could_use_fail_at_load(sets, named):
    """Checked where the config is built, not after ingest, fusion and training."""
    with pytest.raises(BlunfError, match=named.replace(".", r"\.")):
        load_config(None, sets)


def test_no_methods_fails_before_the_run_folder_is_made(tmp_path, capsys):
    from pipeline.cli import main

    out = tmp_path / "run"
    assert main(["run", str(tmp_path), "--out", str(out), "--set", "run.methods=[]"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("blunf: error: run.methods"), err
    assert not out.exists()


def test_nested_nerf_settings_and_renamed_keys(tmp_path):
    # nerf's and depth's settings are nested: --set and YAML reach them by their path; the
    # flat keys of earlier versions fail with one line naming the new key (also where an old
    # key is now the name of a section: nerf.field was a string)
    cfg = load_config(None, ["depth.stereo.planes=32", "nerf.train.max_steps=7"])
    assert cfg["depth"].stereo.planes == 32 and cfg["nerf"].train.max_steps == 7
    assert cfg["depth"].stereo.views == default_config()["depth"].stereo.views
    assert cfg.to_dict()["depth"]["stereo"]["planes"] == 32
    p = tmp_path / "nested.yaml"
    p.write_text("depth:\n  stereo:\n    planes: 32\nnerf:\n  field:\n    kind: pe\n")
    cfg = load_config(p)
    assert cfg["depth"].stereo.planes == 32 and cfg["nerf"].field.kind == "pe"
    poses = load_config(None, ["poses.matching.kind=sequential", "poses.ba.global_growth=1.2"])
    assert poses["poses"].matching.kind == "sequential" and poses["poses"].ba.global_growth == 1.2
    with pytest.raises(BlunfError, match=r"poses.matching.kind: 'vocab' is not one of"):
        load_config(None, ["poses.matching.kind=vocab"])
    # the cache key sees a nested value, in both of the depth stage's implementations
    for impl in ("stereo", "field"):
        a = stage_view(default_config()["depth"], impl)
        assert stage_view(cfg["depth"], impl) != a and a["stereo"]["planes"] == 64
    assert stage_view(cfg["nerf"], "grid") != stage_view(default_config()["nerf"], "grid")
    for old, new in [
        ("nerf.max_steps=10", "nerf.train.max_steps"),
        ("nerf.field=pe", "nerf.field.kind"),
        ("nerf.occ_res=64", "nerf.occupancy.res"),
        ("poses.matching=sequential", "poses.matching.kind"),
        ("poses.sequential_overlap=5", "poses.matching.overlap"),
        ("poses.exhaustive_max_images=5", "poses.matching.exhaustive_max_images"),
        ("poses.ba_global_growth=1.2", "poses.ba.global_growth"),
        ("poses.ba_local_max_refinements=1", "poses.ba.local_max_refinements"),
    ]:
        key = old.partition("=")[0]
        with pytest.raises(BlunfError, match=rf"{key}: renamed to {new}$") as e:
            load_config(None, [old])
        assert "\n" not in str(e.value)
    # the photos-only depth's settings moved from the nerf stage to the depth stage
    for old, new in [
        ("nerf.stereo.planes=32", "depth.stereo.planes"),
        ("nerf.stereo_planes=32", "depth.stereo.planes"),
        ("nerf.stereo=false", "depth.stereo"),
        ("nerf.stereo.field_fill=false", "depth.field.fill"),
        ("nerf.stereo.field_fill_below=0.3", "depth.field.below"),
        ("nerf.stereo.fill_samples_across=128", "depth.field.sampling.samples_across"),
        ("nerf.stereo.check=0", "depth.field.check"),
        ("nerf.depth_check.enabled=true", "depth.check.enabled"),
        ("nerf.depth_check_tol=0.1", "depth.check.tol"),
        ("nerf.depth_render_scale=1", "depth.field.render_scale"),
    ]:
        key = old.partition("=")[0]
        with pytest.raises(BlunfError, match=rf"{key}: moved to {new}$") as e:
            load_config(None, [old])
        assert "\n" not in str(e.value)
    p.write_text("nerf:\n  stereo:\n    planes: 32\n")
    with pytest.raises(BlunfError, match=r"nested.yaml: nerf.stereo.planes: moved to depth.st"):
        load_config(p)
    with pytest.raises(BlunfError, match="unknown key depth.stereo.plane "):
        load_config(None, ["depth.stereo.plane=3"])


def test_default_configs_stop_on_steps_not_seconds():
    # same photos, same plan: every field a config trains (the nerf stage's, the depth
    # stage's field fill) stops on a step count; a time budget is an opt-in guard
    for path in [None, *sorted((ROOT / "configs").glob("*.yaml"))]:
        cfg = load_config(path)
        for train in (cfg["nerf"].train, cfg["depth"].field.train):
            assert train.max_steps > 0 and train.time_budget == 0, (path, train)
        assert cfg["poses"].deterministic and cfg["poses"].seed == 0, path
    with pytest.raises(BlunfError, match=r"never stops"):
        load_config(None, ["depth.field.train.max_steps=0", "depth.field.train.eval_every=0"])
    with pytest.raises(BlunfError, match=r"time_budget"):
        load_config(None, ["nerf.train.time_budget=.nan"])


def test_nested_semantics_settings_and_renamed_keys(tmp_path):
    # the semantics stage's settings are nested (planes, walls, objects, floor_fill,
    # point_walls); the flat keys fail with one line naming the new key, also where the old
    # key is now a section's name (semantics.point_walls was a bool)
    cfg = load_config(None, ["semantics.walls.behind=0.4", "semantics.point_walls.enabled=true"])
    assert cfg["semantics"].walls.behind == 0.4 and cfg["semantics"].point_walls.enabled
    p = tmp_path / "nested.yaml"
    p.write_text("semantics:\n  floor_fill: {hull: true}\n  planes: {max_tilt_deg: 25}\n")
    cfg = load_config(p)
    assert cfg["semantics"].floor_fill.hull and cfg["semantics"].planes.max_tilt_deg == 25
    assert cfg["semantics"].floor_fill.enabled  # the rest of the section keeps its defaults
    for old, new in [
        ("semantics.wall_behind=0.4", "semantics.walls.behind"),
        ("semantics.point_walls=true", "semantics.point_walls.enabled"),
        ("semantics.floor_fill=false", "semantics.floor_fill.enabled"),
        ("semantics.floor_fill_hull=true", "semantics.floor_fill.hull"),
        ("semantics.object_max_gap=0.2", "semantics.objects.max_gap"),
        ("semantics.plane_dist=0.02", "semantics.planes.plane_dist"),
    ]:
        key = old.partition("=")[0]
        with pytest.raises(BlunfError, match=rf"{key}: renamed to {new}$") as e:
            load_config(None, [old])
        assert "\n" not in str(e.value)
    with pytest.raises(BlunfError, match="semantics.impl"):
        load_config(None, ["semantics.impl=magic"])


def test_the_plan_cell_is_set_once_and_passed_to_the_depth_sweep(tmp_path):
    # project.cell is the plan's cell; the depth sweep's finest useful resolution follows it
    assert default_config()["depth"].stereo.cell == default_config()["project"].cell
    cfg = load_config(None, ["project.cell=0.05"])
    assert cfg["project"].cell == 0.05 and cfg["depth"].stereo.cell == 0.05
    for where, load in [
        ("--set", lambda: load_config(None, ["depth.stereo.cell=0.05"])),
        ("cell.yaml", lambda: load_config(_yaml(tmp_path, "depth:\n  stereo:\n    cell: 0.05\n"))),
    ]:
        with pytest.raises(BlunfError, match=r"depth.stereo.cell: set from project.cell") as e:
            load()
        assert where in str(e.value) and "\n" not in str(e.value)


def _yaml(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cell.yaml"
    p.write_text(text)
    return p

"""The studio's saves survive reruns: they live in RUN/studio/, which no run publishes or
removes, and a real folder of an older layout where a run publishes a link is moved aside
into RUN/studio/, never deleted."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline.publish import STUDIO, Publication
from pipeline.studio.state import SPEC_NAME, Session
from tests.runs import VOXEL, run_ok


def _publish(out: Path, files: dict[str, str]) -> None:
    """One run's publication of `files` (name -> text)."""
    pub = Publication(out)
    for name, text in files.items():
        src = pub.dir.parent / f"src-{name.replace('/', '_')}"
        src.write_text(text)
        pub.add(src, name)
        src.unlink()
    pub.switch()


def test_no_run_removes_the_studios_files(tmp_path) -> None:
    out = tmp_path / "run"
    _publish(out, {"report.json": "{}", "edits/a.png": "1"})  # a run with edits
    save = out / STUDIO / SPEC_NAME
    save.parent.mkdir()
    save.write_text("edits: []\n")
    (out / STUDIO / "textures").mkdir()
    (out / STUDIO / "textures" / "t.png").write_text("px")
    _publish(out, {"report.json": "{}"})  # a rerun without edits
    _publish(out, {"report.json": "{}", "edits/b.png": "2"})  # and one with other edits
    assert save.read_text() == "edits: []\n"
    assert (out / STUDIO / "textures" / "t.png").read_text() == "px"
    assert (out / "edits").is_symlink() and (out / "edits" / "b.png").read_text() == "2"
    with pytest.raises(ValueError, match="studio"):
        Publication(out).add(save, f"{STUDIO}/x.yaml")  # a run never writes there


@pytest.mark.parametrize("rerun_has_edits", [False, True])
def test_an_older_layouts_edits_folder_is_moved_aside(tmp_path, rerun_has_edits) -> None:
    # an older blunf's studio saved into a real RUN/edits/ folder: a rerun (with or without
    # edits of its own) must not delete it; it moves into RUN/studio/, where the studio loads
    out = tmp_path / "run"
    _publish(out, {"report.json": "{}"})
    (out / "edits" / "textures").mkdir(parents=True)
    (out / "edits" / SPEC_NAME).write_text("saved\n")
    (out / "edits" / "textures" / "t.png").write_text("px")
    _publish(out, {"report.json": "{}", **({"edits/c.png": "3"} if rerun_has_edits else {})})
    assert (out / STUDIO / SPEC_NAME).read_text() == "saved\n"
    assert (out / STUDIO / "textures" / "t.png").read_text() == "px"
    assert rerun_has_edits == (out / "edits").is_symlink()
    # a second older folder, when RUN/studio exists already, goes inside it
    (out / "edits").unlink(missing_ok=True)
    (out / "edits").mkdir()
    (out / "edits" / SPEC_NAME).write_text("second\n")
    _publish(out, {"report.json": "{}"})
    older = list((out / STUDIO).glob("older-edits-*"))
    assert len(older) == 1 and (older[0] / SPEC_NAME).read_text() == "second\n"
    assert (out / STUDIO / SPEC_NAME).read_text() == "saved\n"


def test_save_rerun_with_other_settings_load(studio_run, tmp_path) -> None:
    """The issue's case: save in the studio, rerun with other settings, find the save."""
    cap, shared = studio_run  # tests/studio/conftest.py
    out = tmp_path / "run"
    shutil.copytree(shared, out, symlinks=True)  # the run and its caches, not the shared one
    s = Session(out)
    s.select_class("sofa")
    s.apply("recolor", color=(40, 90, 200), strength=0.8)
    s.select_class("table")
    s.apply("retexture", texture="tiles.png")
    path = s.save([0])
    text = path.read_text()
    before = json.loads((out / "report.json").read_text())["config"]["blueprint"]["blunf"]
    run_ok(cap, out, "--set", f"fusion.voxel={VOXEL}", "--set", "blueprint.blunf.steps=40")
    after = json.loads((out / "report.json").read_text())["config"]["blueprint"]["blunf"]
    assert before["steps"] != after["steps"] == 40  # the rerun did run, with other settings
    assert path.read_text() == text
    assert (out / STUDIO / "textures" / "tiles.png").is_file()
    s2 = Session(out)
    assert s2.load() == 2 and s2.edits == s.edits

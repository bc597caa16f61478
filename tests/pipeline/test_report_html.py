"""report.html after a tiny run (self-contained, every stage, the metrics, pictures that
decode) and the run's progress output: ~10 % lines off a terminal, nothing with --quiet."""

from __future__ import annotations

import base64
import io
import json
import logging
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline.report_html import _flatten, report_html, warnings
from stages.common import progress as P
from tests.runs import VOXEL, run_ok, small_room


class _Page(HTMLParser):
    """Every src / href, the images by section, the stage rows and the metric rows."""

    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []
        self.tags: list[str] = []
        self.section = ""
        self.images: dict[str, list[str]] = {}
        self.rows: list[list[str]] = []
        self._h2 = self._row = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        self.links += [v for k, v in attrs if k in ("src", "href") and v is not None]
        if tag == "h2":
            self._h2, self.section = True, ""
        if tag == "img":
            self.images.setdefault(self.section, []).append(a.get("src") or "")
        if tag == "tr" and a.get("class") in ("stage", "metric", "known"):
            self._row = True
            self.rows.append([a["class"]])

    def handle_endtag(self, tag):
        if tag == "h2":
            self._h2 = False
        if tag == "tr":
            self._row = False

    def handle_data(self, data):
        if self._h2:
            self.section += data
        if self._row and data.strip():
            self.rows[-1].append(data.strip())


def parse(text: str) -> _Page:
    p = _Page()
    p.feed(text)
    return p


def decode(src: str) -> Image.Image:
    head, _, b64 = src.partition(",")
    assert head == "data:image/png;base64", head[:40]
    im = Image.open(io.BytesIO(base64.b64decode(b64)))
    im.load()
    return im


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One tiny run with --quiet, then one that reruns the blueprint and what follows it
    without; the progress lines each logged (every step counts: MIN_SECONDS 0)."""
    base = tmp_path_factory.mktemp("report")
    cap = small_room(base / "room")
    out = base / "run"
    lines: dict[str, list[str]] = {}
    handler = _Keep()
    logger = logging.getLogger(P.log.name)
    old_min, old_level = P.MIN_SECONDS, logger.level
    P.MIN_SECONDS = 0.0
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        fusion = ("--set", f"fusion.voxel={VOXEL}")
        run_ok(cap, out, *fusion, "--quiet")
        lines["quiet"], handler.lines = handler.lines, []
        # another BluNF step count: blueprint, layout, evaluate and export rerun (not a tty
        # here: pytest captures stderr), the rest is cached
        report = run_ok(cap, out, *fusion, "--set", "blueprint.blunf.steps=50")
        lines["log"] = handler.lines
    finally:
        P.MIN_SECONDS = old_min
        logger.removeHandler(handler)
        logger.setLevel(old_level)
        P.configure("auto")
    return out, report, lines


class _Keep(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def test_progress_lines_every_tenth_and_none_when_quiet(runs):
    _, _, lines = runs
    assert lines["quiet"] == []
    blunf = [s for s in lines["log"] if s.startswith("blunf:")]
    # 50 steps: one line at each 10 %, with the count and an ETA
    assert len(blunf) == 10, lines["log"]
    assert "(5/50 step)" in blunf[0] and "ETA" in blunf[0] and blunf[-1].endswith("done")


def test_report_html_is_self_contained_and_complete(runs):
    out, report, _ = runs
    page = out / "report.html"
    assert page.is_symlink() and page.resolve().parent == (out / ".current").resolve()
    text = page.read_text()
    p = parse(text)
    assert p.links and all(u.startswith("data:") for u in p.links), [u[:60] for u in p.links]
    assert "script" not in p.tags and "link" not in p.tags
    # a row per stage record, in order, with its status
    stages = [r[1:4] for r in p.rows if r[0] == "stage"]
    assert stages == [[s["name"], s["impl"], s["status"]] for s in report["stages"]]
    assert {s[2] for s in stages} >= {"cached", "ran", "skipped"}
    # every metric, by its dotted name
    metrics = {r[1]: r[2] for r in p.rows if r[0] == "metric" and len(r) == 3}
    names = [k for k, _ in _flatten(report["metrics"])]
    assert "blueprint.blunf.fwiou" in names and set(names) <= set(metrics)
    assert float(metrics["blueprint.blunf.fwiou"]) == pytest.approx(
        report["metrics"]["blueprint"]["blunf"]["fwiou"], rel=1e-3
    )
    # the plan is blueprint.png itself; the cameras are drawn over the plain class picture
    from stages.common.blueprint import Blueprint
    from stages.common.plan_picture import plan_picture

    plan = decode(p.images["Plan"][0])
    png = Image.open(out / "blueprint.png")
    assert plan.size == png.size and np.array_equal(np.asarray(plan), np.asarray(png))
    cams = decode(p.images["Cameras seen from above"][0])
    bare, _ = plan_picture(Blueprint.load(out / "blueprint.npz"))
    assert cams.size == bare.size
    assert not np.array_equal(np.asarray(cams.convert("RGB")), np.asarray(bare.convert("RGB")))
    assert len(p.images["Input photos"]) == 8  # every view of the small room
    assert p.images["Architectural drawing"][0].startswith("data:image/svg+xml;base64,")
    assert "Edits" not in p.images and "<h2>Edits</h2>" not in text  # no edits: no section
    # what the plan knows: the blueprint's shares of seen / inferred / unknown / outside cells
    known = {r[1]: r[2] for r in p.rows if r[0] == "known"}
    shares = Blueprint.load(out / "blueprint.npz").shares()
    assert set(known) == {"seen", "inferred", "unknown", "outside"}, p.rows
    for name, v in known.items():
        assert float(v.rstrip(" %")) == pytest.approx(shares[f"{name}_pct"], abs=0.051)
    assert "m inferred" in text  # the walls' note


def test_missing_or_broken_pictures_leave_the_rest(runs, tmp_path):
    out, report, _ = runs
    folder = tmp_path / "outputs"
    shutil.copytree(out / ".current", folder)
    (folder / "blueprint.png").write_bytes(b"not a png")
    (folder / "plan.svg").unlink()
    t = json.loads((folder / "transforms.json").read_text())
    for f in t["frames"]:
        f["file_path"] = str(tmp_path / "gone" / Path(f["file_path"]).name)
    (folder / "transforms.json").write_text(json.dumps(t))
    p = parse(text := report_html(folder, report))
    assert "Not available: not a PNG file" in text
    assert "Plan" not in p.images and "Architectural drawing" not in text
    assert "0 of 8 photos; 8 unreadable" in text
    assert len([r for r in p.rows if r[0] == "stage"]) == len(report["stages"])
    # the plan picture itself gone: the cameras need only blueprint.npz
    (folder / "blueprint.png").unlink()
    p = parse(report_html(folder, report))
    assert "No blueprint.png" in report_html(folder, report)
    decode(p.images["Cameras seen from above"][0])


def test_stage_warnings_head_the_page(runs, tmp_path):
    out, report, _ = runs
    folder = tmp_path / "outputs"
    shutil.copytree(out / ".current", folder)
    assert "class=warn" not in report_html(folder, report)  # a clean run: no box
    warned = json.loads(json.dumps(report))
    poses = next(s for s in warned["stages"] if s["name"] == "poses")
    poses.setdefault("facts", {})["warnings"] = [
        "the model contradicts 87 of its 3592 matched view pairs <0187-0438>",
        "12 of 480 photos are left out",
    ]
    assert warnings(warned) == [("poses", w) for w in poses["facts"]["warnings"]]
    text = report_html(folder, warned)
    box = text.index("<ul class=warn>")
    assert box < text.index("<h2>")  # above every section
    assert (
        "poses: the model contradicts 87 of its 3592 matched view pairs &lt;0187-0438&gt;" in text
    )
    assert "poses: 12 of 480 photos are left out" in text


def test_edits_section_shows_the_renders(runs, tmp_path):
    out, report, _ = runs
    folder = tmp_path / "outputs"
    shutil.copytree(out / ".current", folder)
    (folder / "edits").mkdir()
    pair = np.zeros((12, 25, 3), np.uint8)
    pair[:, 13:] = 200  # before | after
    Image.fromarray(pair).save(folder / "edits" / "view_000.png")
    shutil.copyfile(out / "blueprint.png", folder / "edits" / "blueprint_edited.png")
    p = parse(report_html(folder, report))
    imgs = p.images["Edits"]
    assert len(imgs) == 2  # the view's render and the edited plan
    assert np.array_equal(np.asarray(decode(imgs[0])), pair)


@pytest.mark.parametrize("quiet", [False, True])
def test_batch_workers_log_lines_never_bars(quiet, tmp_path):
    """A batch task sets its process to log lines into the capture's log (no bars, whatever
    the worker's stderr is), or to nothing with --quiet."""
    from pipeline.batch import BatchOptions, _jobs, run_capture

    cap = tmp_path / "cap"
    cap.mkdir()  # no images: the task fails at once, after setting the mode
    (job,) = _jobs([cap], BatchOptions(out=tmp_path / "out", quiet=quiet))
    P.configure("bar")
    try:
        res = run_capture(job)
        assert not res.ok and res.error
        assert P.mode() == ("off" if quiet else "log")
    finally:
        P.configure("auto")

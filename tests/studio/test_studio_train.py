"""The studio on a run without a NeRF: "Train the NeRF" runs the pipeline on the run (its
cache: only the NeRF and what follows it run), the page's progress names the stage, and the
session renders afterwards; then retexture on that field: the render changes inside the
object, and a second upload under the same name is the texture rendered (slow: a NeRF of 60
steps: ~45 CPU-s, 2-3 min wall on a loaded machine)."""

from __future__ import annotations

import io
import json
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import viser
from PIL import Image

from pipeline.studio.app import Studio
from pipeline.studio.state import SPEC_NAME, Session
from pipeline.studio.train import Trainer
from pipeline.studio.view import FAR, background_depth
from tests.runs import VOXEL, run_ok, small_room

pytestmark = pytest.mark.slow

SETS = ["nerf.train.max_steps=60", "edit.gif.frames=2"]  # a small NeRF, a short GIF


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path, Session, list[str]]:
    """A run without a NeRF opened in the studio (a real viser server, no browser), an edit
    applied, then the page's "Train the NeRF"; returns the lines the page showed."""
    base = tmp_path_factory.mktemp("studio-train")
    cap = small_room(base / "room")
    run_ok(cap, base / "run", "--set", f"fusion.voxel={VOXEL}")
    s = Session(base / "run")
    assert not s.scene.has_field
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    st = Studio(s, server, train_sets=SETS)
    try:
        st.panel.cls.value = "sofa"
        st.panel.do(st.panel._select_class)
        assert st.scene.highlight is not None
        s.apply("recolor", color=(40, 90, 200), strength=0.8)
        st.panel.do(st.panel._train)  # the button
        assert st.trainer.running, st.panel.message.content
        assert (base / "run" / "studio" / SPEC_NAME).is_file()
        lines = []
        while st.trainer.running:
            lines.append(st.panel.train_info.content)
            time.sleep(0.5)
        assert st.trainer.wait(600) == "done", st.trainer.error
        t0 = time.time()
        while st.panel.train_button.visible and time.time() - t0 < 10:  # the page's last update
            time.sleep(0.2)
        lines.append(st.panel.train_info.content)
        # the page: the button and the note gone, the renders take over from the points
        assert not st.panel.train_button.visible and not st.panel.no_field.visible
        assert not st.scene.points.visible and "trained" in st.panel.message.content
        # the run read again: the selection cleared in the session and on the page
        assert s.selection is None and st.scene.highlight is None
    finally:
        st.running = False
        server.stop()
    return cap, base / "run", s, lines


def test_train_from_the_studio(trained) -> None:
    cap, run, s, lines = trained
    assert s.scene.has_field and s.edits  # the field loaded, the edits kept
    report = json.loads((run / "report.json").read_text())
    status = {st["name"]: st["status"] for st in report["stages"]}
    # through the run's cache: the stages before the NeRF found there, the NeRF trained
    assert status["nerf"] == "ran" and status["edit"] == "ran"
    assert status["fusion"] == "cached" and status["ingest"] == "cached"
    assert report["config"]["nerf"]["train"]["edge_batch"] == 0.5  # configs/edit-fast.yaml's
    assert any("nerf" in ln and "running" in ln for ln in lines), lines  # the page's line
    assert lines[-1].startswith("NeRF trained")
    assert (run / "studio" / SPEC_NAME).is_file()  # the run left the studio's save alone
    # a second training is refused: the run has its NeRF
    with pytest.raises(Exception, match="has a NeRF already"):
        Trainer(s).start()


def _png(rgb) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((8, 8, 3), rgb, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_retexture_changes_the_render(trained) -> None:
    cap, run, s, _ = trained
    while s.edits:
        s.undo()
    s.select_class("sofa")
    # the input view that sees most of the sofa
    best = max(range(len(s.scene.cap.frames)), key=lambda v: _footprint(s, *s.scene.view(v)))
    pose, intr = s.scene.view(best)
    before = s.scene.render(pose, intr, fast=True)
    assert before.depth is not None and np.isfinite(before.depth).mean() > 0.9
    bg = background_depth(before.depth)
    assert bg is not None and np.all(bg[~np.isfinite(before.depth)] == FAR)

    def with_texture(content: bytes) -> np.ndarray:
        name = s.add_texture("wood.png", content)
        s.apply("retexture", texture=name, strength=1.0)
        rgb = s.scene.render(pose, intr, s.parsed(), fast=True).rgb.astype(int)
        s.undo()
        return rgb

    red = with_texture(_png((230, 30, 30)))
    green = with_texture(_png((30, 230, 30)))  # the same name, another picture
    b = before.rgb.astype(int)
    changed = np.abs(red - b).max(axis=2) > 12
    assert changed.sum() > 30, changed.sum()
    # the second upload is the one rendered (not the first, kept by the edits' cache)
    assert (green[changed][:, 1] > red[changed][:, 1]).mean() > 0.9


def _footprint(s: Session, pose, intr) -> int:
    """The selected cells (30 cm up) that view (pose, intr) sees in its image."""
    assert s.selection is not None
    g = s.scene.bp.grid
    rows, cols = np.nonzero(s.selection.cells)
    x = g.origin[0] + (cols + 0.5) * g.cell
    y = g.origin[1] + (g.shape[0] - rows - 0.5) * g.cell
    pts = np.stack([x, y, np.full_like(x, 0.3), np.ones_like(x)], 1)
    xc = (np.linalg.inv(pose) @ pts.T).T
    u, v = intr.fx * xc[:, 0] / xc[:, 2] + intr.cx, intr.fy * xc[:, 1] / xc[:, 2] + intr.cy
    ok = (xc[:, 2] > 0) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    return int(ok.sum())

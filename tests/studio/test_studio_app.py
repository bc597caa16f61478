"""The studio's page without a browser: a real viser server and the Studio on a run without a
NeRF; the pointer events the page would send are given to its handlers as viser shapes them
(a click's ray, a drag's grab point and pointer point), and the session and panel checked."""

from __future__ import annotations

import asyncio
import json
import socket
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import viser

from pipeline.studio.app import Studio
from pipeline.studio.plan_view import plan_picture, plan_rgba, screen_ray, top_view
from pipeline.studio.state import Session


@pytest.fixture(scope="module")
def studio(studio_run):
    cap, run = studio_run  # tests/studio/conftest.py
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    st = Studio(Session(run), server)
    yield cap, st
    st.running = False
    server.stop()


def _centre(cap: Path, name: str) -> tuple[float, float]:
    inst = json.loads((cap / "gt" / "instances.json").read_text())
    b = next(v["bbox"] for v in inst.values() if v["name"] == name)
    return (b[0] + b[3]) / 2, (b[1] + b[4]) / 2


def test_plan_on_the_floor_is_north_up(studio) -> None:
    # viser lays an image node's row 0 towards the node's -y (image axes as a camera's, y
    # down; its client turns the textured plane by pi about x): the node's picture must then
    # run south to north, the plan's own rows reversed (row 0 of the plan is its north)
    _, st = studio
    assert np.array_equal(st.scene.plan.image, plan_rgba(st.session.scene.bp)[::-1])


def test_page_without_a_nerf_offers_training(studio) -> None:
    _, st = studio
    assert st.panel.train_button.visible and st.panel.no_field.visible
    hint = st.panel.no_field.content
    assert "blunf run" in hint and "--config configs/edit-fast.yaml" in hint
    st.panel.do(st.panel._train)  # no edit yet: a message, nothing started
    assert "apply an edit first" in st.panel.message.content and st.trainer.state == "idle"


def test_plan_view_click_and_drag(studio) -> None:
    cap, st = studio
    s = st.session
    g = s.scene.bp.grid
    # a click in the plan view on the chair: selected, shown in the panel's picture
    aspect, fov = 16 / 9, np.deg2rad(40.0)
    pos, wxyz = top_view(g, aspect, fov)
    x, y = _centre(cap, "chair_2")
    from pipeline.render import viewer_camera

    pose, intr = viewer_camera(pos, wxyz, fov, aspect, 720)
    xc = np.linalg.inv(pose) @ np.array([x, y, 0.0, 1.0])
    u, v = intr.fx * xc[0] / xc[2] + intr.cx, intr.fy * xc[1] / xc[2] + intr.cy
    o, d = screen_ray(pos, wxyz, fov, aspect, ((u + 0.5) / intr.width, (v + 0.5) / intr.height))
    st._click(SimpleNamespace(ray_origin=tuple(o), ray_direction=tuple(d)))
    assert s.selection is not None and "chair" in st.panel.sel_info.content
    assert np.array_equal(
        st.panel.picture.image, plan_picture(s.scene.bp, s.selection.cells, scale=2)
    )
    # sketch on: a drag on the plan draws the stroke (the plan's image node takes drags)
    st.panel.sketching.value = True
    st._sketch_mode(st.panel.sketching.value)
    assert st.scene.plan._impl.drag_cb, "the plan takes no drag"
    a, b = np.array([x, y]), np.array([x + 0.5, y - 0.4])
    cam = SimpleNamespace(camera=SimpleNamespace(position=pos))

    def ev(phase: str, p) -> SimpleNamespace:
        pointer = pos + 0.5 * (np.array([p[0], p[1], 0.0]) - pos)
        return SimpleNamespace(
            phase=phase, client=cam, start_position=(a[0], a[1], 0.002), end_position=pointer
        )

    async def drag() -> None:
        await st._drag(ev("start", a))
        for t in np.linspace(0, 1, 12)[1:-1]:
            await st._drag(ev("update", a + t * (b - a)))
        await st._drag(ev("end", b))

    asyncio.run(drag())
    assert len(s.stroke) > 3 and np.allclose(s.stroke[-1], b, atol=1e-3)
    assert st.scene.stroke_line is not None and st.panel.stroke_info.content.startswith("Stroke:")
    st.panel.op.value = "sketch"
    st.panel.do(st.panel._apply)
    assert "Applied sketch" in st.panel.message.content and s.edits[-1]["op"] == "sketch"
    assert s.stroke == [] and st.scene.stroke_line is None
    st.panel.sketching.value = False
    st._sketch_mode(st.panel.sketching.value)
    assert not st.scene.plan._impl.drag_cb  # drags on the plan orbit the camera again


def test_forged_dropdowns_are_refused(studio) -> None:
    # viser lets a client set a dropdown's value and even its options: the panel checks the
    # values against the server's own offer, and nothing is written
    from tests.test_bad_input import snapshot

    _, st = studio
    run = st.session.files.run
    st.panel.cls.value = "sofa"
    st.panel.do(st.panel._select_class)
    forged = "../../../pipeline/cli.py"
    st.panel.texture._impl.props.options = (
        *st.panel.texture.options,
        forged,
    )  # as a client's update
    st.panel.texture._impl.value = forged
    st.panel.op._impl.value = "retexture"
    n = len(st.session.edits)
    before = snapshot(run.parent)
    st.panel.do(st.panel._apply)
    assert "Not applied" in st.panel.message.content and "texture" in st.panel.message.content
    assert snapshot(run.parent) == before and len(st.session.edits) == n
    st.panel.view_pick._impl.value = "999: nowhere"
    st.panel.do(lambda: st.panel._go(SimpleNamespace(client=None)))
    assert "Not applied" in st.panel.message.content and "input view" in st.panel.message.content
    st.panel.full_path._impl.value = "../x"
    st.panel.do(st.panel._full_path)
    assert st.panel.full_path.value == "fast" and "Not applied" in st.panel.message.content

"""`blunf studio RUN`: the run in a web page (viser): click on the plan, edit, see the render.

The 3-D view shows the plan on the floor (z = 0), the fused surface as points and the input
cameras as frusta (a click on one jumps there). A click on the floor selects the plan's
component under it (`Session.click_ray`). The page's parts have a module each: the 3-D scene
(`pipeline.studio.scene`), the tabs (`pipeline.studio.tabs`, each tab's camera and render in
`pipeline.studio.view`) and the panel (`pipeline.studio.panel`), which shows the plan
as a picture with the selection, applies edits, undo / redo, save / load, and trains the
NeRF of a run without one. "Plan view (2D)" puts the tab's camera straight above the plan,
where the canvas shows it as a 2-D picture to click on (`pipeline.studio.plan_view` says
why there rather than on the panel's picture); with "Sketch" on, a drag on the plan draws
the sketch's stroke. Each tab's background is the NeRF's render from that tab's camera with
the edits applied (`pipeline.studio.view`): a quarter-resolution preview while the camera
moves, the full view once it rests; both through the fast path (the fused mesh ray-cast,
the field asked at the hits: `stages/edit/surface.py`) unless "Full view" says volume.
Saved views are volume rendered, as `blunf run` renders them. Every tab shares one session
(the panel and the scene are the server's), each has its own camera and render.
"""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Sequence
from pathlib import Path

import viser

from pipeline.studio.guard import ANY, Guard, guarded
from pipeline.studio.panel import Panel
from pipeline.studio.plan_view import StrokeDrag
from pipeline.studio.scene import StudioScene
from pipeline.studio.state import Session
from pipeline.studio.tabs import Tabs
from pipeline.studio.train import Trainer
from pipeline.studio.values import floor_point

log = logging.getLogger(__name__)


class Studio:
    """One run served: the session, the scene, the tabs and the panel, and the pointer's
    events on the canvas (a click selects or adds a stroke point, a drag draws)."""

    def __init__(self, session: Session, server: viser.ViserServer, train_sets: Sequence[str] = ()):
        self.session, self.server = session, server
        self.guard: Guard | None = None  # who may connect (set by `launch`)
        self.running = True  # False stops the tabs' render threads and the training's watch
        self.trainer = Trainer(session, train_sets)
        self.drag = StrokeDrag(session, min_step=session.scene.bp.grid.cell / 2)
        self.tabs = Tabs(self)
        self.scene = StudioScene(session, server, self._camera_clicked)
        self.panel = Panel(
            session, server, self.scene, self.tabs, self.trainer, lambda: self.running,
            self._sketch_mode, self._field_ready,
        )  # fmt: skip
        server.on_client_connect(self.tabs.connect)
        server.on_client_disconnect(self.tabs.disconnect)
        server.scene.on_click()(self._click)

    def _camera_clicked(self, i: int, ev) -> None:
        """A click on input camera i: that tab goes to its view."""
        if ev.client is not None:
            for cv in self.tabs.of(ev):
                cv.jump(i)

    def _field_ready(self) -> None:
        """The run has a NeRF now (trained from the page): the renders take over (the session
        read the run again: nothing is selected)."""
        self.scene.field_ready()
        self.panel.show_selection()
        self.tabs.redraw()

    def _click(self, ev) -> None:
        """A click in the canvas: a stroke point when sketching, else the selection."""

        def go() -> None:
            if self.panel.sketching.value:
                self.session.add_stroke_point(*floor_point(ev.ray_origin, ev.ray_direction))
                self.panel.stroke_changed()
                return
            self.session.click_ray(ev.ray_origin, ev.ray_direction)
            self.panel.show_selection()
            self.panel.say("Selected; choose an operation and Apply.")

        self.panel.do(go)

    def _sketch_mode(self, on: bool) -> None:
        """Sketch on: a left drag on the plan draws (the camera orbits on drags elsewhere);
        off: drags on the plan orbit the camera again."""
        if on:
            self.scene.plan.on_drag("left")(self._drag)
            self.panel.say("Sketch: drag on the plan to draw a stroke, then Apply with sketch.")
        else:
            self.scene.plan.remove_drag_callback("all")

    async def _drag(self, ev) -> None:
        """A drag on the plan (async: its phases arrive in order) -> the stroke."""

        def go() -> None:
            cam = ev.client.camera.position
            if ev.phase == "start":
                self.drag.start(ev.start_position)
                self.drag.move(cam, ev.end_position)
            elif ev.phase == "update":
                self.drag.move(cam, ev.end_position)
            else:
                self.drag.end(cam, ev.end_position)
            self.panel.stroke_changed(picture=ev.phase == "end")

        self.panel.do(go)


def launch(run: Path, host: str = "127.0.0.1", port: int = 8080) -> tuple[Studio, str]:
    """Start the studio's server on `run`; returns the studio and the URL to open (with this
    launch's token: `pipeline.studio.guard` refuses pages and sockets without it)."""
    session = Session(Path(run))  # a folder that is not a run fails here, with one line
    guard = Guard(host)
    with guarded(guard):  # viser's server starts (and binds) inside ViserServer()
        server = viser.ViserServer(host=host, port=port, verbose=False)
    studio = Studio(session, server)
    studio.guard = guard
    name = socket.gethostname() if host in ANY else host
    name = f"[{name}]" if ":" in name else name
    return studio, f"http://{name}:{server.get_port()}/?token={guard.token}"


def serve(run: Path, host: str = "127.0.0.1", port: int = 8080) -> int:
    """Serve the studio until interrupted."""
    studio, url = launch(run, host, port)
    print(f"blunf studio: {url}  ({run})", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        studio.running = False
        studio.server.stop()
    return 0

"""`blunf studio RUN`: the run in a web page (viser): click on the plan, edit, see the render.

The 3-D view shows the plan on the floor (z = 0), the fused surface as points and the input
cameras as frusta (a click on one jumps there). A click on the floor selects the plan's
component under it (`Session.click_ray`); the panel (`pipeline.studio.panel`) shows the plan
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

import numpy as np
import viser

from pipeline.render import pose_wxyz
from pipeline.studio.guard import ANY, Guard, guarded
from pipeline.studio.panel import Panel
from pipeline.studio.plan_view import HIGHLIGHT, STROKE, StrokeDrag, plan_extent, plan_rgba
from pipeline.studio.state import Session
from pipeline.studio.train import Trainer
from pipeline.studio.view import ClientView

log = logging.getLogger(__name__)

MAX_POINTS = 60000  # points of the fused surface sent to the page


class Studio(Panel):
    def __init__(self, session: Session, server: viser.ViserServer, train_sets: Sequence[str] = ()):
        self.session, self.server = session, server
        self.guard: Guard | None = None  # who may connect (set by `launch`)
        self.running = True
        self.clients: dict[int, ClientView] = {}
        self.views_seen: set[int] = set()
        self.renders = 0  # renders shown so far (the page numbers them)
        self.trainer = Trainer(session, train_sets)
        self.drag = StrokeDrag(session, min_step=session.scene.bp.grid.cell / 2)
        self._build_scene()
        self._build_gui()
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)
        server.scene.on_click()(self._click)

    # ---- scene -----------------------------------------------------------------------------
    def _floor_image(self, name: str, rgba: np.ndarray, z: float):
        """A picture of the plan's cells (row 0 north) lying on the floor at height z."""
        cx, cy, w, h = plan_extent(self.session.scene.bp.grid)
        # viser lays an image's row 0 towards the node's -y (its image axes are a camera's:
        # y down), so the rows go in south first to put the plan's north at +y
        return self.server.scene.add_image(
            name, np.ascontiguousarray(rgba[::-1]), w, h, format="png", position=(cx, cy, z)
        )

    def _build_scene(self) -> None:
        sc, sess = self.server.scene, self.session
        sc.set_up_direction("+z")
        self.plan = self._floor_image("/plan", plan_rgba(sess.scene.bp), 0.002)
        self.highlight: viser.ImageHandle | None = None
        self.stroke_line: viser.LineSegmentsHandle | None = None
        self._surface_points()
        self.frusta = []
        for i, f in enumerate(sess.scene.cap.frames):
            if f.pose is None:
                continue
            pose = np.asarray(f.pose)
            intr = f.intrinsics
            h = sc.add_camera_frustum(
                f"/cameras/{i}", float(2 * np.arctan(0.5 * intr.height / intr.fy)),
                intr.width / intr.height, scale=0.15, wxyz=pose_wxyz(pose),
                position=pose[:3, 3], color=(40, 80, 200),
            )  # fmt: skip
            h.on_click(self._jumper(i))
            self.frusta.append(h)

    def _surface_points(self) -> None:
        sess = self.session
        v, c = sess.scene.verts, sess.scene.colors
        idx = np.linspace(0, len(v) - 1, min(len(v), MAX_POINTS)).astype(int)
        col = (c[idx] * 255).astype(np.uint8) if c is not None else (180, 180, 180)
        self.points = self.server.scene.add_point_cloud(
            "/surface", v[idx].astype(np.float32), col, point_size=0.015,
            visible=not sess.scene.has_field,
        )  # fmt: skip

    def _field_ready(self) -> None:
        """The run has a NeRF now (trained from the page): the renders take over (the session
        read the run again: nothing is selected)."""
        self.points.visible = False
        self._show_selection()
        for cv in list(self.clients.values()):
            cv.moved = time.perf_counter()

    def _jumper(self, i: int):
        def jump(ev) -> None:
            if ev.client is not None and ev.client.client_id in self.clients:
                self.clients[ev.client.client_id].jump(i)

        return jump

    def _show_selection(self) -> None:
        s = self.session.selection
        if self.highlight is not None:
            self.highlight.remove()
            self.highlight = None
        self._draw_picture()
        if s is None:
            self.sel_info.content = "Nothing selected: click on the plan."
            return
        rgba = np.zeros((*s.cells.shape, 4), np.uint8)
        rgba[s.cells] = HIGHLIGHT
        hl = self._floor_image("/selection", rgba, 0.004)
        hl.visible = not self.render_only.value
        self.highlight = hl
        i = s.info
        self.sel_info.content = (
            f"**Selected:** {i['class']} (instance {', '.join(map(str, i['instance']))}), "
            f"{i['area_m2']} m², x {i['bbox'][0]}..{i['bbox'][2]}, "
            f"y {i['bbox'][1]}..{i['bbox'][3]} m"
        )

    def _draw_stroke(self) -> None:
        """The stroke being drawn, as a red line on the plan."""
        st = list(self.session.stroke)
        if self.stroke_line is not None:
            self.stroke_line.remove()
            self.stroke_line = None
        if len(st) >= 2:
            p = np.array([(x, y, 0.006) for x, y in st], np.float32)
            seg = np.stack([p[:-1], p[1:]], axis=1)  # [N-1, 2, 3]
            self.stroke_line = self.server.scene.add_line_segments(
                "/stroke", seg, STROKE[:3], thickness=0.02
            )

    def _layers(self) -> None:
        show = not self.render_only.value
        self.plan.visible = show
        if self.highlight is not None:
            self.highlight.visible = show
        self.points.visible = show and not self.session.scene.has_field
        for f in self.frusta:
            f.visible = show

    # ---- pointer ---------------------------------------------------------------------------
    def _click(self, ev) -> None:
        """A click in the canvas: a stroke point when sketching, else the selection."""

        def go() -> None:
            if self.sketching.value:
                from pipeline.studio.state import floor_point

                self.session.add_stroke_point(*floor_point(ev.ray_origin, ev.ray_direction))
                self._stroke_changed()
                return
            self.session.click_ray(ev.ray_origin, ev.ray_direction)
            self._show_selection()
            self.say("Selected; choose an operation and Apply.")

        self._do(go)

    def _sketch_mode(self) -> None:
        """Sketch on: a left drag on the plan draws (the camera orbits on drags elsewhere);
        off: drags on the plan orbit the camera again."""
        if self.sketching.value:
            self.plan.on_drag("left")(self._drag)
            self.say("Sketch: drag on the plan to draw a stroke, then Apply with sketch.")
        else:
            self.plan.remove_drag_callback("all")

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
            self._stroke_changed(picture=ev.phase == "end")

        self._do(go)

    def _to_plan_view(self, ev) -> None:
        targets = [self.clients[ev.client.client_id]] if ev.client else self.clients.values()
        for cv in targets:
            cv.plan_view()
        self.say("Plan view: click on the plan to select, or draw on it with Sketch on.")

    # ---- tabs ------------------------------------------------------------------------------
    def _connect(self, client: viser.ClientHandle) -> None:
        self.clients[client.client_id] = ClientView(self, client)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        cv = self.clients.pop(client.client_id, None)
        if cv is not None:
            cv.alive = False


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

"""`blunf studio RUN`: the run in a web page (viser): click on the plan, edit, see the render.

The 3-D view shows the plan on the floor (z = 0), the fused surface as points and the input
cameras as frusta (a click on one jumps there). A click on the floor selects the plan's
component under it (`Session.click_ray`); the panel applies edits, undo / redo, save / load.
Each tab's background is the NeRF's render from that tab's camera with the edits applied
(`pipeline.render.Scene.render`): a quarter-resolution preview while the camera moves, the
full view once it rests; both through the fast path (the fused mesh ray-cast, the field
asked at the hits: `stages/edit/surface.py`) unless "Full view" says volume. Saved
views are volume rendered, as `blunf run` renders them. Every tab shares one session (the
panel and the scene are the server's), each has its own camera and render.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np
import viser

from pipeline.render import TRAIN_HINT, pose_wxyz, scaled, viewer_camera
from pipeline.studio.state import Session
from stages.common.errors import BlunfError
from stages.common.plan_picture import class_color

log = logging.getLogger(__name__)

PREVIEW = 0.25  # preview resolution, a fraction of the full view
REST = 0.3  # seconds without camera motion before the full view is rendered
MAX_POINTS = 60000  # points of the fused surface sent to the page
OPS = ("remove", "recolor", "retexture", "sketch", "mask")
HIGHLIGHT = (255, 0, 255, 170)
FULL_PATHS = ("fast", "volume")  # how the full view is rendered (the first: the default)


class ClientView:
    """One tab: its camera, its render thread, the input view it stands at (if any)."""

    def __init__(self, studio: Studio, client: viser.ClientHandle):
        self.studio, self.client = studio, client
        self.moved = time.perf_counter()
        self.drawn: tuple | None = None  # (camera state, edits version, before, full) drawn
        self.at_view: int | None = None
        self.alive = True
        self.thread = threading.Thread(target=self._loop, daemon=True)
        client.camera.on_update(lambda _cam: self._on_move())
        self.thread.start()

    def _on_move(self) -> None:
        self.moved = time.perf_counter()

    def jump(self, n: int) -> None:
        pose, intr = self.studio.session.scene.view(n)
        cam = self.client.camera
        with self.client.atomic():
            cam.fov = float(2 * np.arctan(0.5 * intr.height / intr.fy))
            cam.position = pose[:3, 3]
            cam.wxyz = pose_wxyz(pose)
        self.at_view = n
        self.moved = time.perf_counter()  # a preview first, then the full view
        self.studio.views_seen.add(n)

    def camera(self, full: bool):
        """The pose and intrinsics to render: the input view's own pose when the camera
        stands there, the tab's camera otherwise (canvas aspect, the frames' height)."""
        cam = self.client.camera
        sess = self.studio.session
        h0 = sess.scene.cap.frames[0].intrinsics.height
        pose, intr = viewer_camera(cam.position, cam.wxyz, cam.fov, cam.aspect, h0)
        if self.at_view is not None:
            vpose, vintr = sess.scene.view(self.at_view)
            if np.abs(vpose[:3, 3] - pose[:3, 3]).max() < 1e-3 and (
                np.abs(vpose[:3, :3] - pose[:3, :3]).max() < 1e-3
            ):
                pose = vpose
                f = vintr.fy
                from stages.common.camera import Intrinsics

                w = intr.width
                intr = Intrinsics(f, f, vintr.cx + (w - vintr.width) / 2, vintr.cy, w, vintr.height)
            else:
                self.at_view = None
        return pose, intr if full else scaled(intr, PREVIEW)

    def _loop(self) -> None:
        while self.alive and self.studio.running:
            time.sleep(0.03)
            try:
                self._tick()
            except BlunfError as e:
                self.studio.say(f"**Render:** {e}")
                time.sleep(1.0)
            except Exception as e:  # a lost tab: stop this thread, the server goes on
                if not self.alive:
                    return
                log.debug("studio: render failed: %r", e)
                time.sleep(0.5)

    def _key(self) -> tuple | None:
        """What a render depends on: the camera, the edits, the before / after switch, the
        full view's path."""
        cam = self.client.camera
        try:
            state = (tuple(np.round(cam.position, 5)), tuple(np.round(cam.wxyz, 5)),
                     round(cam.fov, 5), cam.image_width, cam.image_height)  # fmt: skip
        except AssertionError:  # no camera state from the page yet
            return None
        st = self.studio
        return (state, st.session.version, st.before.value, st.full_path.value)

    def _tick(self) -> None:
        st = self.studio
        if not st.session.scene.has_field:
            return
        key = self._key()
        if key is None:
            return
        full = time.perf_counter() - self.moved >= REST
        if self.drawn is not None and self.drawn[0] == key and (self.drawn[1] or not full):
            return
        pose, intr = self.camera(full)
        fast = not full or st.full_path.value == "fast"
        scene = st.session.scene
        r = scene.render(pose, intr, st.session.parsed(), before=key[2], fast=fast)
        self.client.scene.set_background_image(r.rgb, format="png")
        if self._key() != key:  # changed while rendering: shown, but not counted as done
            return
        self.drawn = (key, full)
        what = "full" if full else "preview"
        how = "volume render"
        if fast:
            how = f"fast path, {r.volume_rendered or 0.0:.0%} of the rays volume rendered"
        st.renders += 1
        st.timing.content = (
            f"{what} {intr.width}x{intr.height}: {r.seconds * 1000:.0f} ms (render {st.renders})"
            f"  \n{how}"
        )


class Studio:
    def __init__(self, session: Session, server: viser.ViserServer):
        self.session, self.server = session, server
        self.running = True
        self.clients: dict[int, ClientView] = {}
        self.views_seen: set[int] = set()
        self.renders = 0  # renders shown so far (the page numbers them)
        self._build_scene()
        self._build_gui()
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)
        server.scene.on_click()(self._click)

    # ---- scene -----------------------------------------------------------------------------
    def _plan_rgba(self, alpha: int = 150) -> np.ndarray:
        lab = self.session.scene.bp.labels
        lut = np.array([(*class_color(i), alpha) for i in range(256)], np.uint8)
        lut[255, 3] = 0
        return lut[lab]

    def _floor_image(self, name: str, rgba: np.ndarray, z: float):
        g = self.session.scene.bp.grid
        h, w = g.shape
        cx, cy = g.origin[0] + w * g.cell / 2, g.origin[1] + h * g.cell / 2
        return self.server.scene.add_image(
            name, rgba, w * g.cell, h * g.cell, format="png", position=(cx, cy, z)
        )

    def _build_scene(self) -> None:
        sc, sess = self.server.scene, self.session
        sc.set_up_direction("+z")
        self.plan = self._floor_image("/plan", self._plan_rgba(), 0.002)
        self.highlight: viser.ImageHandle | None = None
        v, c = sess.scene.verts, sess.scene.colors
        idx = np.linspace(0, len(v) - 1, min(len(v), MAX_POINTS)).astype(int)
        col = (c[idx] * 255).astype(np.uint8) if c is not None else (180, 180, 180)
        self.points = sc.add_point_cloud(
            "/surface", v[idx].astype(np.float32), col, point_size=0.015,
            visible=not sess.scene.has_field,
        )  # fmt: skip
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

    def _jumper(self, i: int):
        def jump(ev) -> None:
            self._jump(ev.client, i)

        return jump

    def _show_selection(self) -> None:
        s = self.session.selection
        if self.highlight is not None:
            self.highlight.remove()
            self.highlight = None
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

    # ---- panel -----------------------------------------------------------------------------
    def say(self, text: str) -> None:
        self.message.content = text

    def _build_gui(self) -> None:
        gui, sess = self.server.gui, self.session
        gui.add_markdown(f"**blunf studio**: `{sess.files.run}`")
        self.message = gui.add_markdown("Click on the plan (the floor) to select an object.")
        if not sess.scene.has_field:
            gui.add_markdown(
                "This run has no trained NeRF: plan, surface and edits only. Save the edits, "
                "then train it and render them with  \n`"
                + TRAIN_HINT.format(run=sess.files.run)
                + "`"
            )
        self.sel_info = gui.add_markdown("Nothing selected: click on the plan.")
        with gui.add_folder("Select"):
            self.cls = gui.add_dropdown("Class", tuple(sess.classes()) or ("(none)",))
            gui.add_button("Select class").on_click(lambda _: self._do(self._select_class))
            self.sketching = gui.add_checkbox("Sketch: clicks draw", False)
            self.stroke_info = gui.add_markdown("Stroke: no points")
            gui.add_button("Clear stroke").on_click(lambda _: self._do(self._clear_stroke))
        with gui.add_folder("Edit"):
            self.op = gui.add_dropdown("Operation", OPS)
            self.color = gui.add_rgb("Colour", (40, 90, 200))
            self.strength = gui.add_slider("Strength", 0.0, 1.0, 0.05, 0.8)
            tex = tuple(sess.shipped_textures()) or ("(none)",)
            self.texture = gui.add_dropdown("Texture", tex)
            self.upload = gui.add_upload_button("Upload texture", mime_type="image/*")
            self.upload.on_upload(lambda _: self._do(self._uploaded))
            self.width = gui.add_slider("Stroke width (m)", 0.02, 0.5, 0.01, 0.1)
            gui.add_button("Apply").on_click(lambda _: self._do(self._apply))
            gui.add_button("Undo").on_click(lambda _: self._do(self._undo))
            gui.add_button("Redo").on_click(lambda _: self._do(self._redo))
            self.edit_list = gui.add_markdown("No edits.")
        with gui.add_folder("View"):
            self.before = gui.add_checkbox("Before (no edits)", False)
            self.render_only = gui.add_checkbox("Render only", False)
            self.render_only.on_update(lambda _: self._layers())
            names = [f"{i}: {f.stem}" for i, f in enumerate(sess.scene.cap.frames)]
            self.view_pick = gui.add_dropdown("Input view", tuple(names))
            gui.add_button("Go to view").on_click(lambda ev: self._do(lambda: self._go(ev)))
            # the preview always takes the fast path (stages/edit/surface.py); the full
            # view too by default (measured in the README: "The fast render path")
            self.full_path = gui.add_dropdown("Full view", FULL_PATHS)
            self.timing = gui.add_markdown("render: -")
        with gui.add_folder("File"):
            gui.add_button("Save").on_click(lambda _: self._do(self._save))
            gui.add_button("Load saved").on_click(lambda _: self._do(self._load))

    def _do(self, fn) -> None:
        """Run a panel action: a user error becomes the page's message, nothing applied."""
        try:
            fn()
        except BlunfError as e:
            self.say(f"**Not applied:** {e}")

    def _layers(self) -> None:
        show = not self.render_only.value
        self.plan.visible = show
        if self.highlight is not None:
            self.highlight.visible = show
        self.points.visible = show and not self.session.scene.has_field
        for f in self.frusta:
            f.visible = show

    def _click(self, ev) -> None:
        def go() -> None:
            if self.sketching.value:
                from pipeline.studio.state import floor_point

                x, y = floor_point(ev.ray_origin, ev.ray_direction)
                n = self.session.add_stroke_point(x, y)
                self.stroke_info.content = f"Stroke: {n} points (last {x:.2f}, {y:.2f} m)"
                return
            self.session.click_ray(ev.ray_origin, ev.ray_direction)
            self._show_selection()
            self.say("Selected; choose an operation and Apply.")

        self._do(go)

    def _select_class(self) -> None:
        self.session.select_class(self.cls.value)
        self._show_selection()
        self.say(f"Selected every {self.cls.value}.")

    def _clear_stroke(self) -> None:
        self.session.clear_stroke()
        self.stroke_info.content = "Stroke: no points"

    def _uploaded(self) -> None:
        f = self.upload.value
        name = self.session.add_texture(f.name, f.content)
        opts = tuple(dict.fromkeys([*self.texture.options, name]))
        self.texture.options = tuple(o for o in opts if o != "(none)")
        self.texture.value = name  # type: ignore[misc]
        self.say(f"Texture {name} added.")

    def _apply(self) -> None:
        op = self.op.value
        kw: dict = {"color": self.color.value, "strength": self.strength.value}
        if op == "retexture":
            kw["texture"] = self.texture.value
        if op == "sketch":
            kw["width"] = self.width.value
        self.session.apply(op, **kw)
        if op == "sketch":
            self.stroke_info.content = "Stroke: no points"
        self._edits_changed(f"Applied {op}.")

    def _undo(self) -> None:
        self._edits_changed("Undone." if self.session.undo() else "Nothing to undo.")

    def _redo(self) -> None:
        self._edits_changed("Redone." if self.session.redo() else "Nothing to redo.")

    def _edits_changed(self, msg: str) -> None:
        for cv in list(self.clients.values()):
            cv.moved = time.perf_counter()  # a preview first, then the full view
        lines = self.session.describe()
        self.edit_list.content = "  \n".join(lines) if lines else "No edits."
        self.say(msg)

    def _go(self, ev) -> None:
        n = int(str(self.view_pick.value).split(":")[0])
        targets = [self.clients[ev.client.client_id]] if ev.client else self.clients.values()
        for cv in targets:
            cv.jump(n)
        self.say(f"At input view {n}.")

    def _jump(self, client, n: int) -> None:
        if client is not None and client.client_id in self.clients:
            self.clients[client.client_id].jump(n)

    def _save(self) -> None:
        views = sorted(self.views_seen) or [0]
        path = self.session.save(views)
        if self.session.scene.has_field:  # the renders the spec reproduces, beside it
            out = path.parent / "studio_views"
            out.mkdir(exist_ok=True)
            from stages.common.io import write_image

            edits = self.session.parsed()
            for n in views:
                pose, intr = self.session.scene.view(n)
                stem = self.session.scene.cap.frames[n].stem
                write_image(out / f"{stem}.png", self.session.scene.render(pose, intr, edits).rgb)
        self.say(f"Saved {path} (views {views}).")

    def _load(self) -> None:
        n = self.session.load()
        self._edits_changed(f"Loaded {n} edits from {self.session.folder}.")

    # ---- tabs ------------------------------------------------------------------------------
    def _connect(self, client: viser.ClientHandle) -> None:
        self.clients[client.client_id] = ClientView(self, client)

    def _disconnect(self, client: viser.ClientHandle) -> None:
        cv = self.clients.pop(client.client_id, None)
        if cv is not None:
            cv.alive = False


def serve(run: Path, host: str = "127.0.0.1", port: int = 8080) -> int:
    """Serve the studio until interrupted."""
    session = Session(Path(run))  # a folder that is not a run fails here, with one line
    server = viser.ViserServer(host=host, port=port, verbose=False)
    studio = Studio(session, server)
    print(f"blunf studio: http://{host}:{server.get_port()}  ({run})", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        studio.running = False
        server.stop()
    return 0

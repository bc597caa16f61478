"""The studio's panel: selection, edits, view, file, and training the NeRF of a run without one.

It owns the panel's widgets and their actions; what an action changes in the 3-D scene it
asks of the scene (`pipeline.studio.scene`), what it changes in the tabs
(`pipeline.studio.tabs`). Every action runs through `do`, so that a user error becomes the
page's message and changes nothing. A value the page sends is checked against what the
server offered, never against the handle's `options` (viser lets a client set those too):
the session checks the edits' values, `offered` here the input view and the full view's
path.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import viser

from pipeline.render import TRAIN_HINT
from pipeline.studio.plan_view import plan_picture
from pipeline.studio.scene import StudioScene
from pipeline.studio.state import Session
from pipeline.studio.tabs import Tabs
from pipeline.studio.train import Trainer
from pipeline.studio.values import OPS, STRENGTH, WIDTH, offered
from stages.common.errors import BlunfError

FULL_PATHS = ("fast", "volume")  # how the full view is rendered (the first: the default)
PLAN_SCALE = 2  # pixels of the panel's plan picture per plan cell


class Panel:
    """The panel's widgets, and what each does."""

    def __init__(
        self,
        session: Session,
        server: viser.ViserServer,
        scene: StudioScene,
        tabs: Tabs,
        trainer: Trainer,
        running: Callable[[], bool],
        on_sketch: Callable[[bool], None],
        on_field: Callable[[], None],
    ):
        self.session, self.server, self.scene, self.tabs = session, server, scene, tabs
        self.trainer = trainer
        self.on_sketch = on_sketch  # the "Sketch" checkbox changed: drags on the plan draw
        self.on_field = on_field  # the NeRF trained from the page is ready
        self.running = running  # False: the studio stops (the training's watch ends)
        self._build()

    def say(self, text: str) -> None:
        self.message.content = text

    def _build(self) -> None:
        gui, sess = self.server.gui, self.session
        gui.add_markdown(f"**blunf studio**: `{sess.files.run}`")
        self.message = gui.add_markdown("Click on the plan (the floor) to select an object.")
        self.no_field = gui.add_markdown(
            "This run has no trained NeRF: plan, surface and edits only. Apply edits, then "
            "train it here (minutes: the NeRF for editing, as `blunf run` trains it) or with  \n`"
            + TRAIN_HINT.format(run=sess.files.run)
            + "`",
            visible=not sess.scene.has_field,
        )
        self.train_button = gui.add_button("Train the NeRF", visible=not sess.scene.has_field)
        self.train_button.on_click(lambda _: self.do(self._train))
        self.train_bar = gui.add_progress_bar(0.0, visible=False)
        self.train_info = gui.add_markdown("", visible=False)
        self.sel_info = gui.add_markdown("Nothing selected: click on the plan.")
        with gui.add_folder("Plan"):
            self.picture = gui.add_image(
                plan_picture(sess.scene.bp, scale=PLAN_SCALE), format="png"
            )
            gui.add_button("Plan view (2D)").on_click(
                lambda ev: self.do(lambda: self._to_plan_view(ev))
            )
            self.cls = gui.add_dropdown("Class", tuple(sess.classes()) or ("(none)",))
            gui.add_button("Select class").on_click(lambda _: self.do(self._select_class))
            self.sketching = gui.add_checkbox("Sketch: draw on the plan", False)
            self.sketching.on_update(lambda _: self.on_sketch(self.sketching.value))
            self.stroke_info = gui.add_markdown("Stroke: no points")
            gui.add_button("Clear stroke").on_click(lambda _: self.do(self._clear_stroke))
        with gui.add_folder("Edit"):
            self.op = gui.add_dropdown("Operation", OPS)
            self.color = gui.add_rgb("Colour", (40, 90, 200))
            self.strength = gui.add_slider("Strength", *STRENGTH, 0.05, 0.8)
            tex = tuple(sess.textures()) or ("(none)",)
            self.texture = gui.add_dropdown("Texture", tex)
            self.upload = gui.add_upload_button("Upload texture", mime_type="image/*")
            self.upload.on_upload(lambda _: self.do(self._uploaded))
            self.width = gui.add_slider("Stroke width (m)", *WIDTH, 0.01, 0.1)
            gui.add_button("Apply").on_click(lambda _: self.do(self._apply))
            gui.add_button("Undo").on_click(lambda _: self.do(self._undo))
            gui.add_button("Redo").on_click(lambda _: self.do(self._redo))
            self.edit_list = gui.add_markdown("No edits.")
        with gui.add_folder("View"):
            self.before = gui.add_checkbox("Before (no edits)", False)
            self.render_only = gui.add_checkbox("Render only", False)
            self.render_only.on_update(lambda _: self.scene.show(not self.render_only.value))
            self.view_names = tuple(f"{i}: {f.stem}" for i, f in enumerate(sess.scene.cap.frames))
            self.view_pick = gui.add_dropdown("Input view", self.view_names)
            gui.add_button("Go to view").on_click(lambda ev: self.do(lambda: self._go(ev)))
            # the preview always takes the fast path (stages/edit/surface.py); the full
            # view too by default (measured in the README: "The fast render path")
            self.full_path = gui.add_dropdown("Full view", FULL_PATHS)
            self.full_path.on_update(lambda _: self.do(self._full_path))
            self.timing = gui.add_markdown("render: -")
        with gui.add_folder("File"):
            gui.add_button("Save").on_click(lambda _: self.do(self._save))
            gui.add_button("Load saved").on_click(lambda _: self.do(self._load))

    def do(self, fn) -> None:
        """Run a panel action: a user error becomes the page's message, nothing applied."""
        try:
            fn()
        except BlunfError as e:
            self.say(f"**Not applied:** {e}")

    def show_selection(self) -> None:
        """The session's selection on the floor, on the plan picture and in words."""
        s = self.session.selection
        self.scene.show_selection(s)
        self._draw_picture()
        if s is None:
            self.sel_info.content = "Nothing selected: click on the plan."
            return
        i = s.info
        self.sel_info.content = (
            f"**Selected:** {i['class']} (instance {', '.join(map(str, i['instance']))}), "
            f"{i['area_m2']} m², x {i['bbox'][0]}..{i['bbox'][2]}, "
            f"y {i['bbox'][1]}..{i['bbox'][3]} m"
        )

    def _to_plan_view(self, ev) -> None:
        for cv in self.tabs.of(ev):
            cv.plan_view()
        self.say("Plan view: click on the plan to select, or draw on it with Sketch on.")

    def _draw_picture(self) -> None:
        """The panel's plan picture: the selection and the stroke on the plan."""
        s = self.session.selection
        self.picture.image = plan_picture(
            self.session.scene.bp,
            None if s is None else s.cells,
            list(self.session.stroke),
            scale=PLAN_SCALE,
        )

    def _select_class(self) -> None:
        self.session.select_class(self.cls.value)
        self.show_selection()
        self.say(f"Selected every {self.cls.value}.")

    def _clear_stroke(self) -> None:
        self.session.clear_stroke()
        self.stroke_changed()

    def stroke_changed(self, picture: bool = True) -> None:
        st = self.session.stroke
        self.stroke_info.content = (
            f"Stroke: {len(st)} points (last {st[-1][0]:.2f}, {st[-1][1]:.2f} m)"
            if st
            else "Stroke: no points"
        )
        self.scene.draw_stroke(st)
        if picture:
            self._draw_picture()

    def _uploaded(self) -> None:
        f = self.upload.value
        name = self.session.add_texture(f.name, f.content)
        self.texture.options = tuple(self.session.textures())
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
            self.stroke_changed()
        self._edits_changed(f"Applied {op}.")

    def _full_path(self) -> None:
        if self.full_path.value not in FULL_PATHS:  # a value the page was not offered
            self.full_path.options = FULL_PATHS
            # viser defines value's setter apart from its getter: mypy reads it as read-only
            self.full_path.value = FULL_PATHS[0]  # type: ignore[misc]
            raise BlunfError("full view: not one of the choices offered")

    def _undo(self) -> None:
        self._edits_changed("Undone." if self.session.undo() else "Nothing to undo.")

    def _redo(self) -> None:
        self._edits_changed("Redone." if self.session.redo() else "Nothing to redo.")

    def _edits_changed(self, msg: str) -> None:
        self.tabs.redraw()
        lines = self.session.describe()
        self.edit_list.content = "  \n".join(lines) if lines else "No edits."
        self.say(msg)

    def _go(self, ev) -> None:
        n = int(offered(self.view_pick.value, self.view_names, "input view").split(":")[0])
        for cv in self.tabs.of(ev):
            cv.jump(n)
        self.say(f"At input view {n}.")

    def _save(self) -> None:
        views = sorted(self.tabs.views_seen) or [0]
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

    # ---- training --------------------------------------------------------------------------
    def _train(self) -> None:
        spec = self.trainer.start(sorted(self.tabs.views_seen) or [0])
        self.train_button.disabled = True
        self.train_bar.visible = self.train_info.visible = True
        self.say(f"Training the NeRF for {spec} (the page follows it).")
        threading.Thread(target=self._watch_training, daemon=True).start()

    def _watch_training(self) -> None:
        """Show the training's progress once a second; when done, the renders start."""
        while self.running():
            line, frac = self.trainer.progress()
            self.train_info.content = line
            self.train_bar.animated = frac is None
            self.train_bar.value = 100.0 * (frac or 0.0)  # type: ignore[misc]
            if not self.trainer.running:
                break
            time.sleep(1.0)
        if self.trainer.state == "done":
            self.on_field()
            self.train_bar.visible = self.train_button.visible = self.no_field.visible = False
            self.say("The NeRF is trained: the view shows the edits.")
        else:
            self.train_button.disabled = False
            self.say(f"**Not trained:** {self.trainer.error}")

"""One tab of the studio: its camera and the render thread that draws its background.

The background is the NeRF's render from the tab's camera with the edits applied
(`stages.edit.view.EditedView.render`, through `pipeline.render.Scene`): a quarter-resolution
preview while the camera moves, the full view once it rests. It is sent with its depth, so the
plan on the floor, the selection and the frusta are hidden behind the rendered surfaces
(without it, the plan would be drawn over every pixel below the horizon, objects included,
and wash out what an edit changed).
In the plan view (the camera straight above the plan) nothing is rendered: the canvas shows
the plan alone.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Protocol

import numpy as np
import viser

from pipeline.render import pose_wxyz, viewer_camera
from pipeline.studio.plan_view import PLAN_FOV, top_view
from stages.common.errors import BlunfError
from stages.edit.view import scaled

if TYPE_CHECKING:
    from pipeline.studio.state import Session

log = logging.getLogger(__name__)

PREVIEW = 0.25  # preview resolution, a fraction of the full view
REST = 0.3  # seconds without camera motion before the full view is rendered
# the render's depth is sent this much deeper (metres): the plan, 2 mm above the floor, stays
# in front of the rendered floor (the fused floor lies within a few cm of z = 0) and behind
# the objects standing on it
DEPTH_MARGIN = 0.05
FAR = 1000.0  # the depth sent where the render has no surface
LOOKS_DOWN = np.cos(np.deg2rad(0.5))  # a camera this close to straight down shows the plan


def background_depth(depth: np.ndarray | None) -> np.ndarray | None:
    """The depth sent with a render: deeper by DEPTH_MARGIN, FAR where there is no surface."""
    if depth is None:
        return None
    d = np.asarray(depth, np.float32)
    return np.where(np.isfinite(d), d + DEPTH_MARGIN, FAR).astype(np.float32)


class Choices(Protocol):
    """The panel's settings a render reads, and where it reports (`pipeline.studio.panel`)."""

    before: viser.GuiCheckboxHandle  # "Before (no edits)"
    full_path: viser.GuiDropdownHandle  # the full view's path: fast or volume
    timing: viser.GuiMarkdownHandle  # where the render's time is shown

    def say(self, text: str) -> None: ...


class Seen(Protocol):
    """What the tabs keep of every tab (`pipeline.studio.tabs.Tabs`)."""

    views_seen: set[int]
    renders: int  # renders shown so far


class Host(Protocol):
    """What a tab needs of the studio that serves it (`pipeline.studio.app.Studio`)."""

    session: Session
    running: bool

    @property
    def panel(self) -> Choices: ...

    @property
    def tabs(self) -> Seen: ...


class ClientView:
    """One tab: its camera, its render thread, the input view it stands at (if any)."""

    def __init__(self, studio: Host, client: viser.ClientHandle):
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
        self.studio.tabs.views_seen.add(n)

    def plan_view(self) -> None:
        """The camera straight above the plan, north up: the canvas shows the plan in 2-D."""
        cam = self.client.camera
        position, wxyz = top_view(self.studio.session.scene.bp.grid, cam.aspect)
        with self.client.atomic():
            cam.fov = float(PLAN_FOV)
            cam.position = position
            cam.wxyz = wxyz
        self.at_view = None
        self.moved = time.perf_counter()

    def in_plan_view(self) -> bool:
        """Whether the camera looks straight down on the plan (as `plan_view` puts it; a pan
        or a zoom keeps it there, an orbit leaves). Read from the camera alone: the page
        may report its previous camera once more after `plan_view` moved it."""
        cam = self.client.camera
        pose, _ = viewer_camera(cam.position, cam.wxyz, cam.fov, 1.0, 8)
        return bool(pose[2, 2] < -LOOKS_DOWN)

    def camera(self, full: bool):
        """The pose and intrinsics to render: the input view's own pose when the camera
        stands there, the tab's camera otherwise (canvas aspect, the frames' height)."""
        from stages.common.camera import Intrinsics

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
                self.studio.panel.say(f"**Render:** {e}")
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
        return (state, st.session.version, st.panel.before.value, st.panel.full_path.value)

    def _tick(self) -> None:
        st = self.studio
        if not st.session.scene.has_field:
            return
        key = self._key()
        if key is None:
            return
        if self.in_plan_view():
            if self.drawn is None or self.drawn[0] != "plan":
                self.client.scene.set_background_image(None)
                self.drawn = ("plan", True)
            return
        full = time.perf_counter() - self.moved >= REST
        if self.drawn is not None and self.drawn[0] == key and (self.drawn[1] or not full):
            return
        pose, intr = self.camera(full)
        fast = not full or st.panel.full_path.value == "fast"
        scene = st.session.scene
        r = scene.render(pose, intr, st.session.parsed(), before=key[2], fast=fast)
        self.client.scene.set_background_image(r.rgb, format="png", depth=background_depth(r.depth))
        if self._key() != key:  # changed while rendering: shown, but not counted as done
            return
        self.drawn = (key, full)
        what = "full" if full else "preview"
        how = "volume render"
        if fast:
            how = f"fast path, {r.volume_rendered or 0.0:.0%} of the rays volume rendered"
        st.tabs.renders += 1
        st.panel.timing.content = (
            f"{what} {intr.width}x{intr.height}: {r.seconds * 1000:.0f} ms "
            f"(render {st.tabs.renders})"
            f"  \n{how}"
        )

"""The studio's 3-D scene, shared by every tab: the plan on the floor (z = 0), the selection
over it, the sketch's stroke, the fused surface as points (until a NeRF renders the
background) and the input cameras as frusta (a click on one goes to `on_camera`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import viser

from pipeline.render import pose_wxyz
from pipeline.studio.plan_view import HIGHLIGHT, STROKE, plan_extent, plan_rgba
from pipeline.studio.state import Selection, Session

MAX_POINTS = 60000  # points of the fused surface sent to the page


class StudioScene:
    """The scene's nodes: `plan`, `highlight`, `stroke_line`, `points`, `frusta`."""

    def __init__(
        self, session: Session, server: viser.ViserServer, on_camera: Callable[[int, Any], None]
    ):
        self.session, self.server = session, server
        self.shown = True  # the plan, selection, surface and frusta are shown (not "render only")
        sc = server.scene
        sc.set_up_direction("+z")
        self.plan = self._floor_image("/plan", plan_rgba(session.scene.bp), 0.002)
        self.highlight: viser.ImageHandle | None = None
        self.stroke_line: viser.LineSegmentsHandle | None = None
        v, c = session.scene.verts, session.scene.colors
        idx = np.linspace(0, len(v) - 1, min(len(v), MAX_POINTS)).astype(int)
        col = (c[idx] * 255).astype(np.uint8) if c is not None else (180, 180, 180)
        self.points = sc.add_point_cloud(
            "/surface", v[idx].astype(np.float32), col, point_size=0.015,
            visible=not session.scene.has_field,
        )  # fmt: skip
        self.frusta = []
        for i, f in enumerate(session.scene.cap.frames):
            if f.pose is None:
                continue
            pose = np.asarray(f.pose)
            intr = f.intrinsics
            h = sc.add_camera_frustum(
                f"/cameras/{i}", float(2 * np.arctan(0.5 * intr.height / intr.fy)),
                intr.width / intr.height, scale=0.15, wxyz=pose_wxyz(pose),
                position=pose[:3, 3], color=(40, 80, 200),
            )  # fmt: skip
            h.on_click(_clicked(on_camera, i))
            self.frusta.append(h)

    def _floor_image(self, name: str, rgba: np.ndarray, z: float):
        """A picture of the plan's cells (row 0 north) lying on the floor at height z."""
        cx, cy, w, h = plan_extent(self.session.scene.bp.grid)
        # viser lays an image's row 0 towards the node's -y (its image axes are a camera's:
        # y down), so the rows go in south first to put the plan's north at +y
        return self.server.scene.add_image(
            name, np.ascontiguousarray(rgba[::-1]), w, h, format="png", position=(cx, cy, z)
        )

    def show_selection(self, s: Selection | None) -> None:
        """The selected cells highlighted on the floor (none: the highlight goes)."""
        if self.highlight is not None:
            self.highlight.remove()
            self.highlight = None
        if s is None:
            return
        rgba = np.zeros((*s.cells.shape, 4), np.uint8)
        rgba[s.cells] = HIGHLIGHT
        self.highlight = self._floor_image("/selection", rgba, 0.004)
        self.highlight.visible = self.shown

    def draw_stroke(self, stroke: list[tuple[float, float]]) -> None:
        """The stroke being drawn, as a red line on the plan."""
        if self.stroke_line is not None:
            self.stroke_line.remove()
            self.stroke_line = None
        if len(stroke) >= 2:
            p = np.array([(x, y, 0.006) for x, y in stroke], np.float32)
            seg = np.stack([p[:-1], p[1:]], axis=1)  # [N-1, 2, 3]
            self.stroke_line = self.server.scene.add_line_segments(
                "/stroke", seg, STROKE[:3], thickness=0.02
            )

    def show(self, shown: bool) -> None:
        """Show the plan, selection, surface and frusta, or hide them (the render only)."""
        self.shown = shown
        self.plan.visible = shown
        if self.highlight is not None:
            self.highlight.visible = shown
        self.points.visible = shown and not self.session.scene.has_field
        for f in self.frusta:
            f.visible = shown

    def field_ready(self) -> None:
        """The run has a NeRF now: its renders replace the surface's points."""
        self.points.visible = False


def _clicked(on_camera: Callable[[int, Any], None], i: int) -> Callable[[Any], None]:
    def clicked(ev: Any) -> None:
        on_camera(i, ev)

    return clicked

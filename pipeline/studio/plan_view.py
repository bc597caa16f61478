"""The plan as a picture in the page, the top-down view on it, and strokes drawn with the pointer.

viser (1.1) shows a picture in its panel (`gui.add_image`) but reports no pointer event on
it: its client sends no message for a click on a GUI image. So the panel's picture shows
the plan, the selection and the stroke being drawn, and the clicks go through the 3-D
canvas, where the plan lies on the floor as an image node: "Plan view" puts a tab's camera
straight above the plan looking down, north up (`top_view`). A plane seen square-on through
a pinhole is an exact scaled copy of itself, so the canvas then shows the plan as a 2-D
picture, and a click there takes the same path as anywhere in 3-D: the pointer's ray, its
floor point (`values.floor_point`), the plan cell under it (`Session.click`).

Strokes: the plan's image node reports drags (start, update, end, ~20 a second) with the
pointer projected on a plane facing the camera through the grab point; the line from the
camera through that point is the pointer's ray, and its floor point is the stroke's next
point (`StrokeDrag`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.render import viewer_camera
from pipeline.studio.values import floor_point
from stages.common.blueprint import Blueprint, Grid
from stages.common.classes import class_color

HIGHLIGHT = (255, 0, 255, 170)
STROKE = (255, 40, 40, 255)
PLAN_FOV = np.deg2rad(40.0)  # the top view's vertical field of view
# the top view leans this much off the vertical (radians): a camera looking exactly along
# the viewer's up axis leaves its orbit controls without an azimuth
TILT = 1e-3
MARGIN = 1.05  # the top view frames the plan with this much room round it


def plan_rgba(bp: Blueprint, alpha: int = 150) -> np.ndarray:
    """The plan's cells in their class colours [H, W, 4] (unknown cells transparent)."""
    lut = np.array([(*class_color(i), alpha) for i in range(256)], np.uint8)
    lut[255, 3] = 0
    return lut[bp.labels]


def plan_picture(
    bp: Blueprint,
    selected: np.ndarray | None = None,
    stroke: Sequence[tuple[float, float]] = (),
    scale: int = 2,
) -> np.ndarray:
    """The panel's picture [H*scale, W*scale, 3]: the plan on white, the selected cells in
    magenta, the stroke's points in red."""
    rgba = plan_rgba(bp, 255).astype(np.float32)
    a = rgba[..., 3:] / 255.0
    rgb = rgba[..., :3] * a + 255.0 * (1 - a)
    if selected is not None:
        k = HIGHLIGHT[3] / 255.0
        rgb[selected] = (1 - k) * rgb[selected] + k * np.array(HIGHLIGHT[:3], np.float32)
    if len(stroke):
        r, c, ok = bp.grid.cell_of(np.asarray(stroke, np.float64))
        rgb[r[ok], c[ok]] = STROKE[:3]
    out = rgb.round().clip(0, 255).astype(np.uint8)
    return np.repeat(np.repeat(out, scale, axis=0), scale, axis=1)


def cell_centre(grid: Grid, row: int, col: int) -> tuple[float, float]:
    """The world point (x, y) at the centre of cell (row, col)."""
    x = grid.origin[0] + (col + 0.5) * grid.cell
    y = grid.origin[1] + (grid.shape[0] - 1 - row + 0.5) * grid.cell
    return float(x), float(y)


def plan_extent(grid: Grid) -> tuple[float, float, float, float]:
    """The plan's centre (x, y) and size (width, height) in metres."""
    h, w = grid.shape
    cx, cy = grid.origin[0] + w * grid.cell / 2, grid.origin[1] + h * grid.cell / 2
    return float(cx), float(cy), float(w * grid.cell), float(h * grid.cell)


def top_view(grid: Grid, aspect: float, fov: float = PLAN_FOV) -> tuple[np.ndarray, np.ndarray]:
    """The camera (position, quaternion w x y z, OpenCV axes) above the plan's centre that
    looks down on the whole plan, north up, through a vertical field of view `fov`."""
    from pipeline.render import pose_wxyz

    cx, cy, w, h = plan_extent(grid)
    half = 0.5 * MARGIN * max(h, w / max(aspect, 1e-6))  # metres the view must show up / down
    dist = half / np.tan(0.5 * fov)
    fwd = np.array([0.0, np.sin(TILT), -np.cos(TILT)])  # down, a hair north
    right = np.array([1.0, 0.0, 0.0])
    down = np.cross(fwd, right)  # OpenCV: x right, y down, z forward (y = z x x)
    rot = np.stack([right, down, fwd], axis=1)
    position = np.array([cx, cy, 0.0]) - dist * fwd
    return position, pose_wxyz(np.block([[rot, position[:, None]], [np.zeros((1, 3)), 1.0]]))


def screen_ray(
    position: Any, wxyz: Any, fov: float, aspect: float, screen: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """The ray (origin, unit direction) of a viewer camera through a canvas point `screen`
    (OpenCV image coordinates scaled to 0..1, (0, 0) the top left corner)."""
    pose, intr = viewer_camera(position, wxyz, fov, aspect, 1000)
    u = float(screen[0]) * intr.width - 0.5
    v = float(screen[1]) * intr.height - 0.5
    d_cam = np.array([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])
    d = pose[:3, :3] @ d_cam
    return pose[:3, 3].copy(), d / np.linalg.norm(d)


class StrokeDrag:
    """A drag on the plan turned into the session's stroke: `start` begins a new stroke at the
    grab point, each `move` adds the floor point under the pointer (points closer than
    `min_step` metres to the last one are skipped), `end` closes it."""

    def __init__(self, session: Any, min_step: float):
        self.session, self.min_step = session, min_step
        self.active = False

    def start(self, grab: Sequence[float]) -> int:
        self.active = True
        self.session.clear_stroke()
        return self.session.add_stroke_point(float(grab[0]), float(grab[1]))

    def move(self, camera: Any, pointer: Sequence[float]) -> int:
        """Add the floor point on the ray from the camera's position through `pointer` (a
        world point on the pointer's ray); returns the stroke's length."""
        if not self.active:
            return len(self.session.stroke)
        o = np.asarray(camera, np.float64)
        x, y = floor_point(o, np.asarray(pointer, np.float64) - o)
        return self.session.add_stroke_point(x, y, self.min_step)

    def end(self, camera: Any, pointer: Sequence[float]) -> int:
        n = self.move(camera, pointer)
        self.active = False
        return n

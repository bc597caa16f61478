"""The analytic field the edit tests render, with everything about it worked out by hand.

The scene: a grey floor slab z in [-0.1, 0) over [0, 2]^2, a red box A over [0.4, 0.8]^2 and
a blue box B over [1.2, 1.6]^2, both z in [0, 0.5] and both of class chair. Densities are
1e4 / m (opaque within one 1 cm step), 0 elsewhere.

The camera looks straight down from (1, 1, 20) with f = 200 px on a 20 x 20 image (cx = cy =
9.5): pixel (u, v) sees the floor at x = 1 + (u - 9.5) 0.1, y = 1 - (v - 9.5) 0.1, and the
box tops (z = 0.5, 19.5 m away) at x = 1 + (u - 9.5) 0.0975, y = 1 - (v - 9.5) 0.0975.
So A covers columns u 4..7 (x 0.464 .. 0.756; u = 3 gives 0.366, u = 8 0.854) and rows
v 12..15; B covers u 12..15 and v 4..7. The rays are so steep that none clips a box's side
(u = 3 goes from x 0.366 at the top's height to 0.35 at the floor, never reaching 0.4).

The plan: 0.1 m cells from the origin, 20 x 20, floor (0) everywhere but chair (4) on A's
cells (columns 4..7, rows 12..15: row = 19 - floor(y / 0.1)) and B's (columns 12..15,
rows 4..7).
"""

from __future__ import annotations

import numpy as np
import torch

from stages.common.blueprint import Blueprint, Grid
from stages.common.camera import Intrinsics
from stages.common.components import component_map
from stages.common.radiance.field import field_of
from stages.common.radiance.rays import camera_rays
from stages.common.radiance.render import RenderOptions
from stages.edit.config import EditConfig, SelectConfig
from stages.edit.ops import FieldEdit, reference_luminance
from stages.edit.render import look_at, render_rays_edited
from stages.edit.select import extent_of, select_cells
from stages.edit.spec import Selector

GREY = (0.5, 0.5, 0.5)
RED = (1.0, 0.0, 0.0)
BLUE = (0.0, 0.0, 1.0)
BOX_A = (0.4, 0.8, 0.4, 0.8)  # x0, x1, y0, y1
BOX_B = (1.2, 1.6, 1.2, 1.6)
SIGMA = 1e4
# floor_clear 0: the boxes stand on the floor with their bottom at z = 0, the floor slab is
# z < 0, so an extent from z = 0 up holds all of a box and none of the floor. pad 0: the
# footprints are exactly the boxes' cells.
CFG = EditConfig(select=SelectConfig(floor_clear=0.0, pad=0.0))


def _in_box(x: torch.Tensor, b: tuple[float, float, float, float]) -> torch.Tensor:
    return (
        (x[:, 0] >= b[0])
        & (x[:, 0] < b[1])
        & (x[:, 1] >= b[2])
        & (x[:, 1] < b[3])
        & (x[:, 2] >= 0.0)
        & (x[:, 2] <= 0.5)
    )


def _floor(x: torch.Tensor) -> torch.Tensor:
    inside = (x[:, :2] >= 0).all(dim=1) & (x[:, :2] < 2).all(dim=1)
    return inside & (x[:, 2] >= -0.1) & (x[:, 2] < 0.0)


def density(x: torch.Tensor) -> torch.Tensor:
    solid = _floor(x) | _in_box(x, BOX_A) | _in_box(x, BOX_B)
    return torch.where(solid, SIGMA, 0.0)


def color(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    c = torch.tensor(GREY).expand(len(x), 3).clone()
    c[_in_box(x, BOX_A)] = torch.tensor(RED)
    c[_in_box(x, BOX_B)] = torch.tensor(BLUE)
    return c


INTR = Intrinsics(200.0, 200.0, 9.5, 9.5, 20, 20)
POSE = look_at(np.array([1.0, 1.0, 20.0]), np.array([1.0, 1.0, 0.0]))


def _gt_instances() -> np.ndarray:
    """Instance per pixel (1 = A, 2 = B, 0 = floor), from the geometry worked out above."""
    inst = np.zeros((20, 20), np.int32)
    inst[12:16, 4:8] = 1
    inst[4:8, 12:16] = 2
    return inst


def _plan() -> Blueprint:
    lab = np.zeros((20, 20), np.uint8)
    lab[12:16, 4:8] = 4
    lab[4:8, 12:16] = 4
    return Blueprint(lab, Grid((0.0, 0.0), 0.1, (20, 20)), {0: "floor", 4: "chair"})


def _vertices() -> tuple[np.ndarray, np.ndarray]:
    """Points of the surfaces a fusion would see, with colours: the floor at the centres of
    the floor cells (z = 0), the boxes' tops and sides every 5 cm, and a ceiling at z = 2.5
    over everything (the height measurement must stop below it)."""
    pts, cols = [], []
    g = np.arange(0.025, 2.0, 0.05)
    xx, yy = np.meshgrid(g, g)
    xy = np.stack([xx, yy], -1).reshape(-1, 2)
    floor = _plan().sample(xy) == 0
    pts.append(np.c_[xy[floor], np.zeros(floor.sum())])
    cols.append(np.tile(GREY, (floor.sum(), 1)))
    pts.append(np.c_[xy, np.full(len(xy), 2.5)])
    cols.append(np.tile((1.0, 1.0, 1.0), (len(xy), 1)))
    for (x0, x1, y0, y1), c in ((BOX_A, RED), (BOX_B, BLUE)):
        s = np.arange(0.0, 0.41, 0.05)
        tx, ty = np.meshgrid(x0 + s, y0 + s)
        top = np.c_[tx.ravel(), ty.ravel(), np.full(tx.size, 0.5)]
        zz = np.arange(0.05, 0.5, 0.05)
        side = np.array(
            [(x0, y0 + a, z) for a in s for z in zz]
            + [(x1, y0 + a, z) for a in s for z in zz]
            + [(x0 + a, y0, z) for a in s for z in zz]
            + [(x0 + a, y1, z) for a in s for z in zz]
        )
        pts += [top, side]
        cols += [np.tile(c, (len(top), 1)), np.tile(c, (len(side), 1))]
    return np.concatenate(pts), np.concatenate(cols)


def _select(kind: str, value, width: float = 0.0) -> np.ndarray:
    bp = _plan()
    return select_cells(Selector(kind, value, width, f"test.{kind}"), bp, component_map(bp))


def _edit(op: str, cells: np.ndarray, cfg: EditConfig = CFG, **kw) -> FieldEdit:
    bp = _plan()
    v, c = _vertices()
    ext, _ = extent_of(cells, bp, component_map(bp), v, cfg)
    return FieldEdit(op, ext, ref_lum=reference_luminance(ext, v, c), **kw)


def _render(edits=(), masks=(), surface: bool = False) -> dict:
    o, d, _ = camera_rays(POSE, INTR)
    opts = RenderOptions(near=19.0, far=20.2, step=0.01, surface_color=surface)
    out = render_rays_edited(o, d, field_of(density, color), opts, edits, masks)
    return {
        "rgb": out["rgb"].view(20, 20, 3).numpy(),
        "masks": out["masks"].view(-1, 20, 20).numpy(),
    }

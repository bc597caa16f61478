"""Edit operations on a field given as functions, and on the fused mesh.

The field is wrapped, never retrained: `remove` zeroes the density of the samples inside the
extent (what was behind or under shows through; ground that no view saw under the object is
filled with the colour of the fused floor round it, `fill`); the colour ops replace the
colour of the samples inside. `recolor` and `retexture` keep the shading: the new colour is
scaled by the sample's luminance over the selection's reference luminance (the median
luminance of the selection's own colour: the field's at the fused surface inside the extent,
or the mesh's vertex colours there when editing the mesh), so a shadow stays a shadow.
`sketch` paints its colour flat. Each op blends with weight `strength`. `mask` changes
nothing in the field: its output is the per-view mask (see `stages.edit.render`). The same
colour functions edit the mesh's vertices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from stages.common.radiance.field import FieldFns, FieldOut
from stages.edit.select import Extent

LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance weights
MAX_SHADE = 4.0  # a sample at most this many times brighter than the reference
NEUTRAL = 200  # grey level given to a mesh without vertex colours before a colour edit


@dataclass(frozen=True)
class FieldEdit:
    """One resolved edit: what it does and where."""

    op: str  # mask | recolor | retexture | sketch | remove
    extent: Extent
    color: Tensor | None = None  # [3] RGB in [0, 1] (recolor, sketch)
    strength: float = 1.0  # blend weight in [0, 1]
    texture: Tensor | None = None  # [Ht, Wt, 3] RGB in [0, 1], row 0 = highest y (retexture)
    ref_lum: float | None = None  # luminance of the selection's own colour; None = no shading
    fill: Tensor | None = None  # [3] remove: colour of the ground under the footprint where
    #                             the field has none (no view saw it); None = left empty


def luminance(c: Tensor) -> Tensor:
    """[N, 3] RGB -> [N] luminance."""
    return c @ torch.tensor(LUMA, dtype=c.dtype)


def reference_luminance(extent: Extent, vertices: np.ndarray, colors: np.ndarray) -> float | None:
    """Median luminance of the vertex colours [N, 3] (0-1) inside the extent; None if none."""
    if len(vertices) == 0:
        return None
    inside = extent.contains(np.asarray(vertices, np.float64))
    if not inside.any():
        return None
    lum = np.asarray(colors, np.float64)[inside] @ np.asarray(LUMA)
    return float(np.median(lum))


@torch.no_grad()
def _field_colors(field: FieldFns, points: np.ndarray, most: int) -> Tensor | None:
    """The field's colour [M, 3] at surface points [N, 3] (at most `most`, evenly picked),
    seen from above; None without points."""
    if len(points) == 0:
        return None
    idx = np.linspace(0, len(points) - 1, min(len(points), most)).round().astype(int)
    x = torch.from_numpy(np.asarray(points)[idx].astype(np.float32))  # [M, 3]
    return field.query(x, torch.tensor([0.0, 0.0, -1.0]).expand(len(x), 3)).rgb


def field_luminance(field: FieldFns, points: np.ndarray, most: int = 20000) -> float | None:
    """Median luminance of the field's colour at surface points [N, 3]; None without."""
    c = _field_colors(field, points, most)
    return None if c is None else float(luminance(c).median())


def field_color(field: FieldFns, points: np.ndarray, most: int = 20000) -> Tensor | None:
    """Median RGB [3] of the field's colour at surface points [N, 3]; None without."""
    c = _field_colors(field, points, most)
    return None if c is None else c.median(dim=0).values.clamp(0.0, 1.0)


def fill_ground(
    edits: Sequence[FieldEdit], origins: Tensor, dirs: Tensor, rgb: Tensor, acc: Tensor
) -> tuple[Tensor, Tensor]:
    """Rays [R] that reach the floor (z = 0) under a removed footprint with opacity to spare
    take the edit's fill colour for it: rgb + (1 - acc) * fill, acc -> 1. Under an object no
    view saw the ground, and the field has nothing there: without this the render shows
    the void below the floor (black). Returns the new rgb [R, 3] and acc [R]."""
    fills = [e for e in edits if e.op == "remove" and e.fill is not None]
    if not fills:
        return rgb, acc
    down = dirs[:, 2] < 0
    t = torch.where(down, -origins[:, 2] / torch.where(down, dirs[:, 2], -1.0), -1.0)
    hit = origins + t.clamp(min=0.0)[:, None] * dirs  # [R, 3] the floor point
    for e in fills:
        assert e.fill is not None
        under = down & (t > 0) & torch.as_tensor(e.extent.over(hit[:, :2]))
        rest = torch.where(under, 1.0 - acc, 0.0).clamp(min=0.0)  # [R]
        rgb = rgb + rest[:, None] * e.fill.to(rgb.dtype)
        acc = acc + rest
    return rgb, acc


def edit_colors(edits: Sequence[FieldEdit], x: Tensor, c: Tensor) -> Tensor:
    """Colours c [N, 3] of points x [N, 3] after the colour ops of `edits`, in order."""
    for e in edits:
        if e.op not in ("recolor", "retexture", "sketch"):
            continue
        inside = e.extent.contains(x)  # [N]
        if not bool(inside.any()):
            continue
        xi, ci = x[inside], c[inside]
        if e.op == "retexture":
            new = _texture_at(e, xi).to(c.dtype)  # [M, 3]
        else:
            new = e.color.to(c.dtype).expand(len(xi), 3)  # type: ignore[union-attr]
        if e.op != "sketch" and e.ref_lum is not None:
            shade = (luminance(ci) / max(e.ref_lum, 1e-3)).clamp(0.0, MAX_SHADE)  # [M]
            new = new * shade[:, None]
        ci = (1.0 - e.strength) * ci + e.strength * new.clamp(0.0, 1.0)
        c = c.clone()
        c[inside] = ci
    return c


def _texture_at(e: FieldEdit, x: Tensor) -> Tensor:
    """The texel (nearest) under points x [M, 3]: the texture stretched over the extent's
    bounding box in plan coordinates, image row 0 at the highest y. Returns [M, 3]."""
    tex = e.texture  # [Ht, Wt, 3]
    assert tex is not None
    ht, wt = tex.shape[:2]
    x0, y0, x1, y1 = e.extent.bbox()
    u = (x[:, 0].double() - x0) / (x1 - x0)  # [M] 0 at x_min
    v = (y1 - x[:, 1].double()) / (y1 - y0)  # [M] 0 at y_max
    col = torch.floor(u * wt).long().clamp(0, wt - 1)
    row = torch.floor(v * ht).long().clamp(0, ht - 1)
    return tex[row, col]


def wrap_field(field: FieldFns, edits: Sequence[FieldEdit]) -> FieldFns:
    """The field's functions with the edits applied: `remove` zeroes the density inside its
    extent, the colour ops change the colour there; the logits are left as they are."""
    removes = [e for e in edits if e.op == "remove"]
    paints = [e for e in edits if e.op in ("recolor", "retexture", "sketch")]
    if not removes and not paints:
        return field

    def removed(x: Tensor, sigma: Tensor) -> Tensor:
        for e in removes:
            sigma = torch.where(e.extent.contains(x), torch.zeros_like(sigma), sigma)  # type: ignore[arg-type]
        return sigma

    def sigma(x: Tensor) -> Tensor:
        return removed(x, field.sigma(x))  # [N]

    def query(x: Tensor, dirs: Tensor | None) -> FieldOut:
        f = field.query(x, dirs)
        rgb = f.rgb if f.rgb is None or not paints else edit_colors(paints, x, f.rgb)
        return FieldOut(rgb, removed(x, f.sigma), f.logits)

    return FieldFns(sigma, query)


def vertex_colors(mesh: trimesh.Trimesh) -> np.ndarray | None:
    """The mesh's per-vertex RGBA uint8 [V, 4], or None when it has no vertex colours."""
    vis = mesh.visual
    if isinstance(vis, trimesh.visual.ColorVisuals) and vis.kind == "vertex":
        return np.asarray(vis.vertex_colors, np.uint8)
    return None


def edit_mesh(mesh: trimesh.Trimesh, edits: Sequence[FieldEdit]) -> tuple[trimesh.Trimesh, dict]:
    """The mesh with the edits applied: vertex colours changed by the colour ops (in order),
    then the faces whose centroid lies inside a removed extent dropped. Returns the new mesh
    and counts."""
    v = np.asarray(mesh.vertices, np.float64)  # [V, 3]
    rgba = vertex_colors(mesh)  # [V, 4]
    if rgba is None:  # no colours to edit: start from a neutral grey
        rgba = np.tile(np.array([NEUTRAL, NEUTRAL, NEUTRAL, 255], np.uint8), (len(v), 1))
    rgba = rgba.copy()
    x = torch.from_numpy(v)
    c = torch.from_numpy(rgba[:, :3].astype(np.float64) / 255.0)
    c_new = edit_colors(edits, x, c).numpy()
    changed = np.any(np.abs(c_new - c.numpy()) > 0, axis=1)
    rgba[:, :3] = np.round(np.clip(c_new, 0, 1) * 255).astype(np.uint8)
    faces = np.asarray(mesh.faces)
    keep = np.ones(len(faces), bool)
    if len(faces):
        centroids = v[faces].mean(axis=1)  # [F, 3]
        for e in edits:
            if e.op == "remove":
                keep &= ~np.asarray(e.extent.contains(centroids))
    out = trimesh.Trimesh(v, faces[keep], vertex_colors=rgba, process=False)
    out.remove_unreferenced_vertices()
    stats = {
        "vertices_recolored": int(changed.sum()),
        "faces_removed": int((~keep).sum()),
        "faces_left": int(keep.sum()),
    }
    return out, stats

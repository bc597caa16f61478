"""The edited view: one owner for what an edit looks like from a camera.

`EditedView` holds a trained field and the fused mesh, loaded once, resolves each edit of a
spec once (its 3-D extent, reference luminance and ground fill), and renders any camera with
the edits applied: the field edits wrap the field (`stages.edit.ops.wrap_field`), and each
mask edit's selection is blended half with MASK_TINT, the selections being those of the
unedited scene (a removed object keeps its mask). The edit stage's before | after pictures
and orbit GIF, `blunf render`, the studio and the preview bench all render through it.
"""

from __future__ import annotations

import pickle
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy import ndimage

from stages.common.blueprint import Blueprint
from stages.common.camera import Intrinsics
from stages.common.errors import BlunfError
from stages.common.io import read_image
from stages.common.radiance.field import RadianceField, load_field
from stages.common.threads import torch_threads
from stages.edit.config import EditConfig
from stages.edit.ops import FieldEdit, field_color, field_luminance, vertex_colors
from stages.edit.render import render_view_edited
from stages.edit.select import Extent, extent_of, select_cells
from stages.edit.spec import Edit
from stages.edit.surface import SurfaceRenderer

MASK_TINT = np.array([1.0, 0.0, 1.0])  # mask edits: selected pixels blended half with magenta
REF_POINTS = 20000  # surface points at most whose field colour sets a selection's reference
FILL_RING = 0.2  # metres round a removed footprint whose fused floor's colour fills under it


def load_model(path: Path) -> RadianceField:
    """A trained field (model.pt), or a one-line error naming the file."""
    try:
        return load_field(path)
    except pickle.UnpicklingError as e:  # load_field does not catch this one
        raise BlunfError(f"{path}: not a NeRF model ({e.__class__.__name__})") from None


def load_mesh(path: Path) -> trimesh.Trimesh:
    """A fused mesh (mesh.ply, vertices unprocessed), or a one-line error naming the file."""
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on a broken file
        raise BlunfError(f"{path}: not a readable mesh ({e.__class__.__name__})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise BlunfError(f"{path}: the mesh has no vertices")
    return mesh


def scaled(intr: Intrinsics, s: float) -> Intrinsics:
    """The camera at `s` times its resolution (edit.render.scale, edit.gif.scale, a preview)."""
    if s == 1.0:
        return intr
    return intr.scaled(max(1, round(intr.width * s)), max(1, round(intr.height * s)))


def tint(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """rgb [H, W, 3] in [0, 1] with the pixels of mask [H, W] blended half with MASK_TINT."""
    return np.where(mask[..., None], 0.5 * rgb + 0.5 * MASK_TINT, rgb)


def to_u8(rgb: np.ndarray) -> np.ndarray:
    """rgb in [0, 1] -> uint8 (rounded)."""
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def ground_fill(
    cfg: EditConfig,
    e: Edit,
    ext: Extent,
    comps: list[dict],
    verts: np.ndarray,
    colors: np.ndarray | None,
    model,
) -> torch.Tensor | None:
    """A removal's ground fill: the median colour of the fused floor (|z| <= floor_band) in a
    FILL_RING band round the footprint, from the mesh's vertex colours `colors` [V, 3] (what
    the photos showed there), or from the field when the mesh has none. None for other ops,
    for a removal of floor itself, and when no floor surrounds the footprint."""
    if e.op != "remove" or any(c["class"] == cfg.select.floor_class for c in comps):
        return None
    grow = max(1, round(FILL_RING / ext.grid.cell))
    ring = ndimage.binary_dilation(ext.footprint, iterations=grow) & ~ext.footprint  # [H, W]
    band = cfg.select.floor_band
    ring_ext = Extent(ext.grid, np.where(ring, -band, np.inf).astype(np.float32),
                      np.where(ring, band, -np.inf).astype(np.float32))  # fmt: skip
    on = ring_ext.contains(verts)  # [V] fused floor round the footprint
    if not on.any():
        return None
    if colors is not None:
        return torch.from_numpy(np.median(colors[on], axis=0).astype(np.float32))
    return field_color(model.fns(semantics=False), verts[on], REF_POINTS)


@dataclass(frozen=True)
class Resolved:
    """One edit of a spec as it wraps the field, and the plan components it selected."""

    edit: FieldEdit
    components: list[dict]  # the selection's plan components (id, class, ...)


@dataclass
class Picture:
    """One rendered view."""

    rgb: np.ndarray  # [H, W, 3] in [0, 1]: field edits applied, mask edits tinted
    field_rgb: np.ndarray  # [H, W, 3] the same before the tint (the field edits alone)
    depth: np.ndarray  # [H, W] float32 metres along the optical axis; inf: no surface
    masks: np.ndarray  # [M, H, W] bool selections in the unedited scene: of every edit for a
    #                    `before` picture, of the mask edits for an edited one
    renders: int  # field renders it took
    seconds: float
    volume_rendered: float | None  # fast path: the fraction of rays volume rendered

    @property
    def image(self) -> np.ndarray:
        """rgb as uint8 [H, W, 3]."""
        return to_u8(self.rgb)


class EditedView:
    """A field and its fused mesh with a plan's edits: `render(pose, intr, edits, fast)`."""

    def __init__(
        self,
        cfg: EditConfig,
        model: RadianceField | None,
        mesh: trimesh.Trimesh,
        bp: Blueprint,
        cmap: np.ndarray,
        cast: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        """`model` None: a run without a field (resolve and render fail with one line);
        `cast`: the (vertices, faces) the fast path ray-casts (default: the mesh's)."""
        self.cfg, self.model, self.mesh, self.bp, self.cmap = cfg, model, mesh, bp, cmap
        self.verts = np.asarray(mesh.vertices, np.float64)  # [V, 3]
        rgba = vertex_colors(mesh)  # [V, 4] or None
        self.colors = None if rgba is None else rgba[:, :3].astype(np.float64) / 255.0  # [V, 3]
        self.cast = cast or (np.asarray(mesh.vertices), np.asarray(mesh.faces))
        self._resolved: dict[tuple, Resolved] = {}
        self._surface: SurfaceRenderer | None = None  # the fast path, made on first use

    @classmethod
    def load(cls, cfg: EditConfig, model: Path | None, mesh: Path, bp: Blueprint,
             cmap: np.ndarray) -> EditedView:  # fmt: skip
        """From the files: model.pt (None: no field) and mesh.ply."""
        return cls(cfg, None if model is None else load_model(model), load_mesh(mesh), bp, cmap)

    def _field(self) -> RadianceField:
        if self.model is None:
            raise BlunfError("edit: no trained NeRF to render")
        return self.model

    def resolve(self, e: Edit, sel: np.ndarray | None = None) -> Resolved:
        """The edit as it wraps the field (once per edit: a texture replaced under the same
        name is read again). `sel`: its plan cells, when already selected."""
        # the texture file's time and size too: an upload under a name used before replaces
        # the file, and the edit must see the new picture
        tex = None if e.texture is None else Path(e.texture)
        stamp = (tex.stat().st_mtime_ns, tex.stat().st_size) if tex and tex.is_file() else None
        key = (e.op, e.select.kind, repr(e.select.value), e.select.width, e.color, e.strength,
               str(e.texture), stamp)  # fmt: skip
        if key not in self._resolved:
            model = self._field()
            if sel is None:
                sel = select_cells(e.select, self.bp, self.cmap)
            ext, comps = extent_of(sel, self.bp, self.cmap, self.verts, self.cfg)
            inside = self.verts[ext.contains(self.verts)]  # [M, 3] fused surface inside
            ref = field_luminance(model.fns(semantics=False), inside, REF_POINTS)
            fill = ground_fill(self.cfg, e, ext, comps, self.verts, self.colors, model)
            self._resolved[key] = Resolved(_field_edit(e, ext, ref, fill), comps)
        return self._resolved[key]

    def surface(self) -> SurfaceRenderer:
        """The fast path's renderer (`stages.edit.surface`) over `cast`, made once."""
        if self._surface is None:
            self._surface = SurfaceRenderer(self._field(), *self.cast)
        return self._surface

    def _draw(self, pose, intr, ops, masks, fast: bool) -> dict[str, np.ndarray]:
        if fast:
            return self.surface().render_view(pose, intr, ops, masks, self.cfg.render.chunk)
        return render_view_edited(self._field(), pose, intr, ops, self.cfg.render.chunk, masks)

    def _edits(self, edits: Sequence[Edit | FieldEdit]) -> list[FieldEdit]:
        return [self.resolve(e).edit if isinstance(e, Edit) else e for e in edits]

    def before(self, pose: np.ndarray, intr: Intrinsics, edits: Sequence[Edit | FieldEdit] = (),
               fast: bool | None = None) -> Picture:  # fmt: skip
        """The unedited view and every edit's selection in it ([E, H, W] masks)."""
        t0 = time.perf_counter()
        eds = self._edits(edits)
        fast = self.cfg.render.path == "surface" if fast is None else fast
        with torch_threads(self.cfg.render.threads):
            res = self._draw(pose, intr, [], [e.extent for e in eds], fast)
        sel = res["masks"] >= self.cfg.render.mask_threshold
        return _picture(res, res["rgb"], sel, 1, t0, fast)

    def render(
        self,
        pose: np.ndarray,
        intr: Intrinsics,
        edits: Sequence[Edit | FieldEdit] = (),
        fast: bool | None = None,
        unedited: Picture | None = None,
    ) -> Picture:
        """The view with `edits` applied. `fast`: through the cast mesh's ray cast, the
        field asked at its hits (`stages.edit.surface`), instead of the volume render (None:
        as edit.render.path says). `unedited`: the `before` picture of the same view and edits,
        whose selections (and, without field edits, rgb) are used instead of rendered."""
        t0 = time.perf_counter()
        eds = self._edits(edits)
        fast = self.cfg.render.path == "surface" if fast is None else fast
        field_ops = [e for e in eds if e.op != "mask"]
        shown = [i for i, e in enumerate(eds) if e.op == "mask"]
        thr = self.cfg.render.mask_threshold
        res, renders = None, 0
        with torch_threads(self.cfg.render.threads):
            ext = [eds[i].extent for i in shown]
            if field_ops or unedited is None:
                res = self._draw(pose, intr, field_ops, [] if field_ops else ext, fast)
                renders += 1
            if unedited is not None:
                sel = unedited.masks[shown]
            elif field_ops and ext:  # masks are those of the unedited scene
                sel = self._draw(pose, intr, [], ext, fast)["masks"] >= thr
                renders += 1
            else:
                assert res is not None
                sel = res["masks"] >= thr
        base = unedited if res is None else _picture(res, res["rgb"], sel, renders, t0, fast)
        assert base is not None
        rgb = base.field_rgb
        for m in sel:
            rgb = tint(rgb, m)
        return replace(base, rgb=rgb, masks=sel, renders=renders, seconds=time.perf_counter() - t0)


def _picture(res: dict, rgb: np.ndarray, sel: np.ndarray, renders: int, t0: float,
             fast: bool) -> Picture:  # fmt: skip
    # per render, not the renderer's: each studio tab renders on its own thread
    share = float(res["fallback"].mean()) if fast else None
    depth = np.where(res["acc"] >= 0.5, res["depth"], np.inf).astype(np.float32)
    return Picture(rgb, rgb, depth, sel, renders, time.perf_counter() - t0, share)


def _field_edit(
    e: Edit, ext: Extent, ref: float | None, fill: torch.Tensor | None = None
) -> FieldEdit:
    color = None if e.color is None else torch.tensor(e.color, dtype=torch.float32) / 255.0
    tex = None
    if e.texture is not None:
        tex = torch.from_numpy(read_image(e.texture).astype(np.float32) / 255.0)  # [Ht, Wt, 3]
    return FieldEdit(e.op, ext, color, e.strength, tex, ref, fill)

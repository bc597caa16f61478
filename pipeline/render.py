"""`blunf render`: one view of a run's NeRF with edits applied, and the studio's engine.

A run folder is read through its report.json: the plan (blueprint.npz), the fused mesh and
the posed frames of the stages it ran, and the trained field when the nerf stage ran. Edits
are resolved exactly as the edit stage resolves them (`stages.edit.nerf.resolve_edit`) and
rendered through the same function (`render_view_edited`), so a view rendered here equals the
edit stage's render of that view with the same spec.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.common.blueprint import Blueprint
from stages.common.camera import Intrinsics, check_pose
from stages.common.capture import Capture
from stages.common.components import component_map, components
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.edit.config import EditConfig
from stages.edit.select import select_cells
from stages.edit.spec import Edit

if TYPE_CHECKING:
    from stages.edit.surface import SurfaceRenderer

TRAIN_HINT = (
    "blunf run CAPTURE --out {run} --config configs/edit-fast.yaml --edits {run}/studio/studio.yaml"
)


@dataclass(frozen=True)
class RunFiles:
    """What a run folder holds for rendering: found through its report.json."""

    run: Path
    capture: Path  # the capture the run was made from
    blueprint: Path
    mesh: Path
    frames: Path  # frames.json with poses and intrinsics (the edit stage's frames)
    model: Path | None  # model.pt of the nerf stage; None when the run trained no field
    edit: dict  # the run's edit settings (config.edit)


RENDER_BYTES = 256  # per pixel of a render: its rays' samples, chunked, and the float images


def run_files(run: Path) -> RunFiles:
    """The files of a finished run, or a one-line error naming what is missing."""
    run = Path(run)
    rep = run / "report.json"
    if not run.is_dir():
        raise BlunfError(f"{run}: not a folder")
    if not rep.is_file():
        raise BlunfError(f"{run}: not a run folder (no report.json; make one with blunf run)")
    try:
        report = read_json(rep)
        stages = {s["name"]: s for s in report["stages"] if s.get("key")}
        capture = Path(report["capture"])
        edit_cfg = dict(report.get("config", {}).get("edit", {}))
    except (BlunfError, KeyError, TypeError) as e:
        raise BlunfError(f"{rep}: not a run report ({e})") from None

    def stage_file(name: str, file: str) -> Path | None:
        s = stages.get(name)
        p = None if s is None else run / name / s["key"] / file
        return p if p is not None and p.is_file() else None

    frames = stage_file("semantics", "frames.json") or stage_file("fusion", "frames.json")
    mesh = stage_file("fusion", "mesh.ply")
    bp = run / "blueprint.npz"
    for what, p in (("frames.json", frames), ("mesh.ply", mesh), ("blueprint.npz", bp)):
        if p is None or not p.is_file():
            raise BlunfError(f"{run}: the run has no {what} (was it finished or cleaned?)")
    model = stage_file("nerf", "model.pt") or stage_file("depth", "model.pt")
    assert frames is not None and mesh is not None
    return RunFiles(run, capture, bp, mesh, frames, model, edit_cfg)


def edit_config(d: dict) -> EditConfig:
    """The run's edit settings (unknown keys of another version dropped)."""
    known = set(EditConfig.__dataclass_fields__)
    return EditConfig(**{k: v for k, v in d.items() if k in known})


def camera_json(path: Path) -> tuple[np.ndarray, Intrinsics]:
    """A camera file: {"pose": 4x4 camera-to-world (OpenCV axes), "intrinsics": {fx, fy, cx,
    cy, width, height}}."""
    try:
        d = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise BlunfError(f"{path}: camera file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BlunfError(f"{path}: not a JSON camera file ({e.__class__.__name__})") from None
    if not isinstance(d, dict) or "pose" not in d or "intrinsics" not in d:
        raise BlunfError(f"{path}: a camera file holds 'pose' (4x4) and 'intrinsics'")
    pose = check_pose(d["pose"], f"{path}: pose")
    if not isinstance(d["intrinsics"], dict):
        raise BlunfError(f"{path}: intrinsics: must map fx, fy, cx, cy, width, height")
    return pose, Intrinsics.from_json(d["intrinsics"], f"{path}: intrinsics")


def viewer_camera(
    position: Sequence[float] | np.ndarray,
    wxyz: Sequence[float] | np.ndarray,
    fov: float,
    aspect: float,
    height: int,
) -> tuple[np.ndarray, Intrinsics]:
    """A web viewer's camera (position, rotation quaternion w x y z of camera-to-world in
    OpenCV axes, vertical field of view in radians, width / height) as a camera-to-world pose
    and pinhole intrinsics `height` pixels high."""
    w, x, y, z = (float(v) for v in wxyz)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    if not np.isfinite(n) or n == 0 or not 0 < fov < np.pi or not aspect > 0:
        raise BlunfError(f"viewer camera: bad rotation {wxyz}, fov {fov} or aspect {aspect}")
    w, x, y, z = w / n, x / n, y / n, z / n
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = np.asarray(position, np.float64)
    h = max(1, int(height))
    wd = max(1, round(h * aspect))
    f = 0.5 * h / np.tan(0.5 * fov)
    return pose, Intrinsics(f, f, wd / 2 - 0.5, h / 2 - 0.5, wd, h)


def pose_wxyz(pose: np.ndarray) -> np.ndarray:
    """The rotation of a camera-to-world pose as a unit quaternion (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(pose)[:3, :3]).as_quat()
    return np.array([w, x, y, z])


def scaled(intr: Intrinsics, s: float) -> Intrinsics:
    """The camera at `s` times its resolution (as the edit stage's render_scale)."""
    if s == 1.0:
        return intr
    return intr.scaled(max(1, round(intr.width * s)), max(1, round(intr.height * s)))


@dataclass
class Rendered:
    rgb: np.ndarray  # [H, W, 3] uint8
    seconds: float
    volume_rendered: float | None = None  # fast path: the fraction of rays volume rendered
    depth: np.ndarray | None = None  # [H, W] metres along the optical axis; inf: no surface


class Scene:
    """A run loaded once for rendering edits: plan, components, mesh, frames and field."""

    def __init__(self, files: RunFiles):
        import torch  # noqa: F401  (the field's loader; imported late: the CLI starts fast)

        from stages.edit.nerf import _load_mesh, _load_model
        from stages.edit.ops import vertex_colors

        self.files = files
        self.cfg = edit_config(files.edit)
        self.bp = Blueprint.load(files.blueprint)
        self.cmap = component_map(self.bp)
        self.components = {c["id"]: c for c in components(self.bp)}
        self.cap = Capture.load(files.frames)
        self.mesh = _load_mesh(files.mesh)
        self.verts = np.asarray(self.mesh.vertices, np.float64)
        rgba = vertex_colors(self.mesh)
        self.colors = None if rgba is None else rgba[:, :3].astype(np.float64) / 255.0
        self.model = None if files.model is None else _load_model(files.model)
        self._resolved: dict[tuple, object] = {}
        self._surface: SurfaceRenderer | None = (
            None  # the fast path (stages.edit.surface), made on first use
        )

    @property
    def has_field(self) -> bool:
        return self.model is not None

    def view(self, n: int) -> tuple[np.ndarray, Intrinsics]:
        """Input view n's pose and intrinsics."""
        if not 0 <= n < len(self.cap.frames) or self.cap.frames[n].pose is None:
            raise BlunfError(
                f"{self.files.frames}: view {n} does not exist or has no pose "
                f"({len(self.cap.frames)} views, 0..{len(self.cap.frames) - 1})"
            )
        f = self.cap.frames[n]
        return np.asarray(f.pose, np.float64), f.intrinsics

    def selection(self, e: Edit) -> np.ndarray:
        """The plan cells an edit selects (one-line error when none)."""
        return select_cells(e.select, self.bp, self.cmap)

    def _field_edit(self, e: Edit):
        from stages.edit.nerf import resolve_edit

        # the texture file's time and size too: an upload under a name used before replaces
        # the file, and the edit must see the new picture
        tex = None if e.texture is None else Path(e.texture)
        stamp = (tex.stat().st_mtime_ns, tex.stat().st_size) if tex and tex.is_file() else None
        key = (e.op, e.select.kind, repr(e.select.value), e.select.width, e.color, e.strength,
               str(e.texture), stamp)  # fmt: skip
        if key not in self._resolved:
            sel = self.selection(e)
            self._resolved[key] = resolve_edit(
                self.cfg, e, sel, self.bp, self.cmap, self.verts, self.colors, self.model
            )
        return self._resolved[key]

    def surface(self) -> SurfaceRenderer:
        """The fast path's renderer (`stages.edit.surface`), made once."""
        from stages.edit.surface import SurfaceRenderer

        if self.model is None:
            raise BlunfError(f"{self.files.run}: the run has no trained NeRF to render")
        if self._surface is None:
            self._surface = SurfaceRenderer(self.model, self.verts, np.asarray(self.mesh.faces))
        return self._surface

    def render(
        self,
        pose: np.ndarray,
        intr: Intrinsics,
        edits: Sequence[Edit] = (),
        before: bool = False,
        fast: bool = False,
    ) -> Rendered:
        """The view with `edits` applied (none when `before`), as the edit stage's `after`
        picture: field edits rendered, mask selections blended half with magenta. `fast`:
        through the fused mesh's ray cast, the field asked at its hits
        (`stages.edit.surface`), instead of the volume render."""
        from stages.common.threads import torch_threads
        from stages.edit.nerf import _overlay, _u8
        from stages.edit.render import render_view_edited

        if self.model is None:
            raise BlunfError(
                f"{self.files.run}: the run has no trained NeRF to render; train one with "
                + TRAIN_HINT.format(run=self.files.run)
            )
        model = self.model
        t0 = time.perf_counter()
        with torch_threads(self.cfg.threads):
            fes = [] if before else [self._field_edit(e) for e in edits]
            field_ops = [fe for fe in fes if fe.op != "mask"]
            masks = [fe.extent for fe in fes if fe.op == "mask"]
            sr = self.surface() if fast else None

            def view(ops: list, ext: list) -> dict[str, np.ndarray]:
                if sr is not None:
                    return sr.render_view(pose, intr, ops, ext)
                return render_view_edited(model, pose, intr, ops, self.cfg.chunk, ext)

            # masks are those of the unedited scene, as the edit stage draws them
            res = view(field_ops, [] if field_ops else masks)
            if masks and field_ops:
                res["masks"] = view([], masks)["masks"]
            rgb = res["rgb"]
            for k in range(len(masks)):
                rgb = _overlay(rgb, res["masks"][k] >= self.cfg.mask_threshold)
        # per render, not the renderer's: each studio tab renders on its own thread
        share = float(res["fallback"].mean()) if sr is not None else None
        depth = np.where(res["acc"] >= 0.5, res["depth"], np.inf)
        return Rendered(_u8(rgb), time.perf_counter() - t0, share, depth.astype(np.float32))


def render_command(run: Path, view: int | None, camera: Path | None, spec: Path | None,
                   scale: float, out: Path, fast: bool = False) -> dict:  # fmt: skip
    """`blunf render`: write one (edited) view as a PNG; returns what was done. `fast`:
    through the fused mesh's ray cast (`stages.edit.surface`), not the volume render."""
    from stages.common.io import write_image
    from stages.edit.spec import load_spec

    if (view is None) == (camera is None):
        raise BlunfError("render: give exactly one of --view N and --camera FILE")
    if not 0 < scale <= 4:
        raise BlunfError(f"render: --scale must be in (0, 4], got {scale}")
    edits = load_spec(spec).edits if spec is not None else ()
    if camera is not None:  # a bad camera file or size fails before the run is read
        pose, intr = camera_json(camera)
        _check_size(scaled(intr, scale))
    files = run_files(run)
    if files.model is None:
        raise BlunfError(
            f"{run}: the run has no trained NeRF; train one with " + TRAIN_HINT.format(run=run)
        )
    scene = Scene(files)
    if view is not None:
        pose, intr = scene.view(view)
    intr = scaled(intr, scale)
    _check_size(intr)
    for e in edits:  # a selection off the plan fails before any render
        scene.selection(e)
    scene.render(pose, scaled(intr, 0.125), edits, fast=fast)  # warm-up: resolves the edits
    r = scene.render(pose, intr, edits, fast=fast)
    write_image(out, r.rgb)
    res = {"out": str(out), "size": [intr.width, intr.height], "seconds": round(r.seconds, 3),
           "path": "fast" if fast else "volume"}  # fmt: skip
    if fast:
        res["volume_rendered"] = round(r.volume_rendered or 0.0, 4)
    return res


def _check_size(intr: Intrinsics) -> None:
    from stages.common.memory import check_memory

    check_memory(intr.width * intr.height * RENDER_BYTES, f"render: {intr.width}x{intr.height}")

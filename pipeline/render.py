"""`blunf render`: one view of a run's NeRF with edits applied, and the studio's engine.

A run folder is read through its report.json: the plan (blueprint.npz), the fused mesh and
the posed frames of the stages it ran, and the trained field when the nerf stage ran. Edits
are resolved and rendered by the edit stage's own view (`stages.edit.view.EditedView`), so a
view rendered here equals the edit stage's render of that view with the same spec.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import recorded
from stages.common.blueprint import Blueprint
from stages.common.camera import Intrinsics, check_pose
from stages.common.capture import Capture
from stages.common.components import component_map, components
from stages.common.errors import BlunfError
from stages.common.io import read_json
from stages.edit.config import EditConfig
from stages.edit.select import select_cells
from stages.edit.spec import Edit

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
    model = stage_file("nerf", "model.pt") or stage_file("depth", "field/model.pt")
    assert frames is not None and mesh is not None
    return RunFiles(run, capture, bp, mesh, frames, model, edit_cfg)


def edit_config(d: dict) -> EditConfig:
    """The run's edit settings as this version reads them (`pipeline.config.recorded`: the
    flat keys of earlier versions moved to their place, unknown keys dropped)."""
    return recorded(EditConfig, d, "report.json", "edit")


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


@dataclass
class Rendered:
    rgb: np.ndarray  # [H, W, 3] uint8
    seconds: float
    volume_rendered: float | None = None  # fast path: the fraction of rays volume rendered
    depth: np.ndarray | None = None  # [H, W] metres along the optical axis; inf: no surface


class Scene:
    """A run loaded once for rendering edits: plan, components, frames and the edited view
    (`stages.edit.view.EditedView`: fused mesh, field, resolved edits)."""

    def __init__(self, files: RunFiles):
        from stages.edit.view import EditedView

        self.files = files
        self.cfg = edit_config(files.edit)
        self.bp = Blueprint.load(files.blueprint)
        self.cmap = component_map(self.bp)
        self.components = {c["id"]: c for c in components(self.bp)}
        self.cap = Capture.load(files.frames)
        self.edited = EditedView.load(self.cfg, files.model, files.mesh, self.bp, self.cmap)
        self.verts, self.colors = self.edited.verts, self.edited.colors

    @property
    def has_field(self) -> bool:
        return self.edited.model is not None

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

    def render(
        self,
        pose: np.ndarray,
        intr: Intrinsics,
        edits: Sequence[Edit] = (),
        before: bool = False,
        fast: bool = False,
    ) -> Rendered:
        """The view with `edits` applied (none when `before`), as the edit stage's `after`
        picture (`EditedView.render`). `fast`: through the fused mesh's ray cast, the field
        asked at its hits (`stages.edit.surface`), instead of the volume render."""
        if not self.has_field:
            raise BlunfError(
                f"{self.files.run}: the run has no trained NeRF to render; train one with "
                + TRAIN_HINT.format(run=self.files.run)
            )
        p = self.edited.render(pose, intr, () if before else edits, fast)
        return Rendered(p.image, p.seconds, p.volume_rendered, p.depth)


def render_command(run: Path, view: int | None, camera: Path | None, spec: Path | None,
                   scale: float, out: Path, fast: bool = False) -> dict:  # fmt: skip
    """`blunf render`: write one (edited) view as a PNG; returns what was done. `fast`:
    through the fused mesh's ray cast (`stages.edit.surface`), not the volume render."""
    from stages.common.io import write_image
    from stages.edit.spec import load_spec
    from stages.edit.view import scaled

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

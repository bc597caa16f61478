"""The synthetic room of the fusion, align and Manhattan tests, rendered exactly.

The room (z up, floor at z = 0): floor 4 x 3 m, four walls 2.5 m high, a counter against the
north wall and a box on the floor, seen by 8 cameras at 64x48 whose depth is ray-cast from the
exact triangles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c

from stages.common.camera import Intrinsics, pixel_grid
from stages.common.capture import Capture, Frame
from stages.common.io import write_depth_png, write_image
from stages.fusion import IMPLS, FusionConfig, FusionInputs

W, H = 64, 48
INTR = Intrinsics(48.0, 48.0, 31.5, 23.5, W, H)
VOXEL = 0.04


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Closed axis-aligned box: vertices [8, 3], triangles [12, 3]."""
    m = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
    return np.asarray(m.vertices) + lo, np.asarray(m.triangles)


def _quad(a, b, c, d) -> tuple[np.ndarray, np.ndarray]:
    return np.array([a, b, c, d], np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def room_triangles(ceiling: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The room: vertices [V, 3] float32 and triangles [T, 3] uint32."""
    X, Y, Z = 4.0, 3.0, 2.5
    parts = [
        _quad((0, 0, 0), (X, 0, 0), (X, Y, 0), (0, Y, 0)),  # floor
        _quad((0, 0, 0), (X, 0, 0), (X, 0, Z), (0, 0, Z)),  # south wall y = 0
        _quad((0, Y, 0), (X, Y, 0), (X, Y, Z), (0, Y, Z)),  # north wall y = 3
        _quad((0, 0, 0), (0, Y, 0), (0, Y, Z), (0, 0, Z)),  # west wall x = 0
        _quad((X, 0, 0), (X, Y, 0), (X, Y, Z), (X, 0, Z)),  # east wall x = 4
        _box((0.0, 2.4, 0.0), (1.6, 3.0, 0.9)),  # counter against the north wall
        _box((2.4, 0.8, 0.0), (3.0, 1.3, 0.7)),  # a box on the floor
    ]
    if ceiling:
        parts.append(_quad((0, 0, Z), (X, 0, Z), (X, Y, Z), (0, Y, Z)))
    verts, tris, n = [], [], 0
    for v, t in parts:
        verts.append(v)
        tris.append(t + n)
        n += len(v)
    return np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.uint32)


def look_at(centre, target) -> np.ndarray:
    """Camera-to-world [4, 4] with OpenCV axes (x right, y down, z forward), world z up."""
    z = np.subtract(target, centre) / np.linalg.norm(np.subtract(target, centre))
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = centre
    return pose


def room_poses() -> list[np.ndarray]:
    """8 cameras 1.3-1.6 m high looking out and down over a 200-degree arc (so their mean up
    leans away from the vertical, as when a user films one side of a room)."""
    poses = []
    for i, a in enumerate(np.radians(np.linspace(-30, 170, 8))):
        c = (2.0 + 0.5 * np.cos(a), 1.5 + 0.4 * np.sin(a), 1.3 + 0.1 * (i % 4))
        t = (2.0 + 2.2 * np.cos(a), 1.5 + 1.6 * np.sin(a), 0.3)
        poses.append(look_at(c, t))
    return poses


def render(scene: o3d.t.geometry.RaycastingScene, pose: np.ndarray) -> tuple[np.ndarray, ...]:
    """Exact depth [H, W] (z along the optical axis, 0 = no hit) and normals [H, W, 3]."""
    uv = pixel_grid(W, H)  # [H, W, 2]; integer = pixel centre
    d_cam = np.stack(
        [(uv[..., 0] - INTR.cx) / INTR.fx, (uv[..., 1] - INTR.cy) / INTR.fy, np.ones((H, W))],
        axis=-1,
    )  # [H, W, 3], camera z = 1
    d = d_cam @ pose[:3, :3].T
    rays = np.concatenate([np.broadcast_to(pose[:3, 3], d.shape), d], axis=-1)
    ans = scene.cast_rays(o3c.Tensor(rays.astype(np.float32)))
    t = ans["t_hit"].numpy()
    return np.where(np.isfinite(t), t, 0.0), ans["primitive_normals"].numpy()


def make_scene(ceiling: bool = False) -> o3d.t.geometry.RaycastingScene:
    v, t = room_triangles(ceiling)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3c.Tensor(v), o3c.Tensor(t))
    return scene


def room_capture(
    folder: Path,
    ceiling: bool = False,
    gravity=None,
    transform=None,
    depth_suffix: str = ".png",
    poses: list[np.ndarray] | None = None,
) -> Path:
    """Render the room into `folder` (images, depth, frames.json) from `poses` (default
    room_poses()). `transform` [4, 4] moves the world (poses become transform @ pose; depth
    maps are camera-frame, unchanged)."""
    scene = make_scene(ceiling)
    folder.mkdir(parents=True, exist_ok=True)
    M = np.eye(4) if transform is None else transform
    frames = []
    for i, pose in enumerate(room_poses() if poses is None else poses):
        depth, normals = render(scene, pose)
        stem = f"v{i:02d}"
        write_image(folder / f"{stem}.png", (128 + 100 * normals).clip(0, 255).astype(np.uint8))
        dpath = folder / f"{stem}{depth_suffix}"
        if depth_suffix == ".npy":
            np.save(dpath, depth.astype(np.float32))
        else:
            write_depth_png(dpath, depth)
        frames.append(Frame(stem, folder / f"{stem}.png", INTR, depth=dpath, pose=M @ pose))
    cap = Capture(folder, tuple(frames), gravity=gravity)
    cap.save(folder / "frames.json")
    return folder / "frames.json"


def fuse(frames: Path, out: Path, **kw):
    out.mkdir(parents=True, exist_ok=True)
    cfg = FusionConfig(voxel=VOXEL, block_resolution=8, **kw)
    return IMPLS["tsdf"](cfg, FusionInputs(frames), out)

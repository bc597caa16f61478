"""Ray casting of a procedural room: camera loop, textured Lambertian views, top-down plan.

Colour is a pure function of the 3D hit point, the part hit and its normal (procedural
value noise + Lambertian shading under fixed directional lights, no specular, no shadows),
so every view of a surface point agrees: a radiance field can fit it exactly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d

from stages.common.blueprint import Blueprint, Grid
from stages.common.camera import Intrinsics, pixel_grid
from stages.common.capture import UNKNOWN
from stages.synth.realism import PLAIN_CELL, Realism, camera_effects, plain_albedo, smooth_floor
from stages.synth.room import CAM_Z, CEILING, CLASSES, FLOOR, WALL, Part, Room

HFOV_DEG = 65.0  # horizontal field of view of the synthetic camera
SKY = (0.55, 0.70, 0.90)  # colour where a ray leaves the room (no ceiling)
AMBIENT = 0.35
LIGHTS = (((0.35, 0.55, 1.0), 0.55), ((-0.7, -0.3, 0.45), 0.35), ((0.6, -0.8, 0.2), 0.15))
# Texture: chosen by counting SIFT features and matches (pycolmap) on 320x240 views. Fine
# smooth noise beat coarse octaves and hashed cells with sharp edges (which also alias).
NOISE_CELL = 0.08  # lattice spacing (metres) of the coarsest noise octave
OCTAVES = 2  # each halves the spacing: the finest is 4 cm
GAIN = 0.65  # amplitude ratio of successive octaves
CONTRAST = 3.0  # stretch of the noise around its mean before clipping to [0, 1]
HUE_CELL = 0.77  # lattice spacing (metres) of the noise mixing in a second hue


def intrinsics_for(width: int, height: int) -> Intrinsics:
    """Pinhole camera of HFOV_DEG, square pixels, principal point at the image centre.

    Pixel centres sit at integer (u, v) (DESIGN.md), so the centre is ((W-1)/2, (H-1)/2).
    """
    f = (width / 2) / math.tan(math.radians(HFOV_DEG) / 2)
    return Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)


@dataclass(frozen=True)
class Hits:
    """First hits of R rays."""

    t: np.ndarray  # [R] float64 distance in units of the direction length (inf = none)
    part: np.ndarray  # [R] int64 index into the tracer's parts (-1 = none)
    normal: np.ndarray  # [R, 3] float64 unit normal of the hit triangle


class Tracer:
    """Embree ray caster over a list of parts (Open3D RaycastingScene, CPU, headless)."""

    def __init__(self, parts: Sequence[Part]) -> None:
        self.parts = tuple(parts)
        # one build thread: the same BVH, so the same hits, on every run
        self.scene = o3d.t.geometry.RaycastingScene(nthreads=1)
        gids = []
        self._buffers = []  # keep the arrays Open3D's tensors view alive with the scene
        for p in self.parts:
            v = np.asarray(p.mesh.vertices, np.float32)  # [V, 3]
            f = np.asarray(p.mesh.faces, np.uint32)  # [F, 3]
            self._buffers += [v, f]
            vt, ft = o3d.core.Tensor.from_numpy(v), o3d.core.Tensor.from_numpy(f)
            gids.append(self.scene.add_triangles(vt, ft))
        self._part_of = np.full(max(gids) + 2, -1, np.int64)  # geometry id -> part index
        self._part_of[np.asarray(gids)] = np.arange(len(gids))
        self.cls = np.array([p.cls for p in self.parts] + [UNKNOWN], np.int64)  # [P + 1]
        self.inst = np.array([p.instance for p in self.parts] + [0], np.int64)  # [P + 1]

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """First hits of rays origins [R, 3] + t * dirs [R, 3] (world, metres)."""
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)  # [R, 6]
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=1)
        t = ans["t_hit"].numpy().astype(np.float64)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        part = np.where(hit, self._part_of[np.where(hit, gid, -1)], -1)
        return Hits(t, part, ans["primitive_normals"].numpy().astype(np.float64))


# ---- procedural texture ----------------------------------------------------------------
_PRIMES = tuple(
    np.uint64(x)
    for x in (0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9, 0x27D4EB2F165667C5)
)


def _mix(h: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser of uint64 keys [N] to uniform float32 in [0, 1) (24 bits)."""
    with np.errstate(over="ignore"):
        h = h ^ (h >> np.uint64(30))
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    return (h >> np.uint64(40)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def value_noise(p: np.ndarray, salt: np.ndarray) -> np.ndarray:
    """Smooth value noise on the unit lattice at points p [N, 3]. Returns float32 [N] in [0, 1]."""
    i = np.floor(p)
    f = (p - i).astype(np.float32)
    s = f * f * (3.0 - 2.0 * f)  # [N, 3] smoothstep weights
    i = np.ascontiguousarray(i.astype(np.int64).T)  # [3, N]
    with np.errstate(over="ignore"):
        # lattice keys of the two corners along each axis: key(i + 1) = key(i) + prime
        k = [[i[a].view(np.uint64) * _PRIMES[a]] for a in range(3)]
        for a in range(3):
            k[a].append(k[a][0] + _PRIMES[a])
        ks = salt.view(np.uint64) * _PRIMES[3]
    sx, sy, sz = s[:, 0], s[:, 1], s[:, 2]
    out = np.zeros(len(p), np.float32)
    for dz in (0, 1):
        yz = []
        for dy in (0, 1):
            kyz = k[1][dy] ^ k[2][dz] ^ ks
            h0, h1 = _mix(k[0][0] ^ kyz), _mix(k[0][1] ^ kyz)
            yz.append(h0 + sx * (h1 - h0))
        out += (sz if dz else 1 - sz) * (yz[0] + sy * (yz[1] - yz[0]))
    return out


def fbm(p: np.ndarray, salt: np.ndarray) -> np.ndarray:
    """OCTAVES of value noise from NOISE_CELL down, gain 0.65. Returns [N] in [0, 1]."""
    total, amp, norm = np.zeros(len(p), np.float32), 1.0, 0.0
    for o in range(OCTAVES):
        total += np.float32(amp) * value_noise(p * (2.0**o / NOISE_CELL), salt + o)
        norm += amp
        amp *= GAIN
    return total / np.float32(norm)


def texture(points: np.ndarray, part: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Albedo at world points [N, 3] of parts [N] with base colours [P, 3]. Returns [N, 3]."""
    salt = part.astype(np.int64) * 7919 + 17
    v = np.clip(0.5 + CONTRAST * (fbm(points, salt) - 0.5), 0.0, 1.0)  # contrast-stretched
    mix = np.clip(0.5 + 2.0 * (value_noise(points / HUE_CELL, salt + 101) - 0.5), 0.0, 1.0)
    b = base[part]  # [N, 3]
    alt = np.clip(1.15 - b, 0.05, 0.95) * 0.5 + b * 0.5  # a second hue per part
    albedo = b * (1 - 0.45 * mix[:, None]) + alt * (0.45 * mix[:, None])
    return albedo * (0.35 + 0.9 * v)[:, None]


def _plain(
    pts: np.ndarray, part: np.ndarray, base: np.ndarray, cls: np.ndarray, albedo: np.ndarray
) -> np.ndarray:
    """`albedo` [N, 3] with walls and ceilings plain and floors smooth (realism.py)."""
    out = albedo.copy()
    salt = part.astype(np.int64) * 7919 + 17
    c = cls[part]
    flat = (c == WALL) | (c == CEILING)
    if flat.any():
        low = value_noise(pts[flat] / PLAIN_CELL, salt[flat] + 203)
        out[flat] = plain_albedo(base[part[flat]], low)
    fl = c == FLOOR
    if fl.any():
        out[fl] = smooth_floor(base[part[fl]], fbm(pts[fl], salt[fl]))
    return out


def shade(normal: np.ndarray) -> np.ndarray:
    """Lambertian irradiance for unit normals [N, 3] under LIGHTS + AMBIENT. Returns [N]."""
    out = np.full(len(normal), AMBIENT)
    for d, k in LIGHTS:
        out += k * np.clip(normal @ (np.asarray(d) / np.linalg.norm(d)), 0.0, None)
    return out


# linear [0, 1] in 4096 steps -> 8-bit display value (gamma 2.2)
_GAMMA = np.round(np.linspace(0.0, 1.0, 4096) ** (1 / 2.2) * 255).astype(np.uint8)


# ---- views -----------------------------------------------------------------------------
@dataclass(frozen=True)
class View:
    """One rendered view."""

    rgb: np.ndarray  # [H, W, 3] uint8
    depth: np.ndarray  # [H, W] float64 metres along the optical axis (0 = no hit)
    label: np.ndarray  # [H, W] uint8 class id (UNKNOWN = no hit)
    instance: np.ndarray  # [H, W] uint8 instance id (0 = floor, wall, ceiling or no hit)
    camera: dict = field(default_factory=dict)  # the camera effects drawn (realism.py)


def render(
    tracer: Tracer,
    pose: np.ndarray,
    intr: Intrinsics,
    textured: bool = True,
    realism: Realism | None = None,
    rng: np.random.Generator | None = None,
) -> View:
    """Ray-cast one pinhole view from a camera-to-world pose [4, 4].

    realism: plain surfaces and the camera's exposure, blur and noise (stages/synth/realism.py),
    drawn from `rng` (needed when a camera effect is on); None = the textured, perfect camera.
    """
    realism = realism or Realism()
    w, h = intr.width, intr.height
    uv = pixel_grid(w, h).reshape(-1, 2)  # [R, 2]
    d_cam = np.stack(
        [(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))], axis=1
    )  # [R, 3], camera z = 1
    dirs = d_cam @ pose[:3, :3].T  # [R, 3]
    origins = np.broadcast_to(pose[:3, 3], dirs.shape)
    hits = tracer.cast(origins, dirs)
    hit = hits.part >= 0
    # direction has unit camera z, so the hit distance *is* the depth along the optical axis
    depth = np.where(hit, hits.t, 0.0)
    rgb = np.tile(np.asarray(SKY), (len(uv), 1))  # [R, 3]
    n = hits.normal[hit]
    n *= -np.sign(np.sum(n * dirs[hit], axis=1, keepdims=True) + 1e-12)  # face the camera
    base = np.array([p.color for p in tracer.parts])  # [P, 3]
    if textured:
        pts = origins[hit] + hits.t[hit, None] * dirs[hit]  # [N, 3]
        albedo = texture(pts, hits.part[hit], base)
        if realism.surfaces == "plain":
            albedo = _plain(pts, hits.part[hit], base, tracer.cls, albedo)
    else:
        albedo = base[hits.part[hit]]
    rgb[hit] = albedo * shade(n)[:, None]
    if realism.camera:
        if rng is None:
            raise ValueError("render: camera effects need a random generator")
        lin, drawn = camera_effects(rgb.reshape(h, w, 3), realism, rng)
        rgb = lin.reshape(-1, 3)
    lin = np.round(np.clip(rgb, 0.0, 1.0) * (len(_GAMMA) - 1)).astype(np.int64)
    return View(
        rgb=_GAMMA[lin].reshape(h, w, 3),
        depth=depth.reshape(h, w),
        label=tracer.cls[hits.part].astype(np.uint8).reshape(h, w),
        instance=tracer.inst[hits.part].astype(np.uint8).reshape(h, w),
        camera=drawn if realism.camera else {},
    )


def look(eye: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenCV axes) at `eye`, heading `yaw`, `pitch` up (radians)."""
    f = np.array(
        [math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)]
    )
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([r, np.cross(f, r), f], axis=1)  # columns: x right, y down, z fwd
    pose[:3, 3] = eye
    return pose


def camera_path(room: Room, views: int, seed: int) -> np.ndarray:
    """Poses [C, 4, 4] on the room's ellipse, each looking across the room, tilted down.

    Height, heading and tilt vary smoothly along the loop (low-frequency sinusoids with
    seeded phases) plus a small per-view jitter; consecutive views are 360/C degrees apart.
    """
    rng = np.random.default_rng([seed, 2, views])
    cx, cy, a, b = room.loop
    ph = rng.uniform(0, 2 * np.pi, 4)
    z_mid, z_amp = (CAM_Z[0] + CAM_Z[1]) / 2, (CAM_Z[1] - CAM_Z[0]) / 2 - 0.03
    poses = []
    for k in range(views):
        th = ph[0] + 2 * np.pi * k / views
        eye = np.array(
            [
                cx + a * math.cos(th),
                cy + b * math.sin(th),
                z_mid + z_amp * math.sin(2 * th + ph[1]) + rng.uniform(-0.03, 0.03),
            ]
        )
        yaw = (
            math.atan2(cy - eye[1], cx - eye[0])
            + math.radians(25) * math.sin(3 * th + ph[2])
            + math.radians(rng.uniform(-2, 2))
        )
        pitch = -math.radians(24 + 6 * math.sin(2 * th + ph[3]) + rng.uniform(-1.5, 1.5))
        poses.append(look(eye, yaw, pitch))
    return np.stack(poses)


def top_down(room: Room, cell: float = 0.02, margin: float = 0.1) -> Blueprint:
    """The ground-truth plan: one vertical ray down through each cell centre.

    Rays start above the walls and ignore the ceiling; a cell gets the class of the first
    surface hit, UNKNOWN (255) when nothing is hit. The grid covers the room with its walls
    plus `margin` metres.
    """
    t = room.wall
    grid = Grid.covering(
        np.array([-t, -t]), np.array([room.size[0] + t, room.size[1] + t]), cell, pad=margin
    )
    tracer = Tracer([p for p in room.parts if p.cls != CEILING])
    xy = grid.centers().reshape(-1, 2)  # [R, 2]
    origins = np.concatenate([xy, np.full((len(xy), 1), room.height + 1.0)], axis=1)
    dirs = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    labels = tracer.cls[tracer.cast(origins, dirs).part].astype(np.uint8).reshape(grid.shape)
    return Blueprint(labels, grid, dict(CLASSES))


def camera_paths(room: Room, views: int, seed: int) -> np.ndarray:
    """Poses [C, 4, 4]: the rectangular room's loop (camera_path); an L's views split
    between its arms' loops, the first half on the first."""
    if not room.loops:
        return camera_path(room, views, seed)
    n = [views // len(room.loops) + (i < views % len(room.loops)) for i in range(len(room.loops))]
    parts = [
        camera_path(replace(room, loop=loop), k, seed + 7919 * i)
        for i, (loop, k) in enumerate(zip(room.loops, n, strict=True))
        if k > 0
    ]
    return np.concatenate(parts)

"""Furniture of the procedural room, built from boxes in a local frame: footprint centred at
the origin, back towards +y."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from stages.common.classes import BED, CABINET, CHAIR, PLANT, SOFA, TABLE


# ---- primitives ------------------------------------------------------------------------
def box_mesh(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> trimesh.Trimesh:
    """Axis-aligned box between the given bounds (local frame)."""
    t = np.eye(4)
    t[:3, 3] = [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]
    return trimesh.creation.box(extents=[x1 - x0, y1 - y0, z1 - z0], transform=t)


def _cylinder(x: float, y: float, r: float, z0: float, z1: float) -> trimesh.Trimesh:
    t = np.eye(4)
    t[:3, 3] = [x, y, (z0 + z1) / 2]
    return trimesh.creation.cylinder(radius=r, height=z1 - z0, sections=32, transform=t)


def _legs(hx: float, hy: float, inset: float, side: float, z1: float) -> list[trimesh.Trimesh]:
    """Four square legs under a rectangle of half extents (hx, hy)."""
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (hx - inset - side / 2), sy * (hy - inset - side / 2)
            out.append(box_mesh(cx - side / 2, cx + side / 2, cy - side / 2, cy + side / 2, 0, z1))
    return out


# ---- furniture, in a local frame: footprint centred at the origin, back towards +y ------
# Each builder returns (parts, footprint half extents (hx, hy) or radius as (r, -1), height).
Built = tuple[list[trimesh.Trimesh], tuple[float, float], float]


def _measure(parts: list[trimesh.Trimesh], round_foot: bool = False) -> Built:
    """Parts with their footprint (symmetric about the origin) and height, from the vertices."""
    v = np.concatenate([m.vertices for m in parts])  # [V, 3]
    if round_foot:
        ext = (float(np.linalg.norm(v[:, :2], axis=1).max()), -1.0)
    else:
        ext = (float(np.abs(v[:, 0]).max()), float(np.abs(v[:, 1]).max()))
    return parts, ext, float(v[:, 2].max())


def build_table(rng: np.random.Generator) -> Built:
    w, d, h = rng.uniform(1.0, 1.6), rng.uniform(0.7, 0.9), rng.uniform(0.72, 0.78)
    parts = [box_mesh(-w / 2, w / 2, -d / 2, d / 2, h - 0.04, h)]
    parts += _legs(w / 2, d / 2, 0.05, 0.05, h - 0.04)
    return _measure(parts)


def build_chair(rng: np.random.Generator) -> Built:
    s, sh, top = rng.uniform(0.42, 0.48), rng.uniform(0.43, 0.47), rng.uniform(0.78, 0.88)
    parts = [
        box_mesh(-s / 2, s / 2, -s / 2, s / 2, sh - 0.04, sh),
        box_mesh(-s / 2, s / 2, s / 2 - 0.04, s / 2, sh, top),
    ]
    parts += _legs(s / 2, s / 2, 0.01, 0.035, sh - 0.04)
    return _measure(parts)


def _sofa(rng: np.random.Generator) -> Built:
    w, d = rng.uniform(1.6, 2.2), rng.uniform(0.8, 0.95)
    seat, back, arm, at = rng.uniform(0.40, 0.45), rng.uniform(0.78, 0.86), 0.6, 0.18
    parts = [
        box_mesh(-w / 2, w / 2, -d / 2, d / 2, 0.0, seat),
        box_mesh(-w / 2, w / 2, d / 2 - 0.22, d / 2, 0.0, back),
        box_mesh(-w / 2, -w / 2 + at, -d / 2, d / 2, 0.0, arm),
        box_mesh(w / 2 - at, w / 2, -d / 2, d / 2, 0.0, arm),
    ]
    # two seat cushions, slightly proud of the base
    mid = 0.01
    parts += [
        box_mesh(-w / 2 + at + 0.02, -mid, -d / 2 + 0.03, d / 2 - 0.24, seat, seat + 0.06),
        box_mesh(mid, w / 2 - at - 0.02, -d / 2 + 0.03, d / 2 - 0.24, seat, seat + 0.06),
    ]
    return _measure(parts)


def _cabinet(rng: np.random.Generator) -> Built:
    w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.4, 0.55), rng.uniform(1.0, 1.9)
    door = 0.015
    y0 = -d / 2 + door  # body front; the doors stand proud of it
    parts = [
        box_mesh(-w / 2, w / 2, y0, d / 2, 0.08, h),
        box_mesh(-w / 2 + 0.03, w / 2 - 0.03, y0 + 0.03, d / 2, 0.0, 0.08),
    ]
    for x0, x1 in ((-w / 2 + 0.02, -0.005), (0.005, w / 2 - 0.02)):
        parts.append(box_mesh(x0, x1, -d / 2, y0, 0.12, h - 0.04))
        hx = x1 - 0.05 if x0 < 0 else x0 + 0.05
        parts.append(
            box_mesh(hx - 0.012, hx + 0.012, -d / 2 - 0.02, -d / 2, h / 2 - 0.1, h / 2 + 0.1)
        )
    return _measure(parts)


def _bed(rng: np.random.Generator) -> Built:
    w, length, h = rng.uniform(1.4, 1.8), rng.uniform(1.9, 2.1), rng.uniform(0.45, 0.55)
    hb = 0.06  # headboard thickness, at the +y end
    y1 = length / 2 - hb
    parts = [
        box_mesh(-w / 2, w / 2, -length / 2, y1, 0.0, h - 0.2),
        box_mesh(-w / 2 + 0.03, w / 2 - 0.03, -length / 2 + 0.03, y1, h - 0.2, h),
        box_mesh(-w / 2, w / 2, y1, length / 2, 0.0, 0.88),
    ]
    for x0, x1 in ((-w / 2 + 0.1, -0.05), (0.05, w / 2 - 0.1)):
        parts.append(box_mesh(x0, x1, y1 - 0.45, y1 - 0.08, h, h + 0.12))
    return _measure(parts)


def _plant(rng: np.random.Generator) -> Built:
    rp, hp, rf = rng.uniform(0.14, 0.22), rng.uniform(0.3, 0.45), rng.uniform(0.28, 0.42)
    foliage = trimesh.creation.icosphere(subdivisions=3, radius=rf)
    foliage.apply_translation([0, 0, hp + 0.85 * rf])
    parts = [_cylinder(0, 0, rp, 0.0, hp), _cylinder(0, 0, rp + 0.02, hp - 0.04, hp), foliage]
    return _measure(parts, round_foot=True)


BUILDERS: dict[int, Callable[[np.random.Generator], Built]] = {
    TABLE: build_table,
    CHAIR: build_chair,
    SOFA: _sofa,
    CABINET: _cabinet,
    BED: _bed,
    PLANT: _plant,
}


def join_meshes(meshes: list[trimesh.Trimesh], colors: np.ndarray | None = None) -> trimesh.Trimesh:
    """One mesh from several, optionally with one RGBA uint8 colour [M, 4] per input mesh."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=False)])
    vc = None if colors is None else np.repeat(colors, np.diff(offsets), axis=0)
    verts = np.concatenate([m.vertices for m in meshes])
    return trimesh.Trimesh(verts, faces, vertex_colors=vc, process=False)

"""Openings read off the mesh along each wall: rays from just inside the room out through the
wall's face at a few heights (Open3D's ray casting). Where no ray meets the wall along a
stretch at least `min_opening` wide, it is a door (up to `door_max` wide) or a passage when a
ray cast down in the wall's middle meets the floor there (the floor runs through), and a
window where the lowest ray meets the wall and the others do not."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from stages.layout.config import LayoutConfig

HEIGHTS = (0.3, 1.0, 1.5)  # metres: the horizontal rays (below a window sill, at and above)
INSET = 0.05  # metres: rays start this far inside the room
BIN = 0.02  # metres: ray spacing along a wall
BEYOND = (0.04, 0.08, 0.12)  # metres beyond the face: where the floor is looked for


def _tensor(a: np.ndarray) -> o3d.core.Tensor:
    return o3d.core.Tensor.from_numpy(np.ascontiguousarray(a))


def scene_of(verts: np.ndarray, tris: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(_tensor(verts.astype(np.float32)), _tensor(tris.astype(np.uint32)))
    return scene


def _runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index pairs (end exclusive) of the True runs of a 1-D mask."""
    d = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0], strict=True))


def mesh_openings(
    walls: list[dict], verts: np.ndarray, tris: np.ndarray, cfg: LayoutConfig
) -> list[dict]:
    """plan.json openings of `walls` (world metres) found in the mesh."""
    scene = scene_of(verts, tris)
    out = []
    for wi, w in enumerate(walls):
        a, b, t = np.asarray(w["start"]), np.asarray(w["end"]), float(w["thickness"])
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        n = np.array([d[1], -d[0]])  # outwards
        s = np.arange(BIN / 2, length, BIN)
        xy = a + s[:, None] * d - n * INSET  # [S, 2]
        rays = np.concatenate(
            [
                np.concatenate([xy, np.full((len(s), 1), h), np.tile([*n, 0.0], (len(s), 1))], 1)
                for h in HEIGHTS
            ]
        ).astype(np.float32)
        hit = scene.cast_rays(_tensor(rays))["t_hit"].numpy().reshape(len(HEIGHTS), -1)
        wall = hit <= INSET + t + 0.05  # [H, S]
        # the floor beyond the face: rays cast down at a few depths into the wall line (a
        # fused threshold has holes: measured half of it on a 30-view room); a wall that the
        # views did not see, behind furniture, has none
        down = np.concatenate(
            [
                np.concatenate(
                    [a + s[:, None] * d + n * off, np.full((len(s), 1), 0.5)]
                    + [np.tile([0, 0, -1.0], (len(s), 1))],
                    1,
                )
                for off in BEYOND
            ]
        ).astype(np.float32)
        floor_t = scene.cast_rays(_tensor(down))["t_hit"].numpy().reshape(len(BEYOND), -1)
        floor = (np.abs(floor_t - 0.5) < 0.08).any(0)
        for kind_of, open_ in (
            ("door", ~wall.any(0)),
            ("window", wall[0] & ~wall[1:].any(0)),
        ):
            for i, j in _runs(open_):
                width = (j - i) * BIN
                if width < cfg.min_opening:
                    continue
                kind = kind_of
                if kind == "door":
                    if floor[i:j].mean() < 0.4:
                        continue
                    kind = "door" if width <= cfg.door_max else "passage"
                p, q = a + (i * BIN) * d, a + (j * BIN) * d
                out.append(
                    {
                        "kind": kind,
                        "wall": wi,
                        "start": np.round(p, 4).tolist(),
                        "end": np.round(q, 4).tolist(),
                        "width": round(width, 4),
                    }
                )
    return out


def ceiling(scene: o3d.t.geometry.RaycastingScene, floor_xy: np.ndarray) -> float | None:
    """Height of the ceiling's underside: the median hit of rays cast up from floor points
    [N, 2] (at least half must meet it), None when there is no ceiling."""
    if len(floor_xy) == 0:
        return None
    rays = np.concatenate(
        [floor_xy, np.full((len(floor_xy), 1), 0.05), np.tile([0, 0, 1.0], (len(floor_xy), 1))], 1
    )
    t = scene.cast_rays(_tensor(rays.astype(np.float32)))["t_hit"].numpy()
    hit = t[np.isfinite(t)]
    return float(0.05 + np.median(hit)) if len(hit) >= max(3, len(t) // 2) else None


def heights(
    scene: o3d.t.geometry.RaycastingScene, xys: list[np.ndarray], ceil: float | None
) -> list[float | None]:
    """Top of the surface over each set of floor points [N, 2]: the 98th percentile of the
    first hits of rays cast down from just under the ceiling (from 5 m without one)."""
    z0 = ceil - 0.02 if ceil is not None else 5.0
    out: list[float | None] = []
    for xy in xys:
        rays = np.concatenate(
            [xy, np.full((len(xy), 1), z0), np.tile([0, 0, -1.0], (len(xy), 1))], 1
        )
        t = scene.cast_rays(_tensor(rays.astype(np.float32)))["t_hit"].numpy()
        t = t[np.isfinite(t)]
        out.append(round(float(np.percentile(z0 - t, 98)), 4) if len(t) else None)
    return out

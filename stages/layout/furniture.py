"""Furniture against a wall that the plan drew as wall: a room outline's notch (a step in
from a straight face and back out to the same line) is a tall cabinet or a wardrobe when the
mesh shows the wall's face on the straight line above it; the outline then runs along the wall
behind it, as the room's walls do, and the furniture stays an object.

A plan class map labels wall what stands at a wall's height near it: the 3-room home's 1.6 m
cabinet against the living room's south wall was drawn as a 0.92 x 0.49 m notch, four corners
the room does not have."""

from __future__ import annotations

import numpy as np
import open3d as o3d

NOTCH_DEPTH = 0.7  # metres: the deepest step a piece of furniture makes in a face
NOTCH_WIDTH = 2.5  # metres: the widest one
ABOVE = 0.25  # metres: the wall is read from this far over the furniture up to this far under
#                the ceiling, every ABOVE
BIN = 0.05  # metres: ray spacing along the notch
REACH = 0.06  # metres: the wall's face must lie this close to the straight face's line
SUPPORT = 0.5  # share of the rays at one height that must meet it


def _line(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = (b - a) / max(float(np.linalg.norm(b - a)), 1e-12)
    return d, np.array([-d[1], d[0]])


def _wall_behind(
    scene: o3d.t.geometry.RaycastingScene,
    p: np.ndarray,
    q: np.ndarray,
    out: np.ndarray,
    depth: float,
    top: float,
    ceil: float,
) -> bool:
    """Whether rays cast outwards (`out`, unit) from the notch's inner face p->q, at heights
    from `top` + ABOVE to ceil - ABOVE, meet a surface facing them `depth` beyond it (within
    REACH) for SUPPORT of them at one height at least."""
    length = float(np.linalg.norm(q - p))
    d = (q - p) / length
    s = np.arange(0.1 * length, 0.9 * length, BIN)
    xy = p + s[:, None] * d - out * 0.05  # from just inside the room
    for h in np.arange(top + ABOVE, ceil - ABOVE + 1e-9, ABOVE):
        rays = np.concatenate([xy, np.full((len(s), 1), h), np.tile([*out, 0.0], (len(s), 1))], 1)
        hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays.astype(np.float32)))
        t = hit["t_hit"].numpy() - 0.05
        facing = (hit["primitive_normals"].numpy()[:, :2] @ out) < 0
        ok = np.isfinite(t) & (np.abs(t - depth) <= REACH) & facing
        if len(ok) and ok.mean() >= SUPPORT:
            return True
    return False


def _top(scene: o3d.t.geometry.RaycastingScene, quad: np.ndarray, ceil: float) -> float:
    """The highest surface over the notch quad [4, 2] (rays down from under the ceiling)."""
    lo, hi = quad.min(0), quad.max(0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 7)[1:-1], np.linspace(lo[1], hi[1], 7)[1:-1])
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    z0 = ceil - 0.02
    rays = np.concatenate([xy, np.full((len(xy), 1), z0), np.tile([0, 0, -1.0], (len(xy), 1))], 1)
    t = scene.cast_rays(o3d.core.Tensor.from_numpy(rays.astype(np.float32)))["t_hit"].numpy()
    t = t[np.isfinite(t)]
    return float(z0 - np.percentile(t, 10)) if len(t) else ceil


def filled_notches(plan: dict, scene: o3d.t.geometry.RaycastingScene, ceil: float | None) -> dict:
    """The plan with each room's furniture notches (see the module) taken out of its outline:
    the notch's three walls and the two faces either side become one wall along the line (the
    first face's thickness, seen when either face was), the room's area grows by the notch."""
    if ceil is None:
        return plan
    walls, rooms = list(plan["walls"]), list(plan["rooms"])
    for ri in range(len(rooms)):
        changed = True
        while changed:
            changed = False
            idx = [i for i, w in enumerate(walls) if w["room"] == ri]
            k = len(idx)
            if k < 8:  # a notch in a rectangle: eight corners
                break
            pts = np.array([walls[i]["start"] for i in idx], np.float64)
            for e in range(k):
                # faces a->b and g->f on one line, the notch b->c->d->g between them
                a, b, c, d, g, f = (pts[(e + m) % k] for m in range(6))
                u, n_in = _line(a, b)  # the face before the notch, the room on its left
                if float(np.linalg.norm(b - a)) < 0.1 or abs((f - a) @ n_in) > 0.02:
                    continue
                if abs((g - a) @ n_in) > 0.02 or float((f - g) @ u) < 0.1:
                    continue
                depth = float((c - b) @ n_in)
                if abs((c - b) @ u) > 0.02 or abs((d - c) @ n_in) > 0.02:
                    continue  # a step in, along, and back out
                width = float((d - c) @ u)
                if not (0.05 < depth <= NOTCH_DEPTH and 0 < width <= NOTCH_WIDTH):
                    continue
                quad = np.array([b, c, d, g])
                top = _top(scene, quad, ceil)
                if not _wall_behind(scene, c, d, -n_in, depth, top, ceil):
                    continue
                # walls idx[e] (a->b) to e+4 (g->f) become one a->f
                first, last = idx[e], idx[(e + 4) % k]
                gone = {idx[(e + m) % k] for m in (1, 2, 3, 4)}
                merged = {
                    **walls[first],
                    "end": walls[last]["end"],
                    "length": round(float(np.linalg.norm(f - a)), 4),
                    "seen": bool(walls[first]["seen"] or walls[last]["seen"]),
                }
                merged.pop("pieces", None)
                walls[first] = merged
                walls = [w for i, w in enumerate(walls) if i not in gone]
                poly = np.array([w["start"] for w in walls if w["room"] == ri])
                x, y = poly[:, 0], poly[:, 1]
                area = 0.5 * float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum())
                rooms[ri] = {**rooms[ri], "polygon": poly.tolist(), "area": round(area, 4)}
                changed = True
                break
    return {**plan, "rooms": rooms, "walls": walls}

"""Scores of an architectural plan (plan.json) against the exact layout (gt/layout.json).

MonteFloor's protocol as RoomFormer reports it: a predicted room matches a ground-truth room
(one to one, Hungarian on IoU) when their IoU is at least 0.5; within matched rooms a corner
matches (one to one, Hungarian on distance) within `corner_tol` metres, and its angle matches
when, in addition, the interior angles at the two corners differ by at most `angle_tol`
degrees. Precision divides by all predicted rooms / corners, recall by all ground-truth ones.
A wall's length error compares each ground-truth wall of a matched room with the predicted
wall of that room whose ends lie nearest its ends; a door (a passage) is found when a
predicted opening of its kind has its centre within `door_tol` metres of its centre (an
opening without a kind is a door), and joins the right rooms when the rooms its `rooms` names
are the ground truth's (through the room matching).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from shapely.geometry import Polygon


def prf(tp: int, n_pred: int, n_gt: int) -> tuple[float, float, float]:
    """(precision, recall, F1); 0 where a count is 0."""
    p = tp / n_pred if n_pred else 0.0
    r = tp / n_gt if n_gt else 0.0
    return p, r, (2 * p * r / (p + r) if p + r > 0 else 0.0)


def interior_angles(poly: np.ndarray) -> np.ndarray:
    """Interior angle (degrees) at each vertex of a counter-clockwise polygon [N, 2]."""
    a = np.roll(poly, 1, axis=0) - poly
    b = np.roll(poly, -1, axis=0) - poly
    ang = np.degrees(np.arctan2(b[:, 0] * a[:, 1] - b[:, 1] * a[:, 0], (a * b).sum(1)))
    return ang % 360  # counter-clockwise from the next edge to the previous one: the inside


def _ccw(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    return poly if (x * np.roll(y, -1) - np.roll(x, -1) * y).sum() > 0 else poly[::-1]


def match_rooms(pred: list[np.ndarray], gt: list[np.ndarray], min_iou: float = 0.5) -> list:
    """(pred index, gt index) pairs, one to one, with IoU >= min_iou."""
    if not pred or not gt:
        return []
    iou = np.zeros((len(pred), len(gt)))
    for i, p in enumerate(pred):
        for j, g in enumerate(gt):
            pp, gg = Polygon(p).buffer(0), Polygon(g).buffer(0)
            u = pp.union(gg).area
            iou[i, j] = pp.intersection(gg).area / u if u > 0 else 0.0
    rows, cols = linear_sum_assignment(-iou)
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=True) if iou[i, j] >= min_iou]


def _edges(poly: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(poly[i], poly[(i + 1) % len(poly)]) for i in range(len(poly))]


def score_layout(
    pred: dict,
    gt: dict,
    corner_tol: float = 0.1,
    angle_tol: float = 5.0,
    door_tol: float = 0.3,
) -> dict:
    """metrics.layout: room / corner / angle precision, recall, F1; median wall-length error
    (metres); doors and passages found of their totals and the largest width error of those
    found."""
    pr = [_ccw(np.asarray(r["polygon"], np.float64)) for r in pred.get("rooms", [])]
    gr = [_ccw(np.asarray(r["polygon"], np.float64)) for r in gt.get("rooms", [])]
    pairs = match_rooms(pr, gr)
    n_pc, n_gc = sum(len(p) for p in pr), sum(len(g) for g in gr)
    tp_c = tp_a = 0
    len_err: list[float] = []
    for i, j in pairs:
        p, g = pr[i], gr[j]
        dist = np.linalg.norm(p[:, None] - g[None], axis=-1)
        rows, cols = linear_sum_assignment(dist)
        ok = dist[rows, cols] <= corner_tol
        tp_c += int(ok.sum())
        dang = np.abs(interior_angles(p)[rows] - interior_angles(g)[cols])
        tp_a += int((ok & (np.minimum(dang, 360 - dang) <= angle_tol)).sum())
        pe = _edges(p)
        for a, b in _edges(g):
            cost = [
                min(
                    np.linalg.norm(a - c) + np.linalg.norm(b - d),
                    np.linalg.norm(a - d) + np.linalg.norm(b - c),
                )
                for c, d in pe
            ]
            k = int(np.argmin(cost))
            len_err.append(abs(float(np.linalg.norm(pe[k][1] - pe[k][0]) - np.linalg.norm(b - a))))
    out: dict = {}
    for name, tp, n_p, n_g in (
        ("room", len(pairs), len(pr), len(gr)),
        ("corner", tp_c, n_pc, n_gc),
        ("angle", tp_a, n_pc, n_gc),
    ):
        p_, r_, f_ = prf(tp, n_p, n_g)
        out[f"{name}_precision"], out[f"{name}_recall"], out[f"{name}_f1"] = (
            round(p_, 4),
            round(r_, 4),
            round(f_, 4),
        )
    out["wall_length_err_m"] = round(float(np.median(len_err)), 4) if len_err else None
    to_gt = dict(pairs)
    joined: list[bool] = []
    for kind, name in (("door", "doors"), ("passage", "passages")):
        pk = [o for o in pred.get("openings", []) if o.get("kind", "door") == kind]
        gk = [o for o in gt.get("openings", []) if o.get("kind", "door") == kind]
        matched: list[tuple[int, int]] = []
        found, werr = _found(pk, gk, door_tol, matched)
        out[f"{name}_found"], out[f"{name}_total"] = found, len(gk)
        out[f"{kind}_width_err_m"] = round(max(werr), 4) if werr else None
        for i, j in matched:
            if "rooms" in gk[j]:
                mine = {to_gt.get(int(r), -1 - int(r)) for r in pk[i].get("rooms", [])}
                joined.append(mine == {int(r) for r in gk[j]["rooms"]})
    # of the openings found whose ground truth names its rooms: how many join the same rooms
    # (the predicted rooms through the room matching); None when none names them
    out["openings_rooms_right"] = sum(joined) if joined else None
    out["openings_rooms_total"] = len(joined) if joined else None
    return out


def _found(
    pred: list[dict], gt: list[dict], tol: float, matched: list | None = None
) -> tuple[int, list[float]]:
    """Ground-truth openings matched one to one to predicted ones by centre distance: how
    many within `tol`, and their width errors; the (pred, gt) index pairs found are appended
    to `matched`."""
    found, werr = 0, []
    if pred and gt:
        pc = np.array([(np.add(o["start"], o["end"]) / 2) for o in pred])
        gc = np.array([(np.add(o["start"], o["end"]) / 2) for o in gt])
        dist = np.linalg.norm(pc[:, None] - gc[None], axis=-1)
        rows, cols = linear_sum_assignment(dist)
        for i, j in zip(rows, cols, strict=True):
            if dist[i, j] <= tol:
                found += 1
                if matched is not None:
                    matched.append((int(i), int(j)))
                werr.append(abs(float(pred[i]["width"]) - float(gt[j]["width"])))
    return found, werr


def layout_to_frame(plan: dict, pred_to_gt: np.ndarray | None) -> dict:
    """plan.json's rooms and openings moved through a 4x4 similarity (e.g. estimated poses to
    the ground truth's frame; None: unchanged). Widths scale with it."""
    if pred_to_gt is None:
        return plan
    m = np.asarray(pred_to_gt, np.float64)
    scale = float(np.cbrt(abs(np.linalg.det(m[:3, :3]))))

    def xy(points: list) -> list:
        p = np.asarray(points, np.float64).reshape(-1, 2)
        p3 = np.c_[p, np.zeros(len(p))] @ m[:3, :3].T + m[:3, 3]
        return p3[:, :2].tolist()

    rooms = [{**r, "polygon": xy(r["polygon"])} for r in plan.get("rooms", [])]
    openings = [
        {
            **o,
            "start": xy([o["start"]])[0],
            "end": xy([o["end"]])[0],
            "width": float(o["width"]) * scale,
        }
        for o in plan.get("openings", [])
    ]
    return {**plan, "rooms": rooms, "openings": openings}

"""The project stage's files, as every later stage reads them: points.npz and grid.json.

points.npz: `xyz` float32 [N, 3] offsets from `origin` float64 [3] (far from the world
origin float32 world coordinates keep only ~1 mm; read_points adds them back), `label` uint8
[N], `view` int32 [N], `instance` int32 [N] (object instance, 0 = none; absent from files
written before points carried instances: read_instances gives zeros) and `classes` (a JSON
object id -> name). grid.json: the plan Grid (Grid.to_json) plus "bounds" [xmin, ymin,
xmax, ymax] of the points it was padded from.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.common.blueprint import Grid
from stages.common.errors import BlunfError
from stages.common.io import read_json, write_json


def write_points(
    path: Path,
    xyz: np.ndarray,
    origin: np.ndarray,
    label: np.ndarray,
    view: np.ndarray,
    instance: np.ndarray,
    classes: dict[int, str],
) -> None:
    """Write points.npz: xyz float32 [N, 3] offsets from origin [3], label, view, instance [N]."""
    np.savez(
        path,
        xyz=xyz,
        origin=origin,
        label=label,
        view=view,
        instance=instance,
        classes=json.dumps(str_keys(classes)),
    )


def write_grid(path: Path, grid: Grid, lo: np.ndarray, hi: np.ndarray) -> None:
    """Write grid.json: the plan grid and the bounds lo [2], hi [2] of its points."""
    write_json(path, {**grid.to_json(), "bounds": [*lo.tolist(), *hi.tolist()]})


def str_keys(classes: dict[int, str]) -> dict[str, str]:
    """A class table with string keys, in id order (as JSON stores it)."""
    return {str(k): v for k, v in sorted(classes.items())}


def read_points(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, str]]:
    """Read points.npz. Returns (world xyz float64 [N, 3], label uint8 [N], view int32 [N],
    classes). The file's float32 xyz are offsets from its float64 origin (0 when absent)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            xyz, label, view = z["xyz"], z["label"], z["view"]
            origin = np.asarray(z["origin"] if "origin" in z.files else np.zeros(3), np.float64)
            classes = {int(k): str(v) for k, v in json.loads(str(z["classes"])).items()}
    except (OSError, KeyError, ValueError) as e:
        raise BlunfError(f"{path}: not a points .npz ({e})") from None
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(label) != len(xyz) or len(view) != len(xyz):
        raise BlunfError(f"{path}: xyz, label and view disagree in length")
    if origin.shape != (3,):
        raise BlunfError(f"{path}: origin must be 3 numbers, got shape {origin.shape}")
    return xyz.astype(np.float64) + origin, label, view, classes


def read_instances(path: Path) -> np.ndarray:
    """The object instance of every point of points.npz (0 = none): int32 [N], all 0 for a
    file written before points carried instances."""
    try:
        with np.load(path, allow_pickle=False) as z:
            n = len(z["label"])
            inst = z["instance"] if "instance" in z.files else np.zeros(n, np.int32)
    except (OSError, KeyError, ValueError) as e:
        raise BlunfError(f"{path}: not a points .npz ({e})") from None
    if inst.shape != (n,):
        raise BlunfError(f"{path}: instance and label disagree in length")
    return inst.astype(np.int32)


def read_grid(path: Path) -> Grid:
    """Read grid.json."""
    d = read_json(path)
    try:
        return Grid.from_json(d)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise BlunfError(f"{path}: not a plan grid ({e})") from None


def read_bounds(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo [2], hi [2]) of the points, from grid.json (None when it does not say)."""
    b = read_json(path).get("bounds")
    if b is None:
        return None
    try:
        lo, hi = np.asarray(b[:2], np.float64), np.asarray(b[2:], np.float64)
    except (TypeError, ValueError) as e:
        raise BlunfError(f"{path}: bad bounds ({e})") from None
    if lo.shape != (2,) or hi.shape != (2,) or not (lo <= hi).all():
        raise BlunfError(f"{path}: bounds must be [xmin, ymin, xmax, ymax], got {b}")
    return lo, hi

"""The blueprint raster: class ids on square cells, row 0 at the highest y (north up), and
optionally the object instance of every cell."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.common.capture import UNKNOWN
from stages.common.errors import BlunfError
from stages.common.io import save_npz


@dataclass(frozen=True)
class Grid:
    """Square cells of `cell` metres; `origin` = world (x_min, y_min) of the lower-left corner."""

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]  # (rows H, cols W)

    @staticmethod
    def covering(xy_min: np.ndarray, xy_max: np.ndarray, cell: float, pad: float = 0.0) -> Grid:
        """The smallest grid of `cell` metres covering [xy_min, xy_max] plus `pad` metres."""
        if not cell > 0:
            raise BlunfError(f"blueprint cell must be > 0 metres, got {cell}")
        lo = np.asarray(xy_min, np.float64) - pad
        hi = np.asarray(xy_max, np.float64) + pad
        lo = np.floor(lo / cell) * cell
        w, h = (np.ceil((hi - lo) / cell - 1e-9).astype(int) + 0).clip(min=1)
        return Grid((float(lo[0]), float(lo[1])), float(cell), (int(h), int(w)))

    def centers(self) -> np.ndarray:
        """World (x, y) of every cell centre. Returns float64 [H, W, 2]."""
        h, w = self.shape
        x = self.origin[0] + (np.arange(w) + 0.5) * self.cell
        y = self.origin[1] + (h - np.arange(h) - 0.5) * self.cell
        xx, yy = np.meshgrid(x, y)
        return np.stack([xx, yy], axis=-1)

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of world points xy [N, 2]; row/col are clipped where outside."""
        xy = np.asarray(xy, np.float64)
        h, w = self.shape
        col = np.floor((xy[:, 0] - self.origin[0]) / self.cell).astype(np.int64)
        row = h - 1 - np.floor((xy[:, 1] - self.origin[1]) / self.cell).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        return row.clip(0, h - 1), col.clip(0, w - 1), inside

    def to_json(self) -> dict:
        return {"origin": list(self.origin), "cell": self.cell, "shape": list(self.shape)}

    @staticmethod
    def from_json(d: dict) -> Grid:
        return Grid(
            (float(d["origin"][0]), float(d["origin"][1])),
            float(d["cell"]),
            (int(d["shape"][0]), int(d["shape"][1])),
        )


@dataclass(frozen=True)
class Blueprint:
    """labels uint8 [H, W] (UNKNOWN = 255 unseen) on `grid`, with the class table.

    `instances` int32 [H, W], when the plan knows them: the object instance of every cell
    (0 = none), so that two objects of one class that touch stay two components.
    `seen` and `inside` uint8 [H, W] (0/1), when the plan knows them: some view observed the
    cell (a projected point lies near it), and the cell lies within the room's outline (what
    the views observed or looked through, its holes filled). Labels are UNKNOWN outside it;
    inside it and unseen they are inferred (BluNF fills the gaps between observations).
    """

    labels: np.ndarray
    grid: Grid
    classes: dict[int, str] = field(default_factory=dict)
    instances: np.ndarray | None = None
    seen: np.ndarray | None = None
    inside: np.ndarray | None = None

    def shares(self) -> dict[str, float] | None:
        """Percent of the plan's cells seen (labelled, observed), inferred (labelled, not
        observed: BluNF filled them), unknown (inside the room, too far from what was seen to
        guess) and outside; None when the plan does not know what was seen."""
        if self.seen is None or self.inside is None:
            return None
        n = max(1, self.labels.size)
        seen, inside, lab = self.seen > 0, self.inside > 0, self.labels != UNKNOWN

        def pct(m: np.ndarray) -> float:
            return round(100.0 * float(m.sum()) / n, 3)

        return {
            "seen_pct": pct(lab & seen),
            "inferred_pct": pct(lab & ~seen),
            "unknown_pct": pct(~lab & inside),
            "outside_pct": pct(~lab & ~inside),
        }

    def sample(self, xy: np.ndarray) -> np.ndarray:
        """Label at world points xy [N, 2] (nearest cell); UNKNOWN outside the raster."""
        row, col, inside = self.grid.cell_of(xy)
        out = self.labels[row, col].copy()
        out[~inside] = UNKNOWN
        return out

    def resample(self, grid: Grid) -> np.ndarray:
        """This plan read at the cell centres of another grid. Returns uint8 [H', W']."""
        c = grid.centers().reshape(-1, 2)
        return self.sample(c).reshape(grid.shape)

    def save(self, path: Path) -> None:
        extra = {} if self.instances is None else {"instances": self.instances.astype(np.int32)}
        for name in ("seen", "inside"):
            a = getattr(self, name)
            if a is not None:
                extra[name] = (np.asarray(a) > 0).astype(np.uint8)
        save_npz(
            path,
            labels=self.labels.astype(np.uint8),
            cell=np.float64(self.grid.cell),
            origin=np.asarray(self.grid.origin, np.float64),
            classes=json.dumps({str(k): v for k, v in sorted(self.classes.items())}),
            **extra,
        )

    @staticmethod
    def load(path: Path) -> Blueprint:
        try:
            z = np.load(path, allow_pickle=False)
            labels = z["labels"].astype(np.uint8)
            grid = Grid(
                (float(z["origin"][0]), float(z["origin"][1])),
                float(z["cell"]),
                (labels.shape[0], labels.shape[1]),
            )
            classes = {int(k): v for k, v in json.loads(str(z["classes"])).items()}
            instances = z["instances"].astype(np.int32) if "instances" in z.files else None
            seen = z["seen"].astype(np.uint8) if "seen" in z.files else None
            inside = z["inside"].astype(np.uint8) if "inside" in z.files else None
        except (OSError, KeyError, ValueError) as e:
            raise BlunfError(f"{path}: not a blueprint .npz ({e})") from None
        if instances is not None and instances.shape != labels.shape:
            raise BlunfError(
                f"{path}: instances {instances.shape} do not match labels {labels.shape}"
            )
        for name, a in (("seen", seen), ("inside", inside)):
            if a is not None and a.shape != labels.shape:
                raise BlunfError(f"{path}: {name} {a.shape} does not match labels {labels.shape}")
        return Blueprint(labels, grid, classes, instances, seen, inside)


def observed_layer(path: Path, name: str, shape: tuple[int, int]) -> np.ndarray | None:
    """One layer of the project stage's observed.npz (e.g. "free", "past") as it is stored, or
    None when the file (an older one) lacks it or its cells do not match the grid `shape`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            a = z[name] if name in z.files else None
    except (OSError, ValueError) as e:
        raise BlunfError(f"{path}: not an observed.npz ({e})") from None
    return a if a is not None and a.shape == tuple(shape) else None


def read_observed(path: Path, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(seen, inside, labelled) bool [H, W] from the project stage's observed.npz."""
    try:
        z = np.load(path, allow_pickle=False)
        out = (z["near"] > 0, z["inside"] > 0, z["labelled"] > 0)
    except (OSError, KeyError, ValueError) as e:
        raise BlunfError(f"{path}: not an observed.npz ({e})") from None
    if any(a.shape != tuple(shape) for a in out):
        raise BlunfError(f"{path}: observed cells {out[0].shape} do not match the grid {shape}")
    return out

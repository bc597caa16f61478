"""Occupancy grid for empty-space skipping (Instant-NGP / nerfacc style, in torch).

Each cell of a box-aligned grid keeps a running estimate of the field's density (`ema`); a
cell is occupied when the estimate exceeds a threshold. Seeding from depth points starts the
grid tight around the surfaces seen; updates decay every estimate and re-measure the density
at a jittered point in a random set of cells, so cells the field empties are dropped and
cells it fills are added. `Occupancy` is what the marcher asks of such a structure.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor, nn

UPDATE_CHUNK = 65536  # points per density call during an update
COARSE = 4  # cells per side of the blocks used to skip long empty stretches


class Occupancy(Protocol):
    """Where the field may hold density: what `marching.march` asks of an occupancy grid."""

    def query(self, x: Tensor) -> Tensor:
        """Occupied? [N, 3] world points -> bool [N]."""
        ...

    def query_coarse(self, x: Tensor) -> Tensor:
        """Occupied within one coarse block of x? [N, 3] -> bool [N] (True wherever `query`
        could be True on a segment of `coarse_size` metres centred at x)."""
        ...

    def coarse_size(self) -> float:
        """Metres: the side of a coarse block (rays are first walked in segments this long)."""
        ...


class OccupancyGrid(nn.Module):
    """Boolean occupancy over the box [lo, hi] with `shape` = (X, Y, Z) cells."""

    # buffers (registered in __init__; declared here for the type checker)
    lo: Tensor  # [3]
    hi: Tensor  # [3]
    ema: Tensor  # [X, Y, Z]
    binary: Tensor  # [X, Y, Z] bool
    keep: Tensor  # [X, Y, Z] bool
    coarse: Tensor  # [X', Y', Z'] bool, derived from binary (not saved)

    def __init__(self, lo: Tensor, hi: Tensor, shape: tuple[int, int, int]) -> None:
        super().__init__()
        self.register_buffer("lo", torch.as_tensor(lo, dtype=torch.float32).clone())  # [3]
        self.register_buffer("hi", torch.as_tensor(hi, dtype=torch.float32).clone())  # [3]
        self.register_buffer("ema", torch.zeros(shape))  # [X, Y, Z] density estimate (1/m)
        self.register_buffer("binary", torch.zeros(shape, dtype=torch.bool))  # [X, Y, Z]
        # cells seen full by depth: occupied whatever the updates measure (a thin surface
        # inside a cell is easily missed by the one jittered point an update looks at)
        self.register_buffer("keep", torch.zeros(shape, dtype=torch.bool))  # [X, Y, Z]
        # blocks of COARSE^3 cells, occupied when any cell of theirs or of a neighbouring
        # block is: recomputed by every method that changes `binary`, and on loading
        self.register_buffer("coarse", self._coarse_of(self.binary), persistent=False)
        self.register_load_state_dict_post_hook(OccupancyGrid._loaded)

    @staticmethod
    def for_box(lo: Tensor, hi: Tensor, res: int) -> OccupancyGrid:
        """Near-cubic cells, `res` of them along the box's longest side."""
        ext = (hi - lo).double()
        sx, sy, sz = (max(1, round(float(e / ext.max() * res))) for e in ext)
        return OccupancyGrid(lo, hi, (sx, sy, sz))

    @property
    def shape(self) -> tuple[int, int, int]:
        x, y, z = self.binary.shape
        return (x, y, z)

    def _cell(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """World [N, 3] -> (flat cell index [N], inside the box [N])."""
        dims = torch.tensor(self.shape, dtype=torch.int64)
        ijk = ((x - self.lo) / (self.hi - self.lo) * dims).floor()
        inside = ((ijk >= 0) & (ijk < dims)).all(dim=-1)
        ijk = ijk.to(torch.int64).clamp(min=torch.zeros_like(dims), max=dims - 1)
        flat = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        return flat, inside

    def cell_size(self) -> float:
        """Smallest side of a cell (metres)."""
        return float(((self.hi - self.lo) / torch.tensor(self.shape)).min())

    @staticmethod
    def _coarse_of(binary: Tensor) -> Tensor:
        """Blocks of COARSE^3 cells, occupied when any cell of theirs or of a neighbouring
        block is (bool [X', Y', Z']). A segment shorter than a block is free when its middle
        lies in a free coarse block."""
        b = binary.float()[None, None]
        b = F.max_pool3d(b, COARSE, stride=COARSE, ceil_mode=True)
        return F.max_pool3d(b, 3, stride=1, padding=1)[0, 0] > 0

    def _changed(self) -> None:
        """Bring `coarse` up to date with `binary`."""
        self.coarse = self._coarse_of(self.binary)

    @staticmethod
    def _loaded(module: nn.Module, _keys: Any) -> None:
        assert isinstance(module, OccupancyGrid)
        module._changed()

    def coarse_size(self) -> float:
        """Smallest side of a coarse block (metres)."""
        return COARSE * self.cell_size()

    def query_coarse(self, x: Tensor) -> Tensor:
        """Occupied within one coarse block of x? [N, 3] world points -> bool [N]."""
        if len(x) == 0:
            return torch.zeros(0, dtype=torch.bool)
        c = self.coarse
        dims = torch.tensor(self.shape, dtype=torch.int64)
        cdims = torch.tensor(c.shape, dtype=torch.int64)
        # clamped, not cut, at the box: a segment whose middle lies just outside the box may
        # still cross its border blocks (e.g. a floor at the bottom of the box)
        u = ((x - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0)
        ijk = (u * dims).floor().to(torch.int64).minimum(dims - 1) // COARSE
        flat = (ijk[:, 0] * cdims[1] + ijk[:, 1]) * cdims[2] + ijk[:, 2]
        return c.view(-1)[flat]

    def query(self, x: Tensor) -> Tensor:
        """Occupied? [N, 3] world points -> bool [N] (False outside the box)."""
        flat, inside = self._cell(x)
        return self.binary.view(-1)[flat] & inside

    def fill(self, value: float) -> None:
        """Every cell occupied, with density estimate `value`."""
        self.ema.fill_(value)
        self.binary.fill_(True)
        self._changed()

    def seed(self, points: Tensor | Iterable[Tensor], value: float, dilate: int) -> int:
        """Mark the cells holding `points` ([N, 3], or several such sets: one per depth map)
        and `dilate` cells around as occupied for good, with estimate `value`; repeated calls
        add up. Returns the occupied cells. The sets' cells are gathered first and dilated
        once: dilating each set on its own cost the 7-Scenes kitchen (88 stereo depth maps)
        7.5 s of max-pooling for the same cells."""
        mark = torch.zeros(self.ema.numel())
        for pts in [points] if isinstance(points, Tensor) else points:
            flat, inside = self._cell(pts)
            mark[flat[inside]] = 1.0
        mark = mark.view(1, 1, *self.shape)
        if dilate > 0:
            mark = F.max_pool3d(mark, 2 * dilate + 1, stride=1, padding=dilate)
        occ = mark.view(self.shape) > 0
        self.ema.copy_(torch.where(occ, torch.maximum(self.ema, torch.tensor(value)), self.ema))
        self.keep |= occ
        self.binary |= occ
        self._changed()
        return int(self.binary.sum())

    @torch.no_grad()
    def refresh(
        self, density_fn: Callable[[Tensor], Tensor], threshold: float, points: int = 4
    ) -> int:
        """Re-measure the occupied cells at `points` jittered points (seeded) and drop those
        whose highest density is below the threshold (seeded ones stay): the running estimates
        of `update` lag behind the field, and each stale cell costs samples on every ray.
        Never adds a cell (the field's density where no ray ever looked is noise), so only
        the occupied cells not seeded are measured (the 7-Scenes kitchen from its photos:
        48 thousand of 640 thousand). Returns the occupied cells."""
        gen = torch.Generator().manual_seed(0)
        dims = torch.tensor(self.shape)
        idx = (self.binary & ~self.keep).view(-1).nonzero().squeeze(1)  # [C] to measure
        ijk = torch.stack(
            [idx // (dims[1] * dims[2]), (idx // dims[2]) % dims[1], idx % dims[2]], dim=-1
        )  # [C, 3]
        best = torch.zeros(len(idx))
        for _ in range(points):
            u = (ijk + torch.rand(len(idx), 3, generator=gen)) / dims
            x = self.lo + u * (self.hi - self.lo)
            for i in range(0, len(x), UPDATE_CHUNK):
                sig = torch.nan_to_num(density_fn(x[i : i + UPDATE_CHUNK]), nan=0.0)
                best[i : i + UPDATE_CHUNK] = torch.maximum(best[i : i + UPDATE_CHUNK], sig)
        self.ema.view(-1)[idx] = best
        self.binary.view(-1)[idx] = best > threshold
        self._changed()
        return int(self.binary.sum())

    @torch.no_grad()
    def update(
        self,
        density_fn: Callable[[Tensor], Tensor],
        threshold: float,
        decay: float,
        n_cells: int,
        gen: torch.Generator,
    ) -> None:
        """Decay all estimates, re-measure `n_cells` cells (half uniformly at random, half
        among the occupied ones) at a jittered point, and re-threshold."""
        total = self.ema.numel()
        self.ema.mul_(decay)
        half = max(1, n_cells // 2)
        cells = [torch.randint(0, total, (half,), generator=gen)]
        occ = self.binary.view(-1).nonzero().squeeze(1)
        if len(occ):
            cells.append(occ[torch.randint(0, len(occ), (half,), generator=gen)])
        idx = torch.cat(cells)  # [M]
        dims = torch.tensor(self.shape)
        ijk = torch.stack(
            [idx // (dims[1] * dims[2]), (idx // dims[2]) % dims[1], idx % dims[2]], dim=-1
        )
        u = (ijk + torch.rand(len(idx), 3, generator=gen)) / dims  # [M, 3] in the unit cube
        x = self.lo + u * (self.hi - self.lo)
        sigma = torch.cat(
            [density_fn(x[i : i + UPDATE_CHUNK]) for i in range(0, len(x), UPDATE_CHUNK)]
        )  # [M]
        flat = self.ema.view(-1)
        flat.scatter_reduce_(0, idx, torch.nan_to_num(sigma, nan=0.0), reduce="amax")
        self.binary.copy_((self.ema > threshold) | self.keep)
        self._changed()

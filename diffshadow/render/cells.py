"""Macro-cells (16³ voxels: the field's value range and the TF's peak opacity over it) and the runs of
occupied lattice samples they leave on each ray, so that marching never sends an empty sample to a network."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.grid import cell_ranges
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

RENDER_CELL = 16  # voxels per macro-cell edge (the authors' renderer)


@dataclass
class MacroGrid:
    """Per 16³-voxel cell: the scalar range and the TF's maximum opacity over it; zero means skip.

    `ranges` replaces the volume's own (min, max) per cell: the data INR's ranges, so that a cell is
    only skipped when the field actually rendered has no opaque value in it.
    """

    max_opacity: torch.Tensor  # (cz, cy, cx)
    empty: torch.Tensor  # (cz, cy, cx) bool
    cell: int
    voxel_size: torch.Tensor  # (3,) box units per voxel
    dims: torch.Tensor  # (3,) voxels (x, y, z)
    ncell: torch.Tensor = field(init=False)
    any_empty: bool = field(init=False)  # read once here, so marching needs no host read for it
    planes: torch.Tensor = field(init=False)  # (P,) every interior cell boundary, box units, axis by axis
    plane_axis: torch.Tensor = field(init=False)  # (P,) its axis

    def __post_init__(self):
        device = self.empty.device
        self.ncell = torch.tensor(self.empty.shape[::-1], device=device)
        self.any_empty = bool(self.empty.any())
        planes, axes = [], []
        for axis in range(3):
            n = self.empty.shape[2 - axis]
            planes.append(torch.arange(1, n, device=device, dtype=torch.float32) * (self.cell * self.voxel_size[axis]))
            axes.append(torch.full((n - 1,), axis, device=device, dtype=torch.long))
        self.planes, self.plane_axis = torch.cat(planes), torch.cat(axes)

    @classmethod
    def build(cls, volume: Volume, tf: TransferFunction, *, cell: int = RENDER_CELL,
              ranges: tuple[ArrayLike, ArrayLike] | None = None, device: torch.device | str = "cpu") -> MacroGrid:
        if ranges is None:
            lo, hi = (r.double().numpy() for r in cell_ranges(torch.from_numpy(volume.data), cell))
        else:
            lo, hi = (np.asarray(r, dtype=np.float64) for r in ranges)
        peak = tf.max_opacity(np.clip(lo, 0, 1), np.clip(hi, 0, 1))
        peak = torch.as_tensor(peak, dtype=torch.float32, device=device)
        if tf.density_scale == 0:
            peak = torch.zeros_like(peak)
        return cls(peak, peak <= 0, cell,
                   torch.as_tensor(volume.voxel_size, dtype=torch.float32, device=device),
                   torch.as_tensor(volume.dims, dtype=torch.float32, device=device))

    @property
    def empty_fraction(self) -> float:
        return float(self.empty.float().mean())

    def cell_of(self, p: torch.Tensor) -> torch.Tensor:
        """Integer cell (x, y, z) of box points (N, 3)."""
        c = torch.floor(p / self.voxel_size / self.cell).long()
        return torch.minimum(c.clamp_min(0), self.ncell - 1)

    def is_empty(self, c: torch.Tensor) -> torch.Tensor:
        return self.empty[c[:, 2], c[:, 1], c[:, 0]]


@dataclass
class Runs:
    """The lattice samples t = t0 + (k + ½)·dt of each ray that lie in occupied macro-cells, as runs.

    Run j of a ray holds its occupied samples number cum[j-1] .. cum[j]-1, at lattice index
    k = m + offset[j] for sample number m. Built once per ray, in one vectorised pass over the cell
    boundaries the ray crosses (fixed shape: every interior plane of the macro grid), so marching needs
    no data-dependent jumps: the m-th occupied sample is one `searchsorted` away.
    """

    cum: torch.Tensor  # (R, J) inclusive running count of occupied samples
    offset: torch.Tensor  # (R, J) lattice index minus sample number within run j
    total: torch.Tensor  # (R,) occupied samples of each ray

    @classmethod
    def build(cls, o: torch.Tensor, d: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor, dt: float,
              macro: MacroGrid | None) -> Runs:
        def lattice(t):  # first lattice index whose sample lies at or after t; integers, so that the running
            # counts below are an integer cumsum (CUDA has no deterministic floating-point one)
            return torch.ceil((t - t0[:, None]) / dt - 0.5).clamp_min(0).to(torch.int32)

        if macro is None or not macro.any_empty:
            count = lattice(t1[:, None])[:, 0] * (t1 > t0)
            return cls(count[:, None], torch.zeros_like(count)[:, None], count)
        # where the ray crosses each interior cell boundary (parallel rays: at t1), all planes in one pass
        da, oa = d[:, macro.plane_axis], o[:, macro.plane_axis]
        crosses = da != 0
        planes = torch.where(crosses, (macro.planes - oa) / torch.where(crosses, da, 1.0), t1[:, None])
        t = torch.cat([t0[:, None], planes, t1[:, None]], 1)
        t = torch.minimum(torch.maximum(t, t0[:, None]), t1[:, None]).sort(1).values
        ta, tb = t[:, :-1], t[:, 1:]
        mid = 0.5 * (ta + tb)
        cells = macro.cell_of((o[:, None] + mid[..., None] * d[:, None]).view(-1, 3))
        occupied = ~macro.is_empty(cells).view(mid.shape)
        ka, kb = lattice(ta), lattice(tb)
        length = (kb - ka) * occupied
        cum = length.cumsum(1, dtype=torch.int32)
        return cls(cum, ka - (cum - length), cum[:, -1])

    def samples(self, rows: torch.Tensor, m: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Lattice indices (R', n) of occupied samples m .. m+n-1 of `rows`, and which exist."""
        ms = m[:, None] + torch.arange(n, device=m.device, dtype=m.dtype)
        cum = self.cum[rows]
        j = torch.searchsorted(cum, ms, right=True).clamp_max(cum.shape[1] - 1)
        return ms + self.offset[rows].gather(1, j), ms < self.total[rows, None]

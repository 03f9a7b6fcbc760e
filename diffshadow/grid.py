"""Generic blocks on the vertex-centred voxel grid: trilinear lookup, ray–box slabs, cell value ranges and
the macro-cells built from them, voxel coordinates. Used by the ground truth (`shadow`), stage 1 (`fit`),
the data INR and the renderer; it knows nothing of any of them (docs/design.md §2: the box convention).
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Callable, Iterable

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import ArrayLike

from diffshadow.siren import box_to_siren
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

# The finest marching step taken, in voxels: 128x finer than the benches' reference step (1/8 voxel). Finer steps
# only make a march take hours without a word (render --step 1e-9 ran 7e10 samples a ray).
MIN_STEP = 2.0 ** -10


class Interrupted(Exception):
    """A march was given up: its `interrupt` said so before an iteration (nothing is returned)."""


def go_on(interrupt: Callable[[], bool] | None) -> None:
    """Raise `Interrupted` if `interrupt` (a host-side flag, asked between a march's iterations) says stop."""
    if interrupt is not None and interrupt():
        raise Interrupted


def check_step(step: float, error: type[ValueError] = ValueError, *, extent: ArrayLike | None = None,
               voxel: float | None = None) -> None:
    """A marching step in voxels: finite, positive and not finer than MIN_STEP, else `error` naming it. Given the
    box's `extent` and its finest `voxel` (box units), also no longer than the box's diagonal: a ray would take
    one sample at most, and its integral would be that sample times the whole ray."""
    if isinstance(step, bool) or not isinstance(step, numbers.Real) or not (math.isfinite(step) and step > 0):
        raise error(f"step: expected a positive number of voxels, got {step!r}")
    if step < MIN_STEP:
        raise error(f"step: {step!r} voxels is finer than the finest step marched ({MIN_STEP:g} voxels)")
    if extent is not None and step * voxel > (diagonal := float(np.linalg.norm(np.asarray(extent, np.float64)))):
        raise error(f"step: {step:g} voxels is longer than the volume's diagonal ({diagonal / voxel:.0f} voxels): "
                    f"a ray would take one sample at most")


def trilinear(grid: torch.Tensor, pos_vox: torch.Tensor) -> torch.Tensor:
    """Trilinear values of a (C, Z, Y, X) grid at (N, 3) voxel positions (x, y, z) → (C, N), clamped to the grid.

    Nested lerps rather than grid_sample's weighted sum of 8 corners: a lerp between equal values is that
    value exactly, so a constant region stays constant. grid_sample's weights sum to 1 - 6e-8, which a steep
    transfer function times density 1e8 turns into μ ≈ 6 where the true μ is 0 (stress suite).
    """
    c, nz, ny, nx = grid.shape
    top, last_cell, strides = lattice((nz, ny, nx), pos_vox.dtype, pos_vox.device)
    p = torch.minimum(pos_vox.clamp_min(0), top)
    i0 = torch.minimum(p.floor(), last_cell)  # the last cell includes its far face
    f = p - i0
    base = (i0.long() * strides).sum(dim=1)
    # the neighbours' offsets from the grid's shape, not read back from the stride tensor: on a GPU each read syncs
    sx, sy, sz = (s if n > 1 else 0 for s, n in ((1, nx), (nx, ny), (nx * ny, nz)))
    flat = grid.reshape(c, -1)

    def at(offset: int) -> torch.Tensor:  # index_select: 3-5x aten::index's gather on a CPU, the same values
        return torch.index_select(flat[:, offset:], 1, base)

    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    y0 = torch.lerp(torch.lerp(at(0), at(sx), fx), torch.lerp(at(sy), at(sy + sx), fx), fy)
    y1 = torch.lerp(torch.lerp(at(sz), at(sz + sx), fx), torch.lerp(at(sz + sy), at(sz + sy + sx), fx), fy)
    return torch.lerp(y0, y1, fz)


def lattice(shape: tuple[int, int, int], dtype: torch.dtype, device: torch.device
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For a (Z, Y, X) lattice: its last point and the first corner of its last cell, (x, y, z) in `dtype`, and its
    flat strides (x, y, z) as int64, all on `device` (`constant`s: shared, never written to)."""
    nz, ny, nx = shape
    return (constant((nx - 1, ny - 1, nz - 1), dtype, device),
            constant((max(nx - 2, 0), max(ny - 2, 0), max(nz - 2, 0)), dtype, device),
            constant((1, nx, nx * ny), torch.int64, device))


def box(extent: ArrayLike, device: torch.device | str) -> torch.Tensor:
    """A volume's extent (x, y, z) as a float32 `constant` on `device`."""
    return constant(tuple(float(v) for v in np.asarray(extent, dtype=np.float64).reshape(-1)), torch.float32,
                    torch.device(device))


@functools.lru_cache(maxsize=256)
def constant(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """`values` as a tensor on `device`, made once per values, dtype and device and shared between calls, so never
    written to: on a GPU a tensor built from host numbers is a copy the host waits for (PyTorch's blocking
    host-to-device copy synchronises the stream), which a march paid at every iteration and a frame at its start."""
    return torch.tensor(values, dtype=dtype, device=device)


# voxels whose cells' ranges `macro_cells` reads at once: unit cells ~12 x 4 bytes a voxel at its peak, larger cells
# two copies of their voxels (the padded slab and its negation)
MACRO_CELLS_PER_PASS = 1 << 22


def macro_cells(scalar: torch.Tensor, tf: TransferFunction, cell: int) -> torch.Tensor:
    """(cz, cy, cx) bool: True where every point of the cell has μ = 0.

    Vertex-centred cells include their boundary voxels (cell c spans voxels c·M .. c·M+M), so any
    trilinear sample in the closed cell lies in [min, max] of the cell's voxels, and the TF's maximum
    opacity over that range bounds μ in the cell.
    """
    # A pass at a time over slabs of cells: the whole grid's ranges, read in float64 with their interpolated
    # opacities, held ~12 grids' bytes at once (6.2 GiB over a sweep's 511³ grid); 8³ cells over it, 2 grids
    per_pass = max(1, MACRO_CELLS_PER_PASS // max(1, scalar[0].numel() * cell))
    out = []
    for z0, z1 in cell_slabs(scalar.shape[0], cell, per_pass):
        lo, hi = cell_ranges(scalar[z0:z1], cell)
        if tf.density_scale == 0:
            out.append(torch.ones_like(hi, dtype=torch.bool))
            continue
        peak = tf.max_opacity(lo.cpu().double().numpy(), hi.cpu().double().numpy())
        out.append(torch.as_tensor(peak <= 0, device=scalar.device))
        del lo, hi, peak
    return out[0] if len(out) == 1 else torch.cat(out)


BOUNDS_CELL = 8  # the coarse cells `occupied_bounds` reads first (each 8³ unit cells)


def occupied_bounds(scalar: torch.Tensor, tf: TransferFunction,
                    coarse: int = BOUNDS_CELL) -> list[tuple[int, int]] | None:
    """The bounding box of the unit cells (`macro_cells(scalar, tf, 1)`) where μ can be non-zero: (first, end) along
    each axis, or None where there are none; the box the unit cells' whole mask gives, at a fraction of its cost.

    A coarse cell's range is the union of its unit cells' ranges (they tile it, neighbours sharing voxels, so the
    union is one interval), and a range is occupied exactly when it meets the opacity's positive set, so a coarse
    cell is occupied exactly when one of its unit cells is. The box's first and last unit cell along an axis then lie
    in the first and last occupied coarse slab, and only those six slabs' unit cells are read (a sweep's 511³ grid:
    its 133 M unit cells had been 45 % of the sweep)."""
    cells = macro_cells(scalar, tf, coarse)
    if cells.all():
        return None
    occupied = ~cells
    bounds = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        hit = torch.nonzero(occupied.any(dim=others)).flatten()
        ends = []
        for c, last in ((int(hit[0]), False), (int(hit[-1]), True)):
            first = c * coarse  # the slab's first voxel plane; its unit cells start there
            planes = min(scalar.shape[axis], first + coarse + 1) - first
            units = ~macro_cells(scalar.narrow(axis, first, planes), tf, 1)
            found = torch.nonzero(units.any(dim=others)).flatten()
            ends.append(first + (int(found[-1]) + 1 if last else int(found[0])))
        bounds.append((ends[0], ends[1]))
    return bounds


def cell_slabs(n: int, cell: int, per_slab: int) -> list[tuple[int, int]]:
    """The first axis's `n` voxel planes as slabs of `per_slab` vertex-centred cells each: (first, end) plane of
    each, a slab's last plane shared with the next. A cell's range is its own voxels', so `cell_ranges` of the
    slabs, joined, are those of the whole grid."""
    cells = max(1, (n - 1 + cell - 1) // cell)
    return [(c0 * cell, min(n, (c0 + per_slab) * cell + 1)) for c0 in range(0, cells, per_slab)]


def cell_ranges(scalar: torch.Tensor, cell: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(min, max) of the voxels of each vertex-centred cell, boundary voxels included: (cz, cy, cx) each."""
    n = torch.tensor(scalar.shape, device="cpu")  # sizes, read on the host
    nc = torch.clamp((n - 1 + cell - 1) // cell, min=1)
    pad = []
    for axis in (2, 1, 0):  # F.pad takes the last axis first
        pad += [0, int(nc[axis] * cell + 1 - n[axis])]
    x = F.pad(scalar[None, None], pad, mode="replicate")
    hi = F.max_pool3d(x, kernel_size=cell + 1, stride=cell)[0, 0]
    lo = -F.max_pool3d(-x, kernel_size=cell + 1, stride=cell)[0, 0]
    return lo, hi


def ray_box(p: torch.Tensor, w: torch.Tensor, extent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit t of rays p + t w against the box [0, extent] (slab method)."""
    inv = torch.where(w != 0, 1.0 / w, torch.full_like(w, math.inf))
    t_a = (0 - p) * inv
    t_b = (extent - p) * inv
    # a zero direction component: the slab is (-inf, inf) when inside it and empty otherwise
    inside = (p >= 0) & (p <= extent)
    lo = torch.where(w != 0, torch.minimum(t_a, t_b), torch.where(inside, -math.inf, math.inf))
    hi = torch.where(w != 0, torch.maximum(t_a, t_b), torch.where(inside, math.inf, -math.inf))
    return lo.max(dim=-1).values, hi.min(dim=-1).values


def lattice_axes(volume: Volume, refine: int = 1, device: torch.device | str = "cpu") -> list[torch.Tensor]:
    """Box coordinates along z, y and x of the voxels' lattice, `refine` times finer (`volume.refine`'s)."""
    return [torch.linspace(0, float(e), (n - 1) * refine + 1, device=device)
            for e, n in zip(volume.extent[::-1], volume.data.shape, strict=True)]


def voxel_points(volume: Volume, device: torch.device | str = "cpu") -> torch.Tensor:
    """Box coordinates (x, y, z) of every voxel, in (Z, Y, X) order → (Z·Y·X, 3)."""
    z, y, x = torch.meshgrid(*lattice_axes(volume, device=device), indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3)


def lattice_points(axes: list[torch.Tensor], start: int, stop: int) -> torch.Tensor:
    """Box coordinates (x, y, z) of points `start`..`stop` - 1 of the lattice of `axes` (z, y, x), in (Z, Y, X)
    order: those rows of `voxel_points` (whose axes are the voxels'), made alone, so that a lattice can be walked a
    chunk at a time without holding every point's 12 bytes."""
    return lattice_points_at(axes, torch.arange(start, stop, device=axes[0].device))


def lattice_points_at(axes: list[torch.Tensor], index: torch.Tensor) -> torch.Tensor:
    """Box coordinates (x, y, z) of the lattice points at flat (Z, Y, X)-order `index` (int64, on the axes'
    device): those rows of `voxel_points`, made alone."""
    rows, cols = len(axes[1]), len(axes[2])
    return torch.stack([axes[2][index % cols], axes[1][(index // cols) % rows], axes[0][index // (rows * cols)]], -1)


def lookup_grids(grids: torch.Tensor, points: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """Trilinear values of K grids (K, Z, Y, X) at (K, N, 3) box points → (K, N). Grids stored channels last
    (`stack_grids`) at points they share (one (N, 3) set expanded, stride 0) are read as K channels of one:
    each point's corners and weights once, a corner's K values from adjacent memory (0.26x the time for 32 grids of
    81³ at 1,024 points on a CPU), each value the same, as grid_sample weighs every channel alike."""
    g = box_to_siren(points, extent)
    if len(grids) > 1 and grids.stride(0) == 1 and points.stride(0) == 0:
        out = F.grid_sample(grids[None], g[:1, None, None], mode="bilinear", padding_mode="border", align_corners=True)
        return out[0, :, 0, 0]
    out = F.grid_sample(grids[:, None], g[:, None, None], mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out[:, 0, 0, 0]


def stack_grids(grids: Iterable[torch.Tensor], count: int, *, channels_last: bool = False) -> torch.Tensor:
    """`count` (Z, Y, X) grids as one (K, Z, Y, X) tensor, each copied in as it comes and let go of before the
    next is asked for, so that a generator's grids are never held twice (torch.stack of a list is: with tooth's 32
    fitting grids at 2x, 1.5 GiB, its fit-siren job peaked at 4.4 GiB, 2.9 stacked as they come;
    docs/performance.md). `channels_last`: stored with K innermost (for `lookup_grids` at shared points)."""
    out, k = None, 0
    for grid in grids:  # not enumerate: its reused result tuple would hold the last grid while the next is made
        if k == count:
            raise ValueError(f"stack_grids: expected {count} grids, got more")
        if out is None:
            shape = (*grid.shape, count) if channels_last else (count, *grid.shape)
            out = torch.empty(shape, dtype=grid.dtype, device=grid.device)
        (out[..., k] if channels_last else out[k]).copy_(grid)
        del grid
        k += 1
    if k != count:
        raise ValueError(f"stack_grids: expected {count} grids, got {k}")
    return out.permute(3, 0, 1, 2) if channels_last else out


def ray_span(o: torch.Tensor, d: torch.Tensor, extent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry (never before the ray's origin) and exit t of rays o + t d against the box."""
    t0, t1 = ray_box(o, d, extent)
    return t0.clamp_min(0), t1

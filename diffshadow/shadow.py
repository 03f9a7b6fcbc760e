"""Ground-truth shadow coefficients g(x, w) = exp(-∫_0^∞ μ(x + t w) dt)  (paper eq. 2).

Two ways to compute them (docs/design.md §3):

* `transmittance` marches each query point toward the light: trilinear scalar lookups classified by
  the transfer function (post-classification), midpoint rule on a fixed lattice of samples per point,
  optical depth accumulated (never a product of transmittances), early termination once the depth
  exceeds `TAU_MAX`, and empty macro-cells jumped over. Skipping only ever removes samples whose μ is
  exactly 0, so results with and without it agree to rounding.
* `shadow_grid(method="sweep")` works slice by slice along the light's dominant axis: it samples μ
  along sheared light-parallel lines (one line per in-plane lattice point, restricted to the bounding
  box of non-empty cells), accumulates optical depth along them with the trapezoid rule, and looks the
  depth up bilinearly at each voxel. Two interpolations in all, none repeated from slice to slice (a
  slice-to-slice recurrence smeared thin shadows over many voxels); the error left is that one lookup,
  largest right at sharp shadow edges (see `diffshadow bench shadow`).

Everything is torch and runs on CPU or CUDA through the same code.
"""

from __future__ import annotations

import itertools
import math
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import ArrayLike

from diffshadow.grid import (
    check_step,
    constant,
    go_on,
    lattice,
    lattice_axes,
    lattice_points_at,
    macro_cells,
    occupied_bounds,
    ray_box,
    trilinear,
)
from diffshadow.hpc import check_host_room
from diffshadow.lights import LightError, as_direction
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume, plane_slabs

DEFAULT_STEP = 0.5  # marcher step in voxels; bench shadow shows max error < 1e-3 on the test blob
DEFAULT_SWEEP_STEP = 1.0  # sweep slice spacing in voxels (1, 1/2, 1/4, ...)
TAU_MAX = 30.0  # optical depth past which a point counts as fully shadowed: exp(-30) ≈ 1e-13
MACRO_CELL = 8  # voxels per macro-cell edge for empty-space skipping
# Skipping costs a table lookup per sample; bench shadow: a net loss at 46 % empty cells (neghip, 0.93x),
# a gain from 90 % (hydrogen_atom 2.8x, bi2o3 4x). `skip_empty=None` turns it on from this fraction.
AUTO_SKIP_FRACTION = 0.5
SAMPLES_PER_ITER = 4  # lattice samples per point per marching iteration (amortises Python overhead)
CHUNK = 1 << 20  # samples held in memory at once on a GPU: fewer, larger launches
# On a CPU, samples per chunk: an iteration's (rays, S, 3) positions and gathers go through memory once per op, and
# in chunks this size the exact march took 0.78x the time of CHUNK at one thread, 0.76x at two (the same values;
# docs/performance.md, "The exact march"). Smaller chunks lose it again to the per-iteration ops.
CPU_CHUNK = 1 << 18


@dataclass
class ShadowField:
    """A volume and transfer function prepared on one device for shadow queries."""

    scalar: torch.Tensor  # (1, 1, Z, Y, X) float32 in [0, 1]
    extent: torch.Tensor  # (3,) box size (x, y, z)
    voxel_size: torch.Tensor  # (3,) box units per voxel (x, y, z)
    dims: torch.Tensor  # (3,) voxel counts (x, y, z)
    empty: torch.Tensor  # (cz, cy, cx) bool: macro-cell has μ = 0 everywhere
    cell: int
    tf: TransferFunction
    # Host copies of what every march reads, taken once here: read from the device at each call they were two
    # waits for it per call on a GPU.
    box: np.ndarray  # (3,) float64 box size (x, y, z)
    voxel: float  # the finest voxel edge in box units, as the float32 `voxel_size` holds it
    empty_share: float  # the share of macro-cells that are empty

    @classmethod
    def build(
        cls, volume: Volume, tf: TransferFunction, *, device: torch.device | str = "cpu", cell: int = MACRO_CELL
    ) -> ShadowField:
        if isinstance(cell, bool) or not isinstance(cell, int) or cell < 0 or cell & (cell - 1):
            raise ValueError(f"cell: expected 0 (no skipping) or a power of two of voxels, got {cell!r}")
        device = torch.device(device)
        scalar = torch.as_tensor(volume.data, dtype=torch.float32, device=device)[None, None]
        empty = (macro_cells(scalar[0, 0], tf, cell) if cell > 0
                 else torch.zeros(1, 1, 1, dtype=torch.bool, device=device))
        return cls(
            scalar=scalar,
            extent=torch.as_tensor(volume.extent, dtype=torch.float32, device=device),
            voxel_size=torch.as_tensor(volume.voxel_size, dtype=torch.float32, device=device),
            dims=torch.as_tensor(volume.dims, dtype=torch.float32, device=device),
            empty=empty,
            cell=cell,
            tf=tf,
            box=np.asarray(volume.extent, dtype=np.float64),
            voxel=float(np.min(np.asarray(volume.voxel_size, dtype=np.float32))),
            empty_share=float(empty.float().mean()),
        )

    def mu(self, pos_vox: torch.Tensor) -> torch.Tensor:
        """Extinction at (N, 3) positions in voxel coordinates (x, y, z) inside the grid → (N,)."""
        return self.tf.extinction(trilinear(self.scalar[0], pos_vox)[0])


def _as_points(points: torch.Tensor | ArrayLike, device) -> torch.Tensor:
    host = points.device if isinstance(points, torch.Tensor) else "cpu"
    pts = torch.as_tensor(points, dtype=torch.float32, device=host)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape (P, 3), got {tuple(pts.shape)}")
    if not torch.isfinite(pts).all():
        raise ValueError("points: must be finite")
    return pts.to(device)


def transmittance(
    volume: Volume | ShadowField,
    tf: TransferFunction,
    light_dir: ArrayLike,
    points: torch.Tensor | ArrayLike,
    *,
    step: float = DEFAULT_STEP,
    skip_empty: bool | None = None,
    tau_max: float = TAU_MAX,
    samples_per_iter: int = SAMPLES_PER_ITER,
    chunk: int | None = None,
    device: torch.device | str = "cpu",
    interrupt: Callable[[], bool] | None = None,
) -> torch.Tensor:
    """Shadow coefficient at each point (P, 3) for a light in direction `light_dir` → (P,) in [0, 1].

    `step` is in voxels (of the finest axis), no longer than the box's diagonal. Points outside the box are
    marched from where their ray enters it. `skip_empty` jumps over macro-cells whose μ is 0 under `tf` (None:
    when at least `AUTO_SKIP_FRACTION` of the cells are empty). `interrupt`, if given, is asked before every
    iteration; once it returns True the march ends with `grid.Interrupted` (the viewer gives up a light it has
    left). `chunk` is the samples held at once (None: `CPU_CHUNK` on a CPU, `CHUNK` elsewhere); it changes no
    value.
    """
    check_step(step)
    w64 = as_direction(light_dir)
    if device is None:
        device = points.device if isinstance(points, torch.Tensor) else "cpu"
    field = volume if isinstance(volume, ShadowField) else ShadowField.build(volume, tf, device=device)
    check_step(step, extent=field.box, voxel=field.voxel)
    pts = _as_points(points, field.scalar.device)
    w = torch.as_tensor(w64, dtype=torch.float32, device=pts.device)  # one direction, broadcast: no (P, 3) copy
    return _transmittance_rays(field, w, pts, step, skip_empty, tau_max, samples_per_iter, chunk, interrupt)


RAYS_PER_MARCH = 1 << 21  # rays marched together by transmittance_per_light (~120 MiB of per-ray state)


def transmittance_per_light(
    volume: Volume | ShadowField,
    tf: TransferFunction,
    lights: ArrayLike,
    points: torch.Tensor | ArrayLike,
    *,
    step: float = DEFAULT_STEP,
    skip_empty: bool | None = None,
    tau_max: float = TAU_MAX,
    samples_per_iter: int = SAMPLES_PER_ITER,
    chunk: int | None = None,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """The shadow of each light (L, 3) at its own points (L, P, 3), or at shared points (P, 3) → (L, P), on the
    field's device. The same values as `transmittance` light by light, marched together in groups of up to
    `RAYS_PER_MARCH` rays: one small march per light is launch-bound (2048 pool lights × 1024 points took 75 s
    on an H200, light by light)."""
    check_step(step)
    try:
        rows = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
    except (TypeError, ValueError):
        raise LightError(f"lights: expected (L, 3) directions, got {np.shape(lights)}") from None
    dirs = np.stack([as_direction(w, name=f"lights[{i}]") for i, w in enumerate(rows)]) if len(rows) else rows
    field = volume if isinstance(volume, ShadowField) else ShadowField.build(volume, tf, device=device)
    check_step(step, extent=field.box, voxel=field.voxel)
    if not isinstance(points, torch.Tensor):
        points = np.asarray(points, dtype=np.float32)
    shared = points.ndim != 3
    if not shared and len(points) != len(dirs):
        raise ValueError(f"points: expected one set per light ({len(dirs)}), got {len(points)}")
    n_points = len(points) if shared else points.shape[1]
    group = max(1, RAYS_PER_MARCH // max(n_points, 1))
    if shared:  # checked and moved once, not once per group
        points = _as_points(points, field.scalar.device)
    out = []
    for a in range(0, len(dirs), group):
        w_np = dirs[a:a + group]
        if shared:
            p = points.repeat(len(w_np), 1)
        else:
            p = _as_points(points[a:a + group].reshape(-1, 3), field.scalar.device)
        w = torch.as_tensor(w_np, dtype=torch.float32, device=p.device).repeat_interleave(n_points, 0)
        out.append(_transmittance_rays(field, w, p, step, skip_empty, tau_max, samples_per_iter, chunk)
                   .view(len(w_np), n_points))
    return torch.cat(out) if out else torch.zeros(0, n_points, device=field.scalar.device)


def _transmittance_rays(field: ShadowField, w: torch.Tensor, pts: torch.Tensor, step: float, skip_empty,
                        tau_max: float, samples_per_iter: int, chunk: int | None,
                        interrupt: Callable[[], bool] | None = None) -> torch.Tensor:
    """exp(-optical depth) from each point (R, 3) toward its light, w (R, 3) or one for all (3,)."""
    t0, t1 = ray_box(pts, w, field.extent)
    t0 = t0.clamp_min(0.0)
    length = (t1 - t0).clamp_min(0.0)
    dt = step * field.voxel
    # The lattice is anchored where the ray leaves the box and runs back toward the point, so every
    # point on one ray shares it: a nearer point's sum is a prefix of a farther one's, and shadows are
    # monotone along the light up to rounding. The last cell is partial and reuses its full cell's sample.
    n = torch.ceil(length / dt).to(torch.int64)
    last = length - (n - 1).clamp_min(0) * dt  # width of the last (partial) cell, in (0, dt]
    exit_vox = torch.where((n > 0)[:, None], (pts + t1.clamp(max=1e30)[:, None] * w) / field.voxel_size,
                           torch.zeros_like(pts))
    dq = (-w / field.voxel_size * dt).expand(len(pts), 3)  # voxel displacement per sample
    chunk = chunk or (CPU_CHUNK if pts.device.type == "cpu" else CHUNK)

    if skip_empty is None:
        skip_empty = field.empty_share >= AUTO_SKIP_FRACTION
    skip = bool(skip_empty) and field.cell > 0
    tau = torch.zeros(len(pts), dtype=torch.float32, device=pts.device)
    per_chunk = max(1, chunk // samples_per_iter)
    for start in range(0, len(pts), per_chunk):
        sl = slice(start, start + per_chunk)
        tau[sl] = _march_chunk(field, exit_vox[sl], dq[sl], dt, last[sl], n[sl], skip, tau_max, samples_per_iter,
                               interrupt)
    return torch.exp(-tau)


def _march_chunk(field: ShadowField, q0, dq, dt: float, last, n, skip: bool, tau_max: float,
                 S: int, interrupt: Callable[[], bool] | None = None) -> torch.Tensor:
    """Optical depth for one chunk of rays; sample j of a ray sits at q0 + (j + ½) dq and weighs dt,
    except the last (j = n - 1), which weighs `last`."""
    device = q0.device
    tau = torch.zeros(len(q0), dtype=torch.float32, device=device)
    k = torch.zeros(len(q0), dtype=torch.int64, device=device)
    offsets = torch.arange(S, device=device)
    # Rows are gathered by index (index_select, index_copy_), not by boolean masks: on a CPU aten::index gathers
    # 3-5x slower (the same values), and on a GPU every mask is a nonzero that waits for the device. An iteration
    # reads the host once (the rays still live), three times skipping empty cells (the occupied samples, the jumps).
    # Cells counted in float32: a power-of-two cell (ShadowField.build) divides exactly, so floor gives the cell
    # torch.div(..., rounding_mode="floor") gives, without its fmod, and the clamps run on 4-byte floats, not
    # int64 (a cell index is a small integer, exact in float32 until cast once): that line was 14% of a march
    # over a mostly empty 512³ volume, now 6% (docs/performance.md, "The exact march")
    last_cell, _, cell_stride = lattice(tuple(field.empty.shape), torch.float32, device)
    no_cell = constant((0.0, 0.0, 0.0), torch.float32, device)
    empty_flat = field.empty.reshape(-1)
    live = torch.nonzero(n > 0).squeeze(1)
    while live.numel():
        go_on(interrupt)
        n_live = n.index_select(0, live)
        k_live = k.index_select(0, live)
        kk = k_live[:, None] + offsets  # (L, S)
        in_range = kk < n_live[:, None]
        dq_live = dq.index_select(0, live)
        pos = q0.index_select(0, live)[:, None, :] + (kk[..., None] + 0.5) * dq_live[:, None, :]
        if skip:
            cidx = torch.clamp(torch.floor(pos / field.cell), min=no_cell, max=last_cell)
            empty = empty_flat.index_select(0, (cidx.long() * cell_stride).sum(dim=-1).view(-1)).view(kk.shape)
            occupied = in_range & ~empty
            mu = torch.zeros(kk.shape, dtype=torch.float32, device=device)
            at = torch.nonzero(occupied.view(-1)).squeeze(1)
            if at.numel():
                mu.view(-1).index_copy_(0, at, field.mu(pos.view(-1, 3).index_select(0, at)))
        else:  # every sample in range is occupied: μ at all, masked (clamped to the grid, finite past a ray's end)
            mu = torch.where(in_range, field.mu(pos.view(-1, 3)).view(kk.shape), 0.0)
        weight = torch.where(kk == n_live[:, None] - 1, last.index_select(0, live)[:, None], dt)
        tau_live = tau.index_select(0, live) + (mu * weight).sum(dim=1)
        tau.index_copy_(0, live, tau_live)
        k_next = k_live + S
        if skip:
            # The last sample sits in an empty cell: jump to the first lattice sample past its exit.
            jump = torch.nonzero(in_range[:, -1] & empty[:, -1]).squeeze(1)
            if jump.numel():
                p_last = pos[:, -1].index_select(0, jump)
                c_last = cidx[:, -1].index_select(0, jump).to(p_last.dtype)
                d = dq_live.index_select(0, jump)
                face = torch.where(d > 0, (c_last + 1) * field.cell, c_last * field.cell)
                steps = torch.where(d != 0, (face - p_last) / d, torch.full_like(d, math.inf))
                exit_u = (kk[:, -1].index_select(0, jump) + 0.5) + steps.min(dim=1).values.clamp_min(0)
                # 1e-3 of a sample of slack: never jump past a sample that might be in the next cell
                first = torch.ceil(exit_u - 0.5 - 1e-3).clamp(max=2**62).long()
                k_next.index_copy_(0, jump, torch.maximum(k_next.index_select(0, jump), first))
        k.index_copy_(0, live, k_next)
        live = live[(k_next < n_live) & (tau_live < tau_max)]
    return tau


def shadow_grid(
    volume: Volume,
    tf: TransferFunction,
    light_dir: ArrayLike,
    *,
    method: str = "sweep",
    step: float | None = None,
    device: torch.device | str = "cpu",
    voxels: torch.Tensor | None = None,
    **march_options: Any,
) -> torch.Tensor:
    """Shadow coefficient at every voxel → (Z, Y, X) float32.

    `method="march"`: `transmittance` at every voxel (the reference; its options too, `interrupt` among them);
    `step` in voxels, default `DEFAULT_STEP`; `voxels` (bool, the grid's shape), if given, the only voxels
    marched, the others 1 (`seen_voxels`: what a renderer reads). `method="sweep"`: the shear sweep; `step` is the
    sample spacing along the lines in slices and must be 1/k for an integer k (default 1).
    """
    w = as_direction(light_dir)
    if method == "march":
        if voxels is not None and (tuple(voxels.shape) != volume.data.shape or voxels.dtype != torch.bool):
            raise ValueError(f"voxels: expected a bool mask of shape {volume.data.shape}, got {voxels.dtype} "
                             f"{tuple(voxels.shape)}")
        field = ShadowField.build(volume, tf, device=device)
        where = field.scalar.device
        step = DEFAULT_STEP if step is None else step
        # The marched voxels' coordinates are made a slab of planes at a time (`volume.plane_slabs`): the whole
        # lattice's were 12 bytes a voxel (1.5 GiB at 512³, where `gt` marches 4 % of its voxels). Rays are
        # independent: the same values.
        axes = lattice_axes(volume, device=where)
        out = torch.ones(volume.data.size, dtype=torch.float32, device=where)
        mask = None if voxels is None else voxels.to(where)
        plane = volume.data.shape[1] * volume.data.shape[2]
        for sl in plane_slabs(volume.data.shape):
            first = sl.start * plane
            i = (torch.arange(first, sl.stop * plane, device=where) if mask is None
                 else torch.nonzero(mask[sl].flatten()).squeeze(1) + first)
            if len(i):
                out[i] = transmittance(field, tf, w, lattice_points_at(axes, i), step=step, **march_options)
        return out.view(volume.data.shape)
    if method == "sweep":
        if voxels is not None:
            march_options["voxels"] = voxels
        if march_options:
            raise TypeError(f"shadow_grid(method='sweep') takes no {sorted(march_options)}")
        return _sweep(volume, tf, w, DEFAULT_SWEEP_STEP if step is None else step, device)
    raise ValueError(f"method: expected 'march' or 'sweep', got {method!r}")


def seen_voxels(volume: Volume, tf: TransferFunction, factor: int = 1, device: torch.device | str = "cpu"
                ) -> torch.Tensor:
    """(Z, Y, X) bool on the volume refined `factor` times (`volume.refine`): the corners of every unit cell of
    `volume` where μ can be non-zero under `tf` (`grid.macro_cells`), as the fine grid's voxels. A renderer reads a
    shadow grid trilinearly at its samples and weighs it by the sample's opacity; a sample in any other cell has μ =
    0, so the shadow there is never seen: `shadow_grid(..., voxels=seen_voxels(...))` draws the same image.
    Judged on `volume` itself, not the refined grid, whose own cell ranges round differently."""
    scalar = torch.as_tensor(np.ascontiguousarray(volume.data), dtype=torch.float32, device=device)
    occupied = ~macro_cells(scalar, tf, 1)  # (Z-1, Y-1, X-1): unit cells, boundary voxels included
    for axis in range(3):
        occupied = occupied.repeat_interleave(factor, dim=axis)
    # a voxel is seen where any of the (up to) 8 cells it is a corner of is occupied: an OR of the padded cells'
    # 8 shifts, a byte a voxel (a float max-pool over them held 9 bytes a voxel, 1.1 GiB at 512³)
    padded = F.pad(occupied, (1, 1, 1, 1, 1, 1))
    seen = padded[1:, 1:, 1:].clone()
    for dz, dy, dx in itertools.product((0, 1), repeat=3):
        if dz or dy or dx:
            seen |= padded[1 - dz:padded.shape[0] - dz, 1 - dy:padded.shape[1] - dy, 1 - dx:padded.shape[2] - dx]
    return seen


def _sweep(volume: Volume, tf: TransferFunction, w: np.ndarray, step: float, device,
           block: int = 32) -> torch.Tensor:
    """Shear sweep: integrate μ along light-parallel lines, then interpolate τ back to the voxels.

    In (slice j, in-plane u) coordinates, with slice 0 facing the light, the ray from (j, u) toward the
    light crosses slice j - m at u + m·δ. Lines are indexed by c = u + j·δ, their crossing of slice 0.
    μ is sampled once along each line (trilinear, 0 outside the box), integrated cumulatively toward the
    light, and τ at a voxel is a bilinear lookup of its line's depth: two interpolations in all, none
    accumulated from slice to slice. Slices are processed in blocks to bound memory.
    """
    factor = round(1.0 / step) if step > 0 else 0
    if factor < 1 or abs(factor * step - 1.0) > 1e-9:
        raise ValueError(f"step: the sweep needs 1/k voxels for an integer k >= 1, got {step!r}")
    device = torch.device(device)
    if device.type == "cpu":  # a GPU's allocator raises an error of its own, which the CLI names
        grid_bytes = 4 * int(np.prod(volume.data.shape))
        check_host_room(int(SWEEP_GRIDS_AT_LEAST * grid_bytes), f"the sweep of a "
                        f"{'x'.join(map(str, volume.data.shape))} shadow grid ({SWEEP_GRIDS_AT_LEAST:g} x its "
                        f"{grid_bytes / 2**30:.1f} GiB)")
    s = torch.as_tensor(volume.data, dtype=torch.float32, device=device)
    box = _occupied_box(volume, tf, s)
    wv = w / volume.voxel_size  # voxels per box length along (x, y, z)
    a = int(np.argmax(np.abs(wv)))  # dominant axis (x=0, y=1, z=2)
    dim = 2 - a  # its array axis in (Z, Y, X)
    others = [i for i in range(3) if i != dim]
    order = [dim, *others]
    s = s.permute(order)
    flip = wv[a] > 0  # flip so the light lies toward slice 0
    if flip:
        s = s.flip(0)
    s = s.contiguous()
    n_j, n_u, n_v = s.shape
    delta = 1.0 / abs(wv[a])  # box length between neighbouring slices along w
    du, dv = (float(wv[2 - o] * delta) for o in others)  # in-plane shift per slice toward the light

    # Only the bounding box of the unit cells (2×2×2 voxels) where μ can be non-zero casts shadows: sample lines there
    # alone. τ is written in the volume's own layout through a view in the sweep's (slices up to jlo see no depth:
    # τ = 1), not made in the sweep's and then flipped and permuted into it: two grids fewer at the end. The box is
    # the volume's, found once (`_occupied_box`), in the sweep's axes: permuted, and its cells counted from the
    # other end along a flipped axis (n - 1 unit cells between n planes)
    bounds = None
    if box is not None:
        bounds = [box[o] for o in order]
        if flip:
            lo, hi = bounds[0]
            bounds[0] = (n_j - 1 - hi, n_j - 1 - lo)
    out = torch.ones(volume.data.shape, dtype=torch.float32, device=device)
    if bounds is not None:
        (jlo, jhi), (ulo, uhi), (vlo, vhi) = bounds
        _sweep_region(s, tf, delta, du, dv, (jlo, jhi), (ulo, uhi), (vlo, vhi), factor, block,
                      out.permute(order), flip)
    # A voxel on a face the light leaves through sees nothing (τ = 0 exactly); the bilinear lookup
    # would blend in the depth of lines just inside, where τ jumps.
    for axis_xyz, comp in enumerate(w):
        if comp != 0:
            index = out.shape[2 - axis_xyz] - 1 if comp > 0 else 0
            out.select(2 - axis_xyz, index).fill_(1.0)
    return out


# the last volume's occupied box: (volume, TF, device) by reference, and the box. A volume's lights are swept one
# after another (a subset's targets, the caches' grids, a viewer's lights), each needing the same box: at 512³
# finding it took 0.9-1.1 s of a light's ~3 s (one thread). Volumes and TFs are frozen; held weakly, so a volume
# dropped is not kept alive, and a new one at the same address is not taken for it
_last_box: tuple | None = None


def _occupied_box(volume: Volume, tf: TransferFunction, scalar: torch.Tensor) -> list[tuple[int, int]] | None:
    """`grid.occupied_bounds` of `volume` under `tf` in its own axes (`scalar`: its data as a tensor), found once
    for the sweeps of one volume."""
    global _last_box
    last = _last_box
    if last is not None and last[0]() is volume and last[1]() is tf and last[2] == scalar.device:
        return last[3]
    box = occupied_bounds(scalar, tf)
    _last_box = (weakref.ref(volume), weakref.ref(tf), scalar.device, box)
    return box


def _cumsum_slices(x: torch.Tensor) -> torch.Tensor:
    """torch.cumsum(x, 0). Under DIFFSHADOW_DETERMINISTIC=1 on CUDA torch refuses a floating-point cumsum (it has
    no deterministic kernel), so there the slices are summed one after another as the CPU sums them (in float64,
    rounded per slice): the CPU's bits."""
    if not (x.is_cuda and torch.are_deterministic_algorithms_enabled()):
        return torch.cumsum(x, 0)
    return _sequential_cumsum(x)


def _sequential_cumsum(x: torch.Tensor) -> torch.Tensor:
    out = torch.empty_like(x)
    acc = torch.zeros_like(x[0], dtype=torch.float64)
    for i in range(len(x)):
        acc = acc + x[i]
        out[i] = acc
    return out


# The sweep's peak above its caller, in grids of its output (a copy of the volume in the sweep's order, τ, the lines'
# depths): 2.93-3.60 on 511³ over four lights (axis-aligned and slanted), 3.3-6.0 on 400³ (its chunks' fixed
# ~0.3 GiB weigh more). A lower bound under all of them, so that the check before it refuses only what cannot fit.
SWEEP_GRIDS_AT_LEAST = 2.75
SWEEP_SAMPLES_PER_CALL = 1 << 21  # μ samples along the sweep's lines looked up at once (bounds its temporaries)


def _sweep_region(s, tf, delta, du, dv, jr, ur, vr, factor, block, out: torch.Tensor, flip: bool) -> None:
    """Write τ into `out` (the output, seen in the sweep's axis order; its slices in reverse where `flip`) at the
    slices past the region's first, jr[0]."""
    device = s.device
    n_j, n_u, n_v = s.shape
    jlo, jhi = jr
    # line lattice: every c = u + j·δ with u in the region and j in its slice range, one line of margin
    lattices = []
    for (lo, hi), d in ((ur, du), (vr, dv)):
        first = lo + min(jlo * d, jhi * d)
        last = hi + max(jlo * d, jhi * d)
        lattices.append(torch.arange(math.floor(first) - 1, math.ceil(last) + 2, device=device,
                                     dtype=torch.float32))
    c_u, c_v = lattices
    h = 1.0 / factor  # sample spacing along a line, in slices

    def mu_on_lines(j: torch.Tensor) -> torch.Tensor:
        """μ at fractional slices j (B,) along every line → (B, Cu, Cv); 0 outside the box."""
        u = c_u[None, :, None] - j[:, None, None] * du
        v = c_v[None, None, :] - j[:, None, None] * dv
        u, v = torch.broadcast_tensors(u, v)
        xyz = torch.stack([v, u, j[:, None, None].expand_as(u)], dim=-1)
        val = trilinear(s[None], xyz.view(-1, 3)).view(u.shape)
        inside = (u >= -1e-4) & (u <= n_u - 1 + 1e-4) & (v >= -1e-4) & (v <= n_v - 1 + 1e-4)
        return tf.extinction(val) * inside

    # τ at voxel (j, u, v) is line (u + j·δu, v + j·δv)'s depth at slice min(j, jhi); slices up to jlo see none.
    # Each block's line depths are summed on from the last row of the block before and read at once, so only one
    # block of them is held: keeping every slice's (on a slanted light up to 4x the grid, and as much again while
    # joined) had set the sweep's peak memory. The same blocks and sums as that, so the same bits.
    uu = torch.arange(n_u, device=device, dtype=torch.float32)
    vv = torch.arange(n_v, device=device, dtype=torch.float32)
    line_size = torch.tensor([len(c_v) - 1, len(c_u) - 1], device=device, dtype=torch.float32)
    last = torch.zeros(1, len(c_u), len(c_v), device=device)  # the lines' depth at the last slice summed: jlo's, 0
    mu_prev = mu_on_lines(torch.tensor([float(jlo)], device=device))[0]
    for j0 in range(jlo + 1, n_j, block):
        j1 = min(n_j, j0 + block)
        summed = min(jhi + 1, j1)  # slices j0..summed-1 lie in the region: their depths are summed here
        rows = last[:0]
        if j0 < summed:
            sub = torch.arange((j0 - 1) * factor + 1, (summed - 1) * factor + 1, device=device,
                               dtype=torch.float32) * h
            # (1 + G·factor, Cu, Cv), sampled a few slices at a time: one call's temporaries (its sample
            # coordinates, the trilinear lookup's corners) were ~2 grids' bytes on 511³; each sample is its own
            per_call = max(1, SWEEP_SAMPLES_PER_CALL // (len(c_u) * len(c_v)))
            mus = torch.cat([mu_prev[None], *(mu_on_lines(sub[i:i + per_call]) for i in range(0, len(sub), per_call))])
            trap = (0.5 * delta * h) * (mus[:-1] + mus[1:])  # trapezoid between sub-samples
            gaps = trap.view(summed - j0, factor, *trap.shape[1:]).sum(1)  # (G, Cu, Cv)
            rows = last + _cumsum_slices(gaps)
            last, mu_prev = rows[-1:], mus[-1]
            del mus, trap, gaps
        src = torch.cat([rows, last.expand(j1 - j0 - len(rows), -1, -1)])[:, None]  # past jhi: jhi's depth
        jb = torch.arange(j0, j1, device=device, dtype=torch.float32)
        cu = uu[None, :, None] + jb[:, None, None] * du - c_u[0]
        cv = vv[None, None, :] + jb[:, None, None] * dv - c_v[0]
        # each coordinate normalised where it varies, (B, 1, V) and (B, U, 1), and only then spread over (B, U, V, 2):
        # the same values, a quarter of the time (over the whole grid, the 2-long last axis vectorises poorly)
        gv, gu = torch.broadcast_tensors(cv / line_size[0] * 2 - 1, cu / line_size[1] * 2 - 1)
        grid = torch.stack([gv, gu], dim=-1)  # (B, U, V, 2)
        # zero padding is exact: the lattice's margin lines miss the region, so their depth is 0
        tau = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, 0]
        if flip:
            out[n_j - j1:n_j - j0] = torch.exp(-tau).flip(0)
        else:
            out[j0:j1] = torch.exp(-tau)

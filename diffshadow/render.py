"""The INR volume renderer (paper appendix, DESIGN.md §6): cameras, a wavefront ray marcher, macro-cells,
shading, and the naive secondary-ray baseline.

The wavefront marcher works on tiles of rays. For each tile, `Runs.build` turns every ray's crossings of
the macro-cell planes into runs of lattice samples t = t0 + (k + ½)·dt that lie in cells whose opacity
is not 0 under the transfer function (one vectorised pass, fixed shape). Then each iteration

1. every live ray takes its next occupied samples (one `searchsorted` into its runs);
2. one batched inference evaluates the scalar field there (the data INR or the raw grid), and the
   shadow source in the same pass (the shadow INR, a shadow grid, or secondary rays);
3. a shading/compositing step adds them front to back, with α = 1 − exp(−μ·Δt) (opacity corrected
   for the step, consistent with the shadow's optical depth);
4. rays out of samples or whose transmittance fell below `min_transmittance` leave.

`MarchPlan` sizes the work per device: every iteration drops finished rays and absent samples; a GPU takes
larger batches (fewer iterations, so fewer kernel launches). Memory is bounded by the plan's batch, never by pixels ×
samples. The naive baseline (`MarchedShadow`) pauses after step 2 and marches a secondary ray toward
the light from every sample through the same scalar field, with the same marcher.

With the fused SIRENs (`DIFFSHADOW_FUSED_SIREN`, unlit shading) there is no loop: per tile, after `Runs.build`,
one kernel marches every ray whole, steps 1-4 per sample in registers (`FusedSamples.march`; `naive`'s secondary
rays: `FusedExtinction.march`). A ray then stops at the first sample below `min_transmittance`, not at the end of
an iteration, which changes the image by less than that threshold.

Shading: colour × (0.1 + 0.9·g) with shadow coefficient g (the authors' code); with `phong=True` the
colour is first lit by Blinn-Phong from the field's gradient. `noshadow` has g = 1.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from diffshadow.fused import (
    COMPILE,
    PRECISIONS,
    FusedExtinction,
    FusedKernelError,
    FusedKernelWarning,
    FusedSamples,
    FusedSiren,
    FusedSirenError,
    fused_setting,
    sine_setting,
)
from diffshadow.fused import available as fused_available
from diffshadow.grid import cell_ranges, ray_span, trilinear
from diffshadow.lights import as_direction
from diffshadow.siren import FoldedSiren, Siren, WeightLayout, box_to_siren, fold, fold_flat
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume, refine

RENDER_CELL = 16  # voxels per macro-cell edge (the authors' renderer)
DEFAULT_STEP = 0.5  # primary and secondary step, in voxels of the finest axis
MIN_TRANSMITTANCE = 1e-3  # early ray termination
SHADOW_TAU_MAX = 10.0  # secondary rays stop here: g < 5e-5, below an 8-bit pixel's resolution
SAMPLES_PER_ITER = 8  # the fewest samples a live ray takes per iteration (more when fewer rays are live)
BATCH = 1 << 16  # samples per network inference on a CPU (2 cores, hydrogen_atom: 2^17 0.8x, 2^18 0.5x)
# On a GPU the frame's cost is mostly kernel launches (~250 per iteration, ~23 µs each on an H200): fewer, larger
# iterations win. Peak memory grows by ~1.1 KiB per sample of the batch (bench render: +1.13 GiB at 2^20).
CUDA_SAMPLE_BYTES = 1280
CUDA_BATCH_MIN, CUDA_BATCH_MAX = 1 << 18, 1 << 22
BACKGROUND = 1.0
AMBIENT, DIFFUSE, SPECULAR, SHININESS = 0.3, 0.7, 0.2, 32.0
MODES = ("noshadow", "gt", "inr", "naive")


class RenderError(ValueError):
    """Bad renderer input; the message names the argument."""


# ----------------------------------------------------------------------------------------------- cameras


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in box coordinates; `fov` is vertical, in degrees."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov: float = 60.0
    width: int = 128
    height: int = 128

    def __post_init__(self):
        if not (0 < self.fov < 180):
            raise RenderError(f"camera fov: expected degrees in (0, 180), got {self.fov}")
        if self.width < 1 or self.height < 1:
            raise RenderError(f"camera image size: expected positive, got {self.width}x{self.height}")
        forward = np.asarray(self.target, float) - np.asarray(self.eye, float)
        if not np.all(np.isfinite(forward)) or np.linalg.norm(forward) == 0:
            raise RenderError(f"camera: eye {self.eye} and target {self.target} must differ and be finite")

    @classmethod
    def look_at(cls, eye, target, *, up=(0.0, 0.0, 1.0), fov: float = 60.0, size: int | tuple[int, int] = 128):
        w, h = (size, size) if isinstance(size, int) else size
        return cls(tuple(map(float, eye)), tuple(map(float, target)), tuple(map(float, up)), float(fov), w, h)

    @classmethod
    def orbit(cls, extent, *, azimuth: float, elevation: float, distance: float = 2.2, fov: float = 60.0,
              size: int | tuple[int, int] = 128) -> Camera:
        """Looking at the box centre from (azimuth, elevation) in degrees; `distance` in box half-diagonals."""
        extent = np.asarray(extent, dtype=float)
        center = extent / 2
        az, el = math.radians(azimuth), math.radians(elevation)
        direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        eye = center + distance * np.linalg.norm(center) * direction
        up = (0.0, 0.0, 1.0) if abs(direction[2]) < 0.999 else (0.0, 1.0, 0.0)
        return cls.look_at(eye, center, up=up, fov=fov, size=size)

    def rays(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """Origins and unit directions (H·W, 3), row 0 at the top of the image."""
        eye = np.asarray(self.eye, float)
        fwd = np.asarray(self.target, float) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(self.up, float))
        if np.linalg.norm(right) < 1e-9:
            raise RenderError(f"camera: up {self.up} is parallel to the view direction")
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        half_h = math.tan(math.radians(self.fov) / 2)
        half_w = half_h * self.width / self.height
        # per pixel on the device, in float64 like the camera frame: made on the host, the directions of a 1024²
        # image took 42 ms here (numpy) and a copy, a third of a GPU frame
        f64 = {"dtype": torch.float64, "device": device}
        u = ((torch.arange(self.width, **f64) + 0.5) / self.width * 2 - 1) * half_w
        v = (1 - (torch.arange(self.height, **f64) + 0.5) / self.height * 2) * half_h
        fwd_t, right_t, up_t = (torch.as_tensor(x, **f64) for x in (fwd, right, up))
        d = fwd_t + u[None, :, None] * right_t + v[:, None, None] * up_t
        d = d / (d * d).sum(-1, keepdim=True).sqrt()
        dirs = d.reshape(-1, 3).to(torch.float32)
        origins = torch.as_tensor(eye, dtype=torch.float32, device=device).expand_as(dirs).contiguous()
        return origins, dirs


def default_views(extent, n: int, *, size: int = 128, elevation: float = 25.0, fov: float = 60.0) -> list[Camera]:
    """`n` orbit cameras evenly spaced in azimuth (the evaluation and rendering-loss views)."""
    return [Camera.orbit(extent, azimuth=30.0 + 360.0 * i / n, elevation=elevation, fov=fov, size=size)
            for i in range(n)]


# ------------------------------------------------------------------------------------------- macro-cells


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
    def build(cls, volume: Volume, tf: TransferFunction, *, cell: int = RENDER_CELL, ranges=None,
              device: torch.device | str = "cpu") -> MacroGrid:
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

    @classmethod
    def disabled(cls, volume: Volume, device: torch.device | str = "cpu") -> MacroGrid:
        one = torch.ones(1, 1, 1, device=device)
        return cls(one, one < 0, max(volume.dims), torch.as_tensor(volume.voxel_size, dtype=torch.float32,
                   device=device), torch.as_tensor(volume.dims, dtype=torch.float32, device=device))

    @property
    def empty_fraction(self) -> float:
        return float(self.empty.float().mean())

    def cell_of(self, p: torch.Tensor) -> torch.Tensor:
        """Integer cell (x, y, z) of box points (N, 3)."""
        c = torch.floor(p / self.voxel_size / self.cell).long()
        return torch.minimum(c.clamp_min(0), self.ncell - 1)

    def is_empty(self, c: torch.Tensor) -> torch.Tensor:
        return self.empty[c[:, 2], c[:, 1], c[:, 0]]


def front_to_back(alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Compositing weights (R, S) of samples seen through those before them, and what gets through (R,)."""
    before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    return before * alpha, (1 - alpha).prod(1)


# ------------------------------------------------------------------------------------------------ fields


class GridScalar:
    """The raw volume: trilinear value and (central-difference) gradient from one 4-channel lookup."""

    def __init__(self, volume: Volume, device: torch.device | str = "cpu"):
        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32, device=device)
        self.voxel = torch.as_tensor(volume.voxel_size, dtype=torch.float32, device=device)
        data = volume.data.astype(np.float64)
        spacing = volume.voxel_size  # (x, y, z)
        gz, gy, gx = np.gradient(data, spacing[2], spacing[1], spacing[0])
        stack = np.stack([data, gx, gy, gz]).astype(np.float32)
        self.channels = torch.as_tensor(stack, device=device)[None]  # (1, 4, Z, Y, X)

    def _lookup(self, p: torch.Tensor, channels: slice) -> torch.Tensor:
        return trilinear(self.channels[0, channels], p / self.voxel)

    def value(self, p: torch.Tensor) -> torch.Tensor:
        return self._lookup(p, slice(0, 1))[0]

    def value_and_grad(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self._lookup(p, slice(0, 4))
        return out[0], out[1:].t()


class InrScalar:
    """The data INR (a SIREN of the scalar field); gradients by autograd through the network. `fused`: the
    fused kernel's precision for values (`diffshadow.fused`), "compile" for the eager SIREN through torch.compile,
    None for the eager SIREN; `sine`: the fused kernel's sine (None: DIFFSHADOW_FUSED_SINE)."""

    def __init__(self, model: Siren, extent, device: torch.device | str = "cpu", fused: str | None = None,
                 sine: str | None = None):
        self.model = model.to(device).eval()
        for q in self.model.parameters():
            q.requires_grad_(False)
        self.extent = torch.as_tensor(np.asarray(extent), dtype=torch.float32, device=device)
        self.box = tuple(np.asarray(extent, dtype=float).tolist())  # on the host, to compare without a sync
        named, blocks = self.model.named_tensors(), self.model.cfg.blocks  # parameters without gradients
        self.fast = _fast_siren(named, blocks, fused, lambda: fold(named, blocks), sine)

    def value(self, p: torch.Tensor) -> torch.Tensor:
        return self.fast(box_to_siren(p, self.extent))

    def value_and_grad(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():
            p = p.detach().requires_grad_(True)
            s = self.model(box_to_siren(p, self.extent))
            (g,) = torch.autograd.grad(s.sum(), p)
        return s.detach(), g


def _fast_siren(named: dict, blocks: int, fused: str | None, layers, sine: str | None = None
                ) -> FusedSiren | FoldedSiren:
    """A SIREN for inference: the fused kernel in precision `fused` with `sine`, else the folded eager SIREN
    (`layers()`: its folded layers), through torch.compile for "compile". A SIREN the kernel cannot take (a width
    that is not a power of two >= 16) falls back to the eager one, with a warning: the setting is a speed-up, not
    a result."""
    if fused in PRECISIONS:
        try:
            return FusedSiren(named, blocks, fused, sine)
        except FusedSirenError as e:
            warnings.warn(f"DIFFSHADOW_FUSED_SIREN={fused}: {e}; using the eager SIREN", stacklevel=3)
    return FoldedSiren(layers(), compiled=fused == COMPILE)


class GridShadow:
    """Shadow coefficients looked up trilinearly in a (Z, Y, X) grid (`shadow_grid`'s output)."""

    def __init__(self, grid, extent, device: torch.device | str = "cpu"):
        self.grid = torch.as_tensor(grid, dtype=torch.float32, device=device)[None, None]
        self.extent = torch.as_tensor(np.asarray(extent), dtype=torch.float32, device=device)

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        g = box_to_siren(p, self.extent).view(1, 1, 1, -1, 3)
        return F.grid_sample(self.grid, g, mode="bilinear", padding_mode="border", align_corners=True).view(-1)


class SirenShadow:
    """A shadow INR (one flat weight vector in `layout`), evaluated in the same pass as the data INR."""

    def __init__(self, weights, layout: WeightLayout, blocks: int, extent, device: torch.device | str = "cpu",
                 fused: str | None = None, sine: str | None = None):
        w = torch.as_tensor(np.asarray(weights), dtype=torch.float32, device=device).reshape(1, -1)
        # eager: one SIREN with a leading K = 1, the batched matmuls of fitting, so the same values
        self.fast = _fast_siren({k: v[0] for k, v in layout.unflatten(w).items()}, blocks, fused,
                                lambda: fold_flat(w, layout, blocks), sine)
        self.batched = not isinstance(self.fast, FusedSiren)
        self.extent = torch.as_tensor(np.asarray(extent), dtype=torch.float32, device=device)
        self.box = tuple(np.asarray(extent, dtype=float).tolist())

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        x = box_to_siren(p, self.extent)
        return (self.fast(x[None])[0] if self.batched else self.fast(x)).clamp(0.0, 1.0)


# -------------------------------------------------------------------------------------- the wavefront loop


@dataclass
class Counters:
    primary_samples: int = 0  # samples sent to the network (after skipping)
    secondary_samples: int = 0
    iterations: int = 0  # the marcher's loop; with whole-ray kernels, the tiles of primary rays
    slots: int = 0  # whole-ray kernels: lanes' sample trips, primary rays (a tile runs until its last ray stops)


@dataclass(frozen=True)
class MarchPlan:
    """How the marcher sizes its work on one device (the images do not depend on it).

    Each iteration sends about `batch` samples to the network: every live ray takes the same number of
    samples, `batch` / live rays, at least `min_samples`. Every iteration drops finished rays and evaluates
    only the samples inside occupied cells (two host syncs per iteration). On an H200 that beat keeping
    shapes fixed between syncs (finished rays masked, absent samples evaluated and thrown away), which sent
    2.5x the samples to the networks: 1.45x faster at 512², 1.2x at 1024² (scripts/render_plans.py,
    docs/tuning.md). Rays are marched in tiles of `batch // min_samples`, so memory is bounded by the batch
    whatever the image size.
    """

    batch: int = BATCH
    min_samples: int = SAMPLES_PER_ITER
    max_samples: int = 256

    @classmethod
    def for_device(cls, device: torch.device, batch: int | None = None, min_samples: int | None = None) -> MarchPlan:
        default = cuda_batch(device) if device.type == "cuda" else BATCH
        return cls(batch=batch or default, min_samples=min_samples or SAMPLES_PER_ITER)

    @property
    def tile(self) -> int:
        return max(1, self.batch // self.min_samples)

    def samples_per_ray(self, live: int) -> int:
        return int(min(self.max_samples, max(self.min_samples, self.batch // max(live, 1))))


def cuda_batch(device: torch.device) -> int:
    """Samples per iteration on a GPU: the largest power of two whose batch takes at most 1/12 of the device's
    memory, within [2^18, 2^22] (80 GiB: 2^22, 40 GiB: 2^21, 8 GiB: 2^19)."""
    total = torch.cuda.get_device_properties(device).total_memory
    fits = max(1, total // 12 // CUDA_SAMPLE_BYTES)
    return min(CUDA_BATCH_MAX, max(CUDA_BATCH_MIN, 1 << (fits.bit_length() - 1)))


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
    def build(cls, o, d, t0, t1, dt: float, macro: MacroGrid | None) -> Runs:
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


def _march(o, d, t0, t1, dt: float, macro: MacroGrid | None, plan: MarchPlan, step, done) -> int:
    """March rays (R,) through their occupied samples. Per iteration, `step(rows, t, valid)` gets the
    live rows, their sample parameters t (R', n) and which samples exist; afterwards `done(rows)` says
    which rows have finished early (opaque, or optically deep). Returns the number of iterations."""
    iterations = 0
    for a in range(0, len(o), plan.tile):
        sl = slice(a, a + plan.tile)
        runs = Runs.build(o[sl], d[sl], t0[sl], t1[sl], dt, macro)
        rows = torch.nonzero(runs.total > 0).flatten()
        m = torch.zeros(len(o[sl]), dtype=runs.cum.dtype, device=o.device)
        left = int(runs.total.max()) if len(rows) else 0  # iterations bound: one host read per tile
        i = 0
        while len(rows) and left > 0:
            n = plan.samples_per_ray(len(rows))
            k, valid = runs.samples(rows, m[rows], n)
            rr = rows + a
            t = t0[rr, None] + (k + 0.5) * dt
            valid &= t < t1[rr, None]
            step(rr, t, valid)
            m[rows] += n
            left -= n
            i += 1
            rows = rows[(m[rows] < runs.total[rows]) & ~done(rr)]
        iterations += i
    return iterations


def _whole_rays(o, d, t0, t1, dt: float, macro: MacroGrid | None, plan: MarchPlan, march) -> tuple[int, int, int]:
    """March rays (R,) in tiles with a kernel that takes each ray from entry to stop: per tile, the runs of
    occupied samples (`Runs.build`), then `march(sl, runs)`, which returns the samples each ray took, the trips
    of each of its programs and their rays per program. Returns (tiles, samples, lane slots)."""
    samples = torch.zeros((), dtype=torch.int64, device=o.device)
    slots = torch.zeros((), dtype=torch.int64, device=o.device)
    tiles = 0
    for a in range(0, len(o), plan.tile):
        sl = slice(a, a + plan.tile)
        count, trips, block = march(sl, Runs.build(o[sl], d[sl], t0[sl], t1[sl], dt, macro))
        samples += count.sum()
        slots += trips.sum() * block
        tiles += 1
    return tiles, int(samples), int(slots)  # the frame's only host reads, at its end


def shading_name(phong: bool) -> str:
    """How the image modes shade a sample (what a report states beside image metrics)."""
    return "Blinn-Phong" if phong else "unlit (colour x (0.1 + 0.9 g))"


@dataclass
class Shading:
    phong: bool = False
    background: float = BACKGROUND


def _shade(rgb: torch.Tensor, grad, g, view_dir, light: torch.Tensor, shading: Shading) -> torch.Tensor:
    """Sample colour: the TF's colour `rgb`, Blinn-Phong lit when asked, times (0.1 + 0.9·g) when there is a
    shadow."""
    if shading.phong:
        n = grad / grad.norm(dim=1, keepdim=True).clamp_min(1e-6)
        h = light[None] - view_dir
        h = h / h.norm(dim=1, keepdim=True).clamp_min(1e-6)
        diffuse = (n @ light).abs()
        specular = (n * h).sum(1).abs() ** SHININESS
        rgb = rgb * (AMBIENT + DIFFUSE * diffuse)[:, None] + SPECULAR * specular[:, None]
    if g is not None:
        rgb = rgb * (0.1 + 0.9 * g)[:, None]
    return rgb.clamp(0.0, 1.0)


class MarchedShadow:
    """The naive baseline: a secondary ray toward the light from every sample, marched through `scalar`
    by the same marcher as the primary rays (empty cells skipped, stopped at optical depth `tau_max`)."""

    def __init__(self, scalar, tf: TransferFunction, extent, voxel: float, *, step: float = DEFAULT_STEP,
                 macro: MacroGrid | None = None, tau_max: float | None = None,
                 samples_per_iter: int | None = None, batch: int | None = None, whole_rays: bool = True):
        self.scalar, self.tf, self.macro, self.whole_rays = scalar, tf, macro, whole_rays
        self.extent = torch.as_tensor(np.asarray(extent), dtype=torch.float32, device="cpu")
        self.dt = step * voxel
        self.tau_max = SHADOW_TAU_MAX if tau_max is None else tau_max
        self.min_samples, self.batch = samples_per_iter, batch
        self.light: torch.Tensor | None = None
        self.counters: Counters | None = None
        # with a fused data INR, each secondary sample's extinction in one kernel: the same treatment as `inr`'s
        # primary samples (FusedSamples), so the baseline is as optimised as ours
        self.fused = (FusedExtinction(scalar.fast, scalar.extent, tf.optics_knots(scalar.extent.device),
                                      tf.density_scale)
                      if isinstance(scalar, InrScalar) and isinstance(scalar.fast, FusedSiren) else None)

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        device = p.device
        plan = MarchPlan.for_device(device, self.batch, self.min_samples)
        d = self.light.to(device).expand(len(p), 3).contiguous()
        _, t1 = ray_span(p, d, self.extent.to(device))
        t0 = torch.zeros_like(t1)
        tau = torch.zeros_like(t1)
        if self.fused is not None and self.whole_rays:
            def march(sl, runs):
                tau[sl], count, trips = self.fused.march(p[sl], d[sl], t0[sl], t1[sl], runs, self.dt, self.tau_max)
                return count, trips, self.fused.block

            samples = _whole_rays(p, d, t0, t1, self.dt, self.macro, plan, march)[1]
            if self.counters is not None:
                self.counters.secondary_samples += samples
            return torch.exp(-tau)

        def step(rows, t, valid):
            pts = (p[rows, None] + t[..., None] * d[rows, None]).view(-1, 3)
            idx = torch.nonzero(valid.view(-1)).flatten()
            if self.counters is not None:
                self.counters.secondary_samples += len(idx)
            if self.fused is not None:
                mu = torch.zeros(valid.numel(), device=device).index_copy_(0, idx, self.fused(pts[idx]))
                tau[rows] += mu.view(valid.shape).sum(1) * self.dt  # absent samples are 0 already
                return
            s = torch.zeros(valid.numel(), device=device).index_copy_(0, idx, self.scalar.value(pts[idx]))
            tau[rows] += (self.tf.extinction(s.view(valid.shape)) * valid).sum(1) * self.dt

        _march(p, d, t0, t1, self.dt, self.macro, plan, step, lambda rows: tau[rows] >= self.tau_max)
        return torch.exp(-tau)


@dataclass
class Image:
    rgb: torch.Tensor  # (H, W, 3) composited over the background
    alpha: torch.Tensor  # (H, W) accumulated opacity
    seconds: float
    counters: Counters = field(default_factory=Counters)

    def to_uint8(self) -> np.ndarray:
        return (self.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def render(
    camera: Camera,
    scalar,
    tf: TransferFunction,
    extent,
    voxel: float,
    *,
    light=None,
    shadow=None,
    shading: Shading | None = None,
    step: float = DEFAULT_STEP,
    macro: MacroGrid | None = None,
    min_transmittance: float = MIN_TRANSMITTANCE,
    samples_per_iter: int | None = None,
    batch: int | None = None,
    whole_rays: bool = True,
    device: torch.device | str = "cpu",
) -> Image:
    """Render one image with the wavefront marcher.

    `scalar`: `GridScalar` or `InrScalar`. `shadow`: None (no shadow), `GridShadow`, `SirenShadow` or
    `MarchedShadow`; `light` (toward the light) is needed for a shadow or Phong. `voxel` is the
    finest voxel size in box units; `step` is in voxels. `whole_rays`: where both fields are fused SIRENs and
    shading is unlit, march each ray from entry to stop in one kernel (`FusedSamples.march`) instead of the
    wavefront loop. A ray then stops at the first sample that takes its transmittance below
    `min_transmittance`, not at the end of a wavefront iteration: the images differ by less than that.
    """
    shading = shading or Shading()
    if step <= 0 or not math.isfinite(step):
        raise RenderError(f"step: expected a positive number of voxels, got {step}")
    if batch is not None and batch < (samples_per_iter or SAMPLES_PER_ITER):
        raise RenderError(f"batch: expected at least samples_per_iter ({samples_per_iter or SAMPLES_PER_ITER}), "
                          f"got {batch}")
    w = None
    if shadow is not None or shading.phong:
        if light is None:
            raise RenderError("light: a light direction is needed for shadows and Phong shading")
        w = torch.as_tensor(as_direction(light), dtype=torch.float32, device=device)
    counters = Counters()
    if isinstance(shadow, MarchedShadow):
        shadow.light, shadow.counters = w, counters
    plan = MarchPlan.for_device(torch.device(device), batch, samples_per_iter)
    start = time.perf_counter()
    extent_t = torch.as_tensor(np.asarray(extent), dtype=torch.float32, device=device)
    o, d = camera.rays(device)
    t0, t1 = ray_span(o, d, extent_t)
    dt = step * voxel
    trans = torch.ones(len(o), device=device)
    color = torch.zeros(len(o), 3, device=device)

    fused = _fused_samples(scalar, shadow, tf, dt, shading)
    if fused is not None and whole_rays:
        def march(sl, runs):
            trans[sl], color[sl], count, trips = fused.march(o[sl], d[sl], t0[sl], t1[sl], runs, min_transmittance)
            return count, trips, fused.block

        counters.iterations, counters.primary_samples, counters.slots = _whole_rays(o, d, t0, t1, dt, macro, plan,
                                                                                    march)
        return _image(camera, color, trans, shading, start, counters)

    def composite(rows, t, valid):
        pts = (o[rows, None] + t[..., None] * d[rows, None]).view(-1, 3)
        idx = torch.nonzero(valid.view(-1)).flatten()
        flat = pts[idx]
        counters.primary_samples += len(flat)
        if len(flat) == 0:
            return
        if fused is not None:
            a, c = fused(flat)
        else:
            s, grad = scalar.value_and_grad(flat) if shading.phong else (scalar.value(flat), None)
            g = shadow(flat) if shadow is not None else None
            view = None
            if shading.phong:
                view = d[rows, None].expand(*valid.shape, 3).reshape(-1, 3)[idx]
            mu, rgb = tf.optics(s)
            a = 1 - torch.exp(-mu * dt)
            c = _shade(rgb, grad, g, view, w, shading)
        alpha = torch.zeros(valid.numel(), device=device).index_copy_(0, idx, a)
        rgb = torch.zeros(valid.numel(), 3, device=device).index_copy_(0, idx, c)
        weight, through = front_to_back(alpha.view(valid.shape))
        color[rows] += ((trans[rows, None] * weight)[..., None] * rgb.view(*valid.shape, 3)).sum(1)
        trans[rows] *= through

    counters.iterations = _march(o, d, t0, t1, dt, macro, plan, composite,
                                 lambda rows: trans[rows] < min_transmittance)
    return _image(camera, color, trans, shading, start, counters)


def _image(camera: Camera, color, trans, shading: Shading, start: float, counters: Counters) -> Image:
    out = color + trans[:, None] * shading.background
    h, w = camera.height, camera.width
    return Image(out.view(h, w, 3), (1 - trans).view(h, w), time.perf_counter() - start, counters)


def _fused_samples(scalar, shadow, tf: TransferFunction, dt: float, shading: Shading) -> FusedSamples | None:
    """The primary samples' step as one kernel where both fields are fused SIRENs on one box and shading is
    unlit (Phong needs the field's gradient, by autograd); None: the eager step."""
    if shading.phong or not (isinstance(scalar, InrScalar) and isinstance(scalar.fast, FusedSiren)):
        return None
    if shadow is not None and not (isinstance(shadow, SirenShadow) and isinstance(shadow.fast, FusedSiren)
                                   and shadow.box == scalar.box):
        return None
    return FusedSamples(scalar.fast, shadow.fast if shadow is not None else None, scalar.extent,
                        tf.optics_knots(scalar.extent.device), tf.density_scale, dt)


def render_all_at_once(camera: Camera, scalar, tf: TransferFunction, extent, voxel: float, *, light=None,
                       shadow=None, shading: Shading | None = None, step: float = DEFAULT_STEP,
                       device: torch.device | str = "cpu") -> Image:
    """The straightforward reference: every lattice sample of every ray at once, no skipping, no early
    termination. Memory grows with pixels × samples: for tests on small images only."""
    shading = shading or Shading()
    w = torch.as_tensor(as_direction(light), dtype=torch.float32, device=device) if light is not None else None
    if isinstance(shadow, MarchedShadow):
        shadow.light = w
    start = time.perf_counter()
    extent_t = torch.as_tensor(np.asarray(extent), dtype=torch.float32, device=device)
    o, d = camera.rays(device)
    t0, t1 = ray_span(o, d, extent_t)
    dt = step * voxel
    n = int(torch.ceil(((t1 - t0).clamp_min(0) / dt).max()).item()) + 1
    t = t0[:, None] + (torch.arange(n, device=device) + 0.5) * dt
    valid = t < t1[:, None]
    pts = o[:, None] + t[..., None] * d[:, None]
    flat = pts[valid]
    s, grad = scalar.value_and_grad(flat) if shading.phong else (scalar.value(flat), None)
    g = shadow(flat) if shadow is not None else None
    alpha = torch.zeros(valid.shape, device=device)
    rgb = torch.zeros(*valid.shape, 3, device=device)
    alpha[valid] = 1 - torch.exp(-tf.extinction(s) * dt)
    rgb[valid] = _shade(tf.color(s), grad, g, d[:, None].expand_as(pts)[valid], w, shading)
    weight, trans = front_to_back(alpha)
    color = (weight[..., None] * rgb).sum(1)
    out = color + trans[:, None] * shading.background
    return Image(out.view(camera.height, camera.width, 3), (1 - trans).view(camera.height, camera.width),
                 time.perf_counter() - start)


# ------------------------------------------------------------------------------------------------ modes


class RenderScene:
    """One volume, its TF and (optionally) its data INR on one device, with the per-mode pieces cached.

    Modes: `noshadow`; `gt` (scalar and shadow from the raw volume; shadow by `shadow_grid`, on the volume
    refined `gt_upsample` times); `inr`
    (shadow INR co-rendered with the scalar field: ours); `naive` (secondary rays through the scalar
    field). `scalar="inr"` renders the data INR, `"grid"` the raw volume (to isolate the shadow's error).
    """

    def __init__(self, volume: Volume, tf: TransferFunction, data_inr=None, *, device: torch.device | str = "cpu",
                 gt_method: str = "march", gt_upsample: int = 1, cell: int = RENDER_CELL):
        self.volume, self.tf, self.data_inr = volume, tf, data_inr
        self.device = torch.device(device)
        # the SIRENs' kernel for values: DIFFSHADOW_FUSED_SIREN where it runs on this device, else eager
        setting = fused_setting()
        self.fused = setting if setting and fused_available(self.device, setting) else None
        # and its sine: read here so a bad DIFFSHADOW_FUSED_SINE stops the run instead of falling back
        self.sine = sine_setting() if self.fused in PRECISIONS else None
        self.gt_method, self.gt_upsample, self.cell = gt_method, gt_upsample, cell
        self.voxel = float(np.min(volume.voxel_size))
        self._cache: dict = {}

    def _cached(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def scalar(self, source: str):
        if source == "grid":
            return self._cached("grid", lambda: GridScalar(self.volume, self.device))
        if source == "inr":
            if self.data_inr is None:
                raise RenderError("scalar 'inr' needs a data INR (train_data_inr's data_inr.pt)")
            return self._cached(("inr", self.fused, self.sine), lambda: InrScalar(
                self.data_inr.model, self.volume.extent, self.device, self.fused, self.sine))
        raise RenderError(f"scalar: expected 'grid' or 'inr', got {source!r}")

    def macro(self, source: str, skip: bool) -> MacroGrid | None:
        if not skip:
            return None
        ranges = None
        if source == "inr":
            ranges = (self.data_inr.cell_lo, self.data_inr.cell_hi)
            if ranges[0] is None or self.cell != RENDER_CELL:
                from diffshadow.data_inr import inr_cell_ranges

                ranges = self._cached(("ranges", self.cell), lambda: inr_cell_ranges(
                    self.data_inr.model, self.volume, cell=self.cell, device=self.device))
        return self._cached(("macro", source), lambda: MacroGrid.build(self.volume, self.tf, cell=self.cell,
                                                                     ranges=ranges, device=self.device))

    @staticmethod
    def _gt_key(light) -> tuple:
        return ("gt", tuple(np.round(as_direction(light), 12).tolist()))

    def forget_gt(self, light) -> None:
        """Drop the cached shadow grid of `light` (a loop over many lights need not keep them all)."""
        self._cache.pop(self._gt_key(light), None)

    def gt_shadow(self, light) -> GridShadow:
        from diffshadow.shadow import shadow_grid

        key = self._gt_key(light)
        w = key[1]
        fine = self._cached("gt_volume", lambda: refine(self.volume, self.gt_upsample))
        return self._cached(key, lambda: GridShadow(
            shadow_grid(fine, self.tf, w, method=self.gt_method, device=self.device), self.volume.extent, self.device))

    def render(self, mode: str, camera: Camera, *, light=None, siren=None, scalar: str | None = None,
               phong: bool = False, step: float = DEFAULT_STEP, skip: bool = True, batch: int | None = None,
               samples_per_iter: int | None = None, min_transmittance: float = MIN_TRANSMITTANCE,
               background: float = BACKGROUND, whole_rays: bool = True) -> Image:
        """`siren`: (weights, layout, blocks) of the shadow INR, for mode `inr`. `whole_rays`: see `render`
        (with fused SIRENs only; for `naive`, its secondary rays). A fused kernel that fails to compile leaves
        this scene on the eager SIREN, with a warning: the setting is a speed-up, not a result."""
        kw = {"light": light, "siren": siren, "scalar": scalar, "phong": phong, "step": step, "skip": skip,
              "batch": batch, "samples_per_iter": samples_per_iter, "min_transmittance": min_transmittance,
              "background": background, "whole_rays": whole_rays}
        try:
            return self._render(mode, camera, **kw)
        except FusedKernelError as e:
            warnings.warn(f"DIFFSHADOW_FUSED_SIREN={self.fused}: {e}; rendering with the eager SIREN from now on",
                          FusedKernelWarning, stacklevel=2)
            self.fused = self.sine = None
            return self._render(mode, camera, **kw)

    def _render(self, mode: str, camera: Camera, *, light, siren, scalar, phong, step, skip, batch,
                samples_per_iter, min_transmittance, background, whole_rays) -> Image:
        if mode not in MODES:
            raise RenderError(f"mode: expected one of {MODES}, got {mode!r}")
        if scalar is None:
            scalar = "grid" if mode == "gt" or self.data_inr is None else "inr"
        if mode == "gt":
            scalar = "grid"
        field_ = self.scalar(scalar)
        macro = self.macro(scalar, skip)
        shadow = None
        if mode != "noshadow" and light is None:
            raise RenderError(f"mode {mode!r}: needs a light direction")
        if mode == "gt":
            shadow = self.gt_shadow(light)
        elif mode == "inr":
            if siren is None:
                raise RenderError("mode 'inr': needs the shadow INR's weights")
            weights, layout, blocks = siren
            shadow = SirenShadow(weights, layout, blocks, self.volume.extent, self.device, self.fused, self.sine)
        elif mode == "naive":
            shadow = MarchedShadow(field_, self.tf, self.volume.extent, self.voxel, step=step, macro=macro,
                                   samples_per_iter=samples_per_iter, batch=batch, whole_rays=whole_rays)
        with torch.no_grad():
            return render(camera, field_, self.tf, self.volume.extent, self.voxel, light=light, shadow=shadow,
                          shading=Shading(phong=phong, background=background), step=step, macro=macro,
                          min_transmittance=min_transmittance, samples_per_iter=samples_per_iter, batch=batch,
                          whole_rays=whole_rays, device=self.device)


def write_png(path, image: Image) -> None:
    """An 8-bit RGB PNG, written atomically."""
    from PIL import Image as PILImage

    from diffshadow.io import atomic_save

    atomic_save(path, lambda tmp: PILImage.fromarray(image.to_uint8()).save(tmp, format="PNG"), suffix=".png")

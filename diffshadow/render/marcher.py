"""The wavefront ray marcher (paper appendix, docs/design.md §3), shading, and the naive secondary-ray baseline.

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

With the fused SIRENs (`render.kernel: fused`, unlit shading) there is no loop: per tile, after `Runs.build`,
one kernel marches every ray whole, steps 1-4 per sample in registers (`FusedSamples.march`; `naive`'s secondary
rays: `FusedExtinction.march`). A ray then stops at the first sample below `min_transmittance`, not at the end of
an iteration, which changes the image by less than that threshold.

Shading: colour × (0.1 + 0.9·g) with shadow coefficient g (the authors' code); with `phong=True` the
colour is first lit by Blinn-Phong from the field's gradient. `noshadow` has g = 1.

A frame can be given up part-way (`interrupt`, asked before every iteration or tile; `grid.Interrupted`): a 480² frame
takes tens of seconds on 2 CPU cores, and the viewer must answer a moved light sooner (docs/performance.md).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.grid import box, check_step, go_on, ray_span
from diffshadow.lights import as_direction
from diffshadow.render.camera import Camera, RenderError
from diffshadow.render.cells import MacroGrid, Runs
from diffshadow.render.fields import GridScalar, GridShadow, InrScalar, SirenShadow
from diffshadow.render.fused import FusedExtinction, FusedSamples, FusedSiren
from diffshadow.transfer import TransferFunction

Scalar = GridScalar | InrScalar  # what the rays sample the scalar field from

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


def front_to_back(alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Compositing weights (R, S) of samples seen through those before them, and what gets through (R,)."""
    before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    return before * alpha, (1 - alpha).prod(1)


@dataclass
class Counters:
    primary_samples: int = 0  # samples sent to the network (after skipping)
    secondary_samples: int = 0
    iterations: int = 0  # the marcher's loop; with whole-ray kernels, the tiles of primary rays
    slots: int = 0  # whole-ray kernels: lanes' sample trips, primary rays (a tile runs until its last ray stops)


@dataclass(frozen=True)
class MarchPlan:
    """How the marcher sizes its work on one device. A ray stops at the end of an iteration, so the images of two
    plans differ by less than the stopping threshold (`min_transmittance`).

    Each iteration sends about `batch` samples to the network: every live ray takes the same number of
    samples, `batch` / live rays, at least `min_samples`. Every iteration drops finished rays and evaluates
    only the samples inside occupied cells (two host syncs per iteration). On an H200 that beat keeping
    shapes fixed between syncs (finished rays masked, absent samples evaluated and thrown away), which sent
    2.5x the samples to the networks: 1.45x faster at 512², 1.2x at 1024² (scripts/render_plans.py,
    docs/performance.md). Rays are marched in tiles of `batch // min_samples`, so memory is bounded by the batch
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


def _march(o, d, t0, t1, dt: float, macro: MacroGrid | None, plan: MarchPlan, step, done,
           interrupt: Callable[[], bool] | None = None) -> int:
    """March rays (R,) through their occupied samples. Per iteration, `step(rows, t, valid)` gets the
    live rows, their sample parameters t (R', n) and which samples exist; afterwards `done(rows)` says
    which rows have finished early (opaque, or optically deep). Returns the number of iterations. `interrupt`
    is asked before each iteration (`Interrupted`)."""
    iterations = 0
    for a in range(0, len(o), plan.tile):
        sl = slice(a, a + plan.tile)
        runs = Runs.build(o[sl], d[sl], t0[sl], t1[sl], dt, macro)
        rows = torch.nonzero(runs.total > 0).flatten()
        m = torch.zeros(len(o[sl]), dtype=runs.cum.dtype, device=o.device)
        left = int(runs.total.max()) if len(rows) else 0  # iterations bound: one host read per tile
        i = 0
        while len(rows) and left > 0:
            go_on(interrupt)
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


def _whole_rays(o, d, t0, t1, dt: float, macro: MacroGrid | None, plan: MarchPlan, march,
                interrupt: Callable[[], bool] | None = None) -> tuple[int, int, int]:
    """March rays (R,) in tiles with a kernel that takes each ray from entry to stop: per tile, the runs of
    occupied samples (`Runs.build`), then `march(sl, runs)`, which returns the samples each ray took, the trips
    of each of its programs and their rays per program. Returns (tiles, samples, lane slots). `interrupt` is
    asked before each tile (`Interrupted`)."""
    samples = torch.zeros((), dtype=torch.int64, device=o.device)
    slots = torch.zeros((), dtype=torch.int64, device=o.device)
    tiles = 0
    for a in range(0, len(o), plan.tile):
        go_on(interrupt)
        sl = slice(a, a + plan.tile)
        count, trips, block = march(sl, Runs.build(o[sl], d[sl], t0[sl], t1[sl], dt, macro))
        samples += count.sum()
        slots += trips.sum() * block
        tiles += 1
    return tiles, int(samples), int(slots)  # the frame's only host reads, at its end


@dataclass
class Samples:
    """A frame's primary samples with everything about them that no light changes: per iteration of the
    marcher, its rows, which of their slots held a sample (`idx`, int32), the samples' points and scalar values,
    and each slot's compositing weight (what gets through times the sample's opacity); ~26 bytes a sample.
    Under another light only the shadow at the points differs, so `render(..., samples=)` draws the same view
    from them with the shadow source and the TF's colour alone, through the same operations in the same order:
    the image the full march draws, to the byte. Kept for unlit shading on the wavefront path (with the fused
    kernels each ray is marched whole in one kernel)."""

    steps: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]  # rows, idx, flat, s, tw
    trans: torch.Tensor  # (R,) what gets through each ray
    primary_samples: int
    iterations: int
    nbytes: int  # what they hold on the device


class _Arena:
    """Tensors copied into a few large blocks as they are kept. Kept where they were made, each a small block left
    among the march's freed temporaries, they split the heap's free space: 480² nucleon frames in the viewer
    (`ViewerScene.frame`, 2 CPU cores) peaked at 1,330 MiB with 298 MiB kept, 779-817 MiB with 320 MiB kept in
    blocks, against 535 MiB keeping nothing."""

    FIRST, LARGEST = 1 << 20, 32 << 20  # each block twice the last: a small frame wastes little, a large one few

    def __init__(self, device: torch.device):
        self.device, self.chunks, self.used = device, [], 0

    @property
    def nbytes(self) -> int:
        return sum(c.numel() for c in self.chunks)

    def put(self, t: torch.Tensor) -> torch.Tensor:
        n = t.numel() * t.element_size()
        if not self.chunks or self.used + n > self.chunks[-1].numel():
            size = min(2 * self.chunks[-1].numel(), self.LARGEST) if self.chunks else self.FIRST
            self.chunks.append(torch.empty(max(size, n), dtype=torch.uint8, device=self.device))
            self.used = 0
        out = self.chunks[-1][self.used:self.used + n].view(t.dtype).view(t.shape).copy_(t)
        self.used += -(-n // 64) * 64  # the next one aligned for any dtype
        return out


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

    def __init__(self, scalar: Scalar, tf: TransferFunction, extent: ArrayLike, voxel: float, *,
                 step: float = DEFAULT_STEP, macro: MacroGrid | None = None, tau_max: float | None = None,
                 samples_per_iter: int | None = None, batch: int | None = None, device: torch.device | str = "cpu"):
        self.scalar, self.tf, self.macro = scalar, tf, macro
        # on the device once per scene (a frame makes its own MarchedShadow): copied anew, it made a GPU wait
        self.extent = box(extent, device)
        self.dt = step * voxel
        self.tau_max = SHADOW_TAU_MAX if tau_max is None else tau_max
        self.min_samples, self.batch = samples_per_iter, batch
        self.light: torch.Tensor | None = None
        self.counters: Counters | None = None
        self.interrupt: Callable[[], bool] | None = None  # the frame's (`render` sets all three)
        # with a fused data INR, whole secondary rays in one kernel: the same treatment as `inr`'s primary rays
        # (FusedSamples.march), so the baseline is as optimised as ours
        self.fused = (FusedExtinction(scalar.fast, scalar.extent, tf.optics_knots(scalar.extent.device),
                                      tf.density_scale)
                      if isinstance(scalar, InrScalar) and isinstance(scalar.fast, FusedSiren) else None)

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        device = p.device
        plan = MarchPlan.for_device(device, self.batch, self.min_samples)
        d = self.light.to(device).expand(len(p), 3).contiguous()
        _, t1 = ray_span(p, d, self.extent)
        t0 = torch.zeros_like(t1)
        tau = torch.zeros_like(t1)
        if self.fused is not None:
            def march(sl, runs):
                tau[sl], count, trips = self.fused.march(p[sl], d[sl], t0[sl], t1[sl], runs, self.dt, self.tau_max)
                return count, trips, self.fused.block

            samples = _whole_rays(p, d, t0, t1, self.dt, self.macro, plan, march, self.interrupt)[1]
            if self.counters is not None:
                self.counters.secondary_samples += samples
            return torch.exp(-tau)

        def step(rows, t, valid):
            pts = (p[rows, None] + t[..., None] * d[rows, None]).view(-1, 3)
            idx = torch.nonzero(valid.view(-1)).flatten()
            if self.counters is not None:
                self.counters.secondary_samples += len(idx)
            s = torch.zeros(valid.numel(), device=device).index_copy_(0, idx, self.scalar.value(pts[idx]))
            tau[rows] += (self.tf.extinction(s.view(valid.shape)) * valid).sum(1) * self.dt

        _march(p, d, t0, t1, self.dt, self.macro, plan, step, lambda rows: tau[rows] >= self.tau_max, self.interrupt)
        return torch.exp(-tau)


# what a sample's shadow coefficient comes from
Shadow = GridShadow | SirenShadow | MarchedShadow


@dataclass
class Image:
    rgb: torch.Tensor  # (H, W, 3) composited over the background
    alpha: torch.Tensor  # (H, W) accumulated opacity
    seconds: float
    counters: Counters = field(default_factory=Counters)
    samples: Samples | None = None  # the frame's, when `render(..., keep=)` kept them
    replayed: bool = False  # drawn from kept samples (`render(..., samples=)`), not marched

    def to_uint8(self) -> np.ndarray:
        return (self.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def render(
    camera: Camera,
    scalar: Scalar,
    tf: TransferFunction,
    extent: ArrayLike,
    voxel: float,
    *,
    light: ArrayLike | None = None,
    shadow: Shadow | None = None,
    shading: Shading | None = None,
    step: float = DEFAULT_STEP,
    macro: MacroGrid | None = None,
    min_transmittance: float = MIN_TRANSMITTANCE,
    samples_per_iter: int | None = None,
    batch: int | None = None,
    device: torch.device | str = "cpu",
    interrupt: Callable[[], bool] | None = None,
    keep: int = 0,
    samples: Samples | None = None,
) -> Image:
    """Render one image with the wavefront marcher.

    `scalar`: `GridScalar` or `InrScalar`. `shadow`: None (no shadow), `GridShadow`, `SirenShadow` or
    `MarchedShadow`; `light` (toward the light) is needed for a shadow or Phong. `voxel` is the
    finest voxel size in box units; `step` is in voxels. Where both fields are fused SIRENs and shading is unlit,
    each ray is marched from entry to stop in one kernel (`FusedSamples.march`) instead of the wavefront loop. A
    ray then stops at the first sample that takes its transmittance below `min_transmittance`, not at the end of
    a wavefront iteration: the images differ by less than that.

    `interrupt`, if given, is called before every iteration (with whole rays: every tile), the naive baseline's
    secondary ones included; once it returns True the frame is given up with `Interrupted`. It must not read the
    device: it is a host-side flag (the viewer's "the view changed"), and the image does not depend on it.

    `keep`: where the frame is marched on the wavefront path with unlit shading, return its `Samples` with it
    (`Image.samples`) if they take at most `keep` bytes. `samples`: a kept frame's, of this camera, scalar field,
    step and marching settings: the image is drawn from them with only `shadow` evaluated (`Image.replayed`), the
    same bytes as marching it.
    """
    shading = shading or Shading()
    check_step(step, RenderError, extent=extent, voxel=voxel)
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
        shadow.light, shadow.counters, shadow.interrupt = w, counters, interrupt
    plan = MarchPlan.for_device(torch.device(device), batch, samples_per_iter)
    start = time.perf_counter()
    if samples is not None:  # the view's samples were kept: no ray is marched
        color = _replay(samples, tf, shadow, w, shading, counters, interrupt)
        return _image(camera, color, samples.trans, shading, start, counters, replayed=True)
    o, d = camera.rays(device)
    t0, t1 = ray_span(o, d, box(extent, device))
    dt = step * voxel
    trans = torch.ones(len(o), device=device)
    color = torch.zeros(len(o), 3, device=device)

    fused = _fused_samples(scalar, shadow, tf, dt, shading)
    if fused is not None:
        def march(sl, runs):
            trans[sl], color[sl], count, trips = fused.march(o[sl], d[sl], t0[sl], t1[sl], runs, min_transmittance)
            return count, trips, fused.block

        counters.iterations, counters.primary_samples, counters.slots = _whole_rays(o, d, t0, t1, dt, macro, plan,
                                                                                    march, interrupt)
        return _image(camera, color, trans, shading, start, counters)

    kept, arena = ([], _Arena(trans.device)) if keep > 0 and not shading.phong else (None, None)

    def composite(rows, t, valid):
        nonlocal kept
        pts = (o[rows, None] + t[..., None] * d[rows, None]).view(-1, 3)
        idx = torch.nonzero(valid.view(-1)).flatten()
        flat = pts[idx]
        counters.primary_samples += len(flat)
        if len(flat) == 0:
            return
        s, grad = scalar.value_and_grad(flat) if shading.phong else (scalar.value(flat), None)
        g = shadow(flat) if shadow is not None else None
        view = None
        if shading.phong:
            view = d[rows, None].expand(*valid.shape, 3).reshape(-1, 3)[idx]
        mu, rgb = tf.optics(s)
        a = 1 - torch.exp(-mu * dt)
        c = _shade(rgb, grad, g, view, w, shading)
        alpha = torch.zeros(valid.numel(), device=device).index_copy_(0, idx, a)
        weight, through = front_to_back(alpha.view(valid.shape))
        tw = trans[rows, None] * weight
        if kept is not None:
            kept.append(tuple(arena.put(x) for x in (rows, idx.int(), flat, s, tw)))
            if arena.nbytes + trans.nbytes > keep:  # past the budget: keep nothing, and free what was kept
                kept, arena.chunks = None, []
        color[rows] += _composited(tw, idx, c)
        trans[rows] *= through

    counters.iterations = _march(o, d, t0, t1, dt, macro, plan, composite,
                                 lambda rows: trans[rows] < min_transmittance, interrupt)
    image = _image(camera, color, trans, shading, start, counters)
    if kept is not None:
        image.samples = Samples(kept, trans, counters.primary_samples, counters.iterations,
                                arena.nbytes + trans.nbytes)
    return image


def _composited(tw: torch.Tensor, idx: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """One iteration's colour per ray (R,): its samples' shaded colours `c` at their slots `idx`, weighted."""
    rgb = torch.zeros(tw.numel(), 3, device=c.device).index_copy_(0, idx, c)
    return (tw[..., None] * rgb.view(*tw.shape, 3)).sum(1)


def _replay(samples: Samples, tf: TransferFunction, shadow: Shadow | None, w,
            shading: Shading, counters: Counters, interrupt: Callable[[], bool] | None) -> torch.Tensor:
    """The colour of a kept frame's rays under the light `w`: each iteration's colour, shadow and shading again
    (the colour from the scalar, a third of its bytes to keep), composited as the march did."""
    color = torch.zeros(len(samples.trans), 3, device=samples.trans.device)
    for rows, idx, flat, s, tw in samples.steps:
        go_on(interrupt)
        g = shadow(flat) if shadow is not None else None
        color[rows] += _composited(tw, idx.long(), _shade(tf.optics(s)[1], None, g, None, w, shading))
    counters.primary_samples, counters.iterations = samples.primary_samples, samples.iterations
    return color


def _image(camera: Camera, color, trans, shading: Shading, start: float, counters: Counters,
           replayed: bool = False) -> Image:
    out = color + trans[:, None] * shading.background
    h, w = camera.height, camera.width
    return Image(out.view(h, w, 3), (1 - trans).view(h, w), time.perf_counter() - start, counters,
                 replayed=replayed)


def _fused_samples(scalar: Scalar, shadow: Shadow | None,
                   tf: TransferFunction, dt: float, shading: Shading) -> FusedSamples | None:
    """Whole primary rays in one kernel where both fields are fused SIRENs on one box and shading is unlit (Phong
    needs the field's gradient, by autograd); None: the wavefront loop's eager step."""
    if shading.phong or not (isinstance(scalar, InrScalar) and isinstance(scalar.fast, FusedSiren)):
        return None
    if shadow is not None and not (isinstance(shadow, SirenShadow) and isinstance(shadow.fast, FusedSiren)
                                   and shadow.box == scalar.box):
        return None
    return FusedSamples(scalar.fast, shadow.fast if shadow is not None else None, scalar.extent,
                        tf.optics_knots(scalar.extent.device), tf.density_scale, dt)


def render_all_at_once(camera: Camera, scalar: Scalar, tf: TransferFunction, extent: ArrayLike,
                       voxel: float, *, light: ArrayLike | None = None,
                       shadow: Shadow | None = None, shading: Shading | None = None,
                       step: float = DEFAULT_STEP, device: torch.device | str = "cpu") -> Image:
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

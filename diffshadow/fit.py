"""Stage 1 (paper §3.2): fit one SIREN per light, K of them jointly, from a shared pre-optimised init.

Targets come from the ground truth: by default one `shadow_grid` per light, looked up trilinearly at
random points; `target="transmittance"` marches every training point exactly instead. A share of the
points is drawn where the volume is visible (opacity > 0), since shadows only matter there. Quality is
voxel PSNR on fresh random points (never used for training) against `transmittance`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.adam import Adam, set_lr
from diffshadow.capacity import Choice, Rung, climb, ladder
from diffshadow.config import changed_settings, section
from diffshadow.graphs import StepGraphs, requested
from diffshadow.grid import lookup_grids, stack_grids
from diffshadow.io import atomic_torch_save, resume
from diffshadow.lights import PoolLights, check_weighting
from diffshadow.metrics import psnr
from diffshadow.progress import FirstNonFinite, eta
from diffshadow.sampling import PROBE_HELD_OUT_SEED, PointSampler, Stream, seeded, to_device
from diffshadow.seams import pool_blends
from diffshadow.shadow import ShadowField, shadow_grid, transmittance_per_light
from diffshadow.siren import (
    PRECISIONS,
    BatchedSiren,
    SirenConfig,
    WeightLayout,
    box_to_siren,
    cosine_lr,
    forward_precision,
    init_siren,
)
from diffshadow.stopping import stop_signals
from diffshadow.transfer import TransferFunction
from diffshadow.truth import presample
from diffshadow.volume import Volume, refine, refined_shape, upsample_factor


class FitError(ValueError):
    """A fit that diverged or cannot run; the message names the lights involved."""


# A SIREN whose training loss ends far above its starting loss has diverged. Two measured cases set the
# thresholds: lr x10 on nucleon settles at 6 dB, the targets' own variance, 12x the init's loss; an exact
# init thrown off by lr = 1 ends at 22 dB from a loss of 1e-15. A fit that is merely short must pass: 40
# steps from the pre-optimised init leave the init's own light at 28 dB, 20x its starting loss of 41 dB.
# A fit from a poor init that ends poor is left to fit.min_psnr.
DIVERGENCE_RATIO, DIVERGENCE_FLOOR = 10.0, 1e-2  # a tenfold rise that ends below 20 dB (fit.min_psnr's default)
COLLAPSE_RATIO, COLLAPSE_FLOOR = 1e3, 1e-4  # a thousandfold rise that ends below 40 dB


def diverged(initial: torch.Tensor, final: torch.Tensor) -> torch.Tensor:
    """(K,) bool: the SIRENs whose final training loss rose tenfold from their starting loss to below 20 dB,
    or a thousandfold to below 40 dB."""
    return (((final > DIVERGENCE_RATIO * initial) & (final > DIVERGENCE_FLOOR))
            | ((final > COLLAPSE_RATIO * initial) & (final > COLLAPSE_FLOOR)))


def check_psnr(psnr: np.ndarray, light_index: list[int], min_psnr: float, where: str) -> None:
    """Fail (naming the lights) when a held-out PSNR is below `min_psnr` or not finite."""
    psnr = np.asarray(psnr, dtype=np.float64)
    bad = ~np.isfinite(psnr) | (psnr < min_psnr)
    if bad.any():
        rows = ", ".join(f"light {light_index[i]}: {psnr[i]:.2f} dB" for i in np.flatnonzero(bad))
        raise FitError(f"{where}: held-out PSNR below fit.min_psnr = {min_psnr} dB ({rows}); the fit did not "
                       f"converge, so nothing was stored. Lower fit.lr or raise fit.steps, or set fit.min_psnr "
                       f"lower if this scene's shadows really are this hard")


@dataclass(frozen=True)
class FitConfig:
    steps: int  # paper: 2000
    points: int  # per SIREN per step (paper: 32,768)
    lr: float  # Adam, paper §3.4
    lr_final: float  # cosine decay to lr · lr_final (authors' code)
    visible_fraction: float  # share of the training lights' points drawn in the visible region (pool lights': 0.5)
    target: str  # "sweep" or "march" (a grid per light) or "transmittance" (exact per point)
    grid_upsample: int | str  # target grids this much finer than the voxels; "auto": volume.upsample_factor
    eval_points: int  # held-out points per light for the stored PSNR
    chunk: int | str  # points per SIREN per forward/backward pass; 0: all at once; "auto": by device
    checkpoint_every: int
    min_psnr: float  # held-out box PSNR below this fails the subset instead of storing it; 0: off
    precision: str  # or "bfloat16": autocast for the SIREN's forward (see docs/numerics.md)
    seed: int
    target_psnr: float = 0.0  # held-out PSNR of preoptimize's probe light to reach by growing steps, then width
    max_width: int = 128  # the SIREN width ladder's top (capacity.ladder)
    # every SIREN of every subset sees the same points at a step: the sampling noise in the weights is then
    # common to all lights, so neighbouring lights' SIRENs stay close in weight space (docs/performance.md)
    shared_points: bool = True
    # The blend loss: lights between the training lights (exact shadows, no SIREN of their own) scored with the
    # weight blend of their training SIRENs (`blend_weights`, as lights.blend_weights), so that the fits vary
    # smoothly with the light and the blend and the diffusion model can interpolate them (docs/performance.md)
    blend_weight: float = 0.0  # 0: off
    blend_weights: str = "triangle"  # "triangle" or "inverse-angle" (the 4 nearest): set it as evaluate.blend_weights
    # pool lights drawn in the training lights' cap per training light (each subset takes its own): a count
    # over the cap thinned the pool as lights were added (200 lights: 1 per light -1.8 dB blend, docs/performance.md)
    blend_per_light: int = 128
    blend_points: int = 1024  # presampled points with exact shadows per pool light
    # a subset also fits the lights of other subsets that blends across its border take (`subset_halo`), and
    # discards them: the blend loss then couples the lights on either side of a seam (docs/performance.md)
    halo: int = 0  # rings of other subsets' lights (0: none)
    # subsets fitted in rounds (`subset_rounds`): a halo light of a subset of an earlier round is held at its stored
    # SIREN, not fitted as a copy, so the blends across that seam are fitted with the SIRENs they will blend
    rounds: bool = False
    # each optimiser step as a replayed CUDA graph (diffshadow.graphs), with grid targets (sweep or march): "auto"
    # where the device is CUDA, True also asked for elsewhere (the fit then steps eagerly, saying so), False never
    # (docs/performance.md: H200 timings). A fit's checkpoint records what was done (True or False)
    cuda_graph: bool | str = "auto"
    # where grid targets (sweep or march) are kept while the subset is fitted: "grids", one shadow grid per light
    # (subset_size x grid_upsample³ x the voxels); "table", each light's grid made in turn and looked up at once at
    # every step's shared points, then let go of (steps x points x the lights); "auto", the smaller. The same
    # values either way, so the same weights (tests/test_fit.py); not in a checkpoint's fingerprint
    target_store: str = "auto"

    @classmethod
    def from_config(cls, d: dict | None = None) -> FitConfig:
        """defaults.yaml's `fit` section overridden by `d`."""
        cfg = section(cls, "fit", d)
        if not (cfg.chunk == "auto" or (isinstance(cfg.chunk, int) and cfg.chunk >= 0)):
            raise ValueError(f"fit.chunk: expected 'auto' or an integer >= 0, got {cfg.chunk!r}")
        if cfg.blend_weight < 0 or (cfg.blend_weight > 0 and (cfg.blend_per_light < 1 or cfg.blend_points < 1)):
            raise ValueError(f"fit.blend_weight, blend_per_light, blend_points: expected a weight >= 0 and, when it "
                             f"is above 0, counts >= 1; got {cfg.blend_weight}, {cfg.blend_per_light}, "
                             f"{cfg.blend_points}")
        if not (cfg.grid_upsample == "auto" or (isinstance(cfg.grid_upsample, int) and cfg.grid_upsample >= 1)):
            raise ValueError(f"fit.grid_upsample: expected 'auto' or an integer >= 1, got {cfg.grid_upsample!r}")
        if cfg.halo < 0:
            raise ValueError(f"fit.halo: expected a count of rings >= 0, got {cfg.halo!r}")
        if cfg.precision not in PRECISIONS:
            raise ValueError(f"fit.precision: expected 'float32' or 'bfloat16', got {cfg.precision!r}")
        check_weighting(cfg.blend_weights, "fit.blend_weights")
        if cfg.target_store not in TARGET_STORES:
            raise ValueError(f"fit.target_store: expected one of {', '.join(TARGET_STORES)}, got {cfg.target_store!r}")
        if cfg.target_store == "table" and not cfg.shared_points:
            raise ValueError("fit.target_store: 'table' looks the targets up at the points every light shares at a "
                             "step; it needs fit.shared_points: true (or target_store: grids or auto)")
        return cfg


TARGET_STORES = ("auto", "grids", "table")
LOOKUP_STEPS = 64  # a table's steps looked up in one pass: bounded memory on the device (x points x 3 floats)
GRIDS_QUIET_S = 5.0  # the target grids log their progress once they have taken this long


def describe_targets(cfg: FitConfig, k: int, shape: tuple[int, ...],
                     device: torch.device | None = None) -> str:
    """One line on how a subset's targets are made and kept (a fit job's log)."""
    if cfg.target == "transmittance":
        return f"targets: exact transmittance marched at every step's points for {k} lights"
    factor = upsample_factor(cfg.grid_upsample, shape)
    grid = refined_shape(shape, factor)
    store, grids, table = target_store(cfg, k, grid, device)
    mib = {name: f"{size / 2**20:,.0f} MiB" if size >= 2**20 else f"{size / 2**10:,.0f} KiB"
           for name, size in (("grids", grids), ("table", table))}
    kept = (f"kept as {k} grids ({mib['grids']}; a table at every step's points: {mib['table']})" if store == "grids"
            else f"made one at a time and kept as their values at every step's points ({mib['table']}; as grids: "
                 f"{mib['grids']})")
    return f"targets: a {cfg.target} shadow grid of {'x'.join(map(str, grid))} per light (the voxels refined " \
           f"{factor} times, fit.grid_upsample: {cfg.grid_upsample}), {kept}, fit.target_store: {cfg.target_store}"


def target_store(cfg: FitConfig, k: int, grid_shape: tuple[int, ...],
                 device: torch.device | None = None) -> tuple[str, int, int]:
    """Where `k` lights' grid targets of `grid_shape` are kept (`FitConfig.target_store`): ("grids" or "table",
    the grids' bytes, the table's bytes, its points included). "auto" on a CPU: the smaller. On a GPU the table's
    step (its targets copied from the host with the points) is not yet timed, so "auto" keeps the grids there
    unless they would take more than half the card's memory, where they could not run at all."""
    grids = 4 * k * int(np.prod(grid_shape))
    table = 4 * cfg.steps * cfg.points * (k + 3)
    if cfg.target_store != "auto":
        return cfg.target_store, grids, table
    smaller = table < grids
    if device is not None and device.type == "cuda":
        smaller = smaller and grids > torch.cuda.get_device_properties(device).total_memory // 2
    return ("table" if cfg.shared_points and smaller else "grids"), grids, table


# Points per SIREN per pass on the CPU: `bench siren` on 2 cores gave 1.2-1.9x over one SIREN at a time
# at 512 (larger passes fall out of cache). A GPU wants every point in one pass (0.26x at 512, 2.1-5.0x at
# 32,768 on an H100; b35accb).
CPU_CHUNK = 512


def blend_pool(volume: Volume, tf: TransferFunction, train: np.ndarray, center: ArrayLike, subset: list[int],
               cfg: FitConfig, *, halo: list[list[int]] = (), held: list[int] = (),
               device: torch.device | str = "cpu") -> PoolLights | None:
    """Pool lights for the blend loss: `cfg.blend_per_light` directions per training light drawn in the training
    lights' cap (the same for every subset), of which this subset takes those whose blend (`cfg.blend_weights`:
    the corners of their triangle among all the training lights, or their k = min(BLEND_K, len(subset)) nearest)
    takes only its own lights, with their exact shadow at `cfg.blend_points` points (`neighbours` are rows of the
    subset); None when the blend loss is off or the subset has fewer than 2 lights. Coupling stays inside a
    subset's job (with `fit.rounds`, its earlier rounds' SIRENs held). With a `halo` (`subset_halo`'s rings, fitted
    after the subset's lights in that order), a pool light whose blend takes the halo's lights counts where it takes
    one of the subset's too, or of a ring inside the outermost. `held` (halo lights held at their stored SIRENs,
    `held_lights`) are the last rows, after the fitted ones in order.

    Without a halo, a pool light at a subset's border is left out, not blended from the subset's own nearest lights:
    that blend is not the one the diffusion model's pool prior and the weight-blend baseline use, and fitting
    towards it cost nucleon's weight blend 2.7 dB and tooth's 2.6 dB in two subsets of 16 (docs/performance.md)."""
    if cfg.blend_weight <= 0 or len(subset) < 2:
        return None
    train = np.asarray(train, dtype=np.float64)
    lights, idx, mix = pool_blends(train, center, len(subset), cfg)
    held_set = set(held)
    fitted = list(subset) + [i for ring in halo for i in ring if i not in held_set] + list(held)
    # a pool light counts where its blend takes a light of the subset or of a ring inside the outermost, whose
    # lights then have blends on every side, as in their own subset
    inner = list(subset) + [i for ring in halo[:-1] for i in ring]
    rows = np.flatnonzero(np.isin(idx, fitted).all(axis=1) & np.isin(idx, inner).any(axis=1))
    if len(rows) == 0:
        return None
    points, values = presample(volume, tf, lights[rows], cfg.blend_points, seed=cfg.seed, stream=Stream.FIT_BLEND_POOL,
                               device=device)
    row_of = np.full(len(train), -1)
    row_of[fitted] = np.arange(len(fitted))  # light index -> row of the fit
    return PoolLights(lights=torch.as_tensor(lights[rows], device="cpu"), points=points, values=values,
                      neighbours=torch.as_tensor(row_of[idx[rows]], device="cpu"),
                      blend=torch.as_tensor(mix[rows], dtype=torch.float32, device="cpu"))


def points_per_pass(chunk: int | str, points: int, device: torch.device) -> int:
    """`fit.chunk` resolved for `device`: "auto" is all points on CUDA, CPU_CHUNK elsewhere; 0 is all."""
    if chunk == "auto":
        return points if device.type == "cuda" else min(points, CPU_CHUNK)
    return int(chunk) or points


def shared_points(sampler: PointSampler, cfg: FitConfig, step: int) -> torch.Tensor:
    """(1, N, 3): step `step`'s points where every SIREN of a subset shares them (`fit.shared_points`), on the host:
    the fit's draw, and a table's targets (`fit.target_store`) looked up at the same points."""
    return sampler.sample(1, cfg.points, seeded(cfg.seed, Stream.FIT_SHARED_POINTS, step))


class Targets:
    """The shadow each SIREN is fitted to at any points: one `shadow_grid` per light looked up trilinearly
    (`fit.target` "sweep" or "march"), or marched exactly per point ("transmittance"). Grid targets are held as
    the grids, or (`fit.target_store`) as a table of their values at every step's shared points (`table_from`),
    each grid made, looked up and let go of in turn: a subset of large volumes then needs one grid, not K."""

    def __init__(self, volume: Volume, tf: TransferFunction, lights: np.ndarray, cfg: FitConfig,
                 device: torch.device, log: Callable[[str], None] | None = None):
        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32, device=device)
        self.tf, self.lights, self.cfg, self.device, self.log = tf, lights, cfg, device, log
        self.grids = self.field = self.fine = self.table = self.table_points = None
        self.table_start, self.tabled = 0, False
        if cfg.target == "transmittance":
            self.field = ShadowField.build(volume, tf, device=device)
        elif cfg.target in ("sweep", "march"):
            fine = refine(volume, upsample_factor(cfg.grid_upsample, volume.data.shape))
            if target_store(cfg, len(lights), fine.data.shape, device)[0] == "table":
                self.fine, self.tabled = fine, True  # the table is made at the first step's number (`table_from`)
                return
            grids = self._grids(fine)
            # channels last where a CPU reads them at shared points: a fit step's lookup 0.26x; not timed on a GPU
            channels = cfg.shared_points and device.type == "cpu"
            self.grids = stack_grids(grids, len(lights), channels_last=channels)
        else:
            raise ValueError(f"fit.target: expected 'sweep', 'march' or 'transmittance', got {cfg.target!r}")

    def _grids(self, fine: Volume) -> Iterator[torch.Tensor]:
        """Each light's grid on `fine` in turn, none held here once the next is asked for; a log line every ~10%
        of the lights once they have taken GRIDS_QUIET_S (a 256³ volume's 32 grids at 2x take 196 s; a small
        volume's, a fraction of a second, need no word)."""
        t0, k = time.perf_counter(), len(self.lights)
        for j, w in enumerate(self.lights):
            yield shadow_grid(fine, self.tf, w, method=self.cfg.target, device=self.device)
            if (self.log is not None and ((j + 1) % max(1, k // 10) == 0 or j + 1 == k)
                    and time.perf_counter() - t0 >= GRIDS_QUIET_S):
                self.log(f"targets: {j + 1}/{k} grids ({eta(j + 1, k, t0)})")

    @torch.no_grad()
    def table_from(self, start: int, sampler: PointSampler) -> None:
        """The table of every light's target at the shared points of steps `start` on (drawn as `SubsetFit.draw`
        draws them), on the host: (steps, K, N), one step's (K, N) contiguous."""
        cfg, k = self.cfg, len(self.lights)
        steps = range(start, cfg.steps)
        self.table_points = torch.cat([shared_points(sampler, cfg, s) for s in steps]) if len(steps) else \
            torch.empty(0, cfg.points, 3, device="cpu")
        self.table = torch.empty(len(steps), k, cfg.points, device="cpu")
        j = 0
        for grid in self._grids(self.fine):  # not enumerate: its reused tuple would hold a grid while the next is made
            grid = grid[None]
            for s0 in range(0, len(steps), LOOKUP_STEPS):
                pts = self.table_points[s0:s0 + LOOKUP_STEPS].to(self.device)
                values = lookup_grids(grid, pts.reshape(1, -1, 3), self.extent).reshape(len(pts), cfg.points)
                self.table[s0:s0 + LOOKUP_STEPS, j] = values.cpu()
            del grid
            j += 1
        self.fine, self.table_start = None, start

    def at_step(self, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The table's (N, 3) shared points and (K, N) targets of step `step`, on the host."""
        i = step - self.table_start
        if not 0 <= i < len(self.table):
            raise ValueError(f"fit targets: step {step} is outside the table of steps {self.table_start} to "
                             f"{self.table_start + len(self.table) - 1}")
        return self.table_points[i], self.table[i]

    @torch.no_grad()
    def __call__(self, pts: torch.Tensor) -> torch.Tensor:
        """(K, N, 3) points in volume coordinates → (K, N) shadow of light k at its points."""
        if self.grids is not None:
            return lookup_grids(self.grids, pts, self.extent)
        if self.tabled:
            raise ValueError("fit targets: a table holds its steps' points only (Targets.at_step)")
        return transmittance_per_light(self.field, self.tf, self.lights, pts)


def fit_step(weights: torch.Tensor, opt: Adam, pts: torch.Tensor, target: torch.Tensor, layout: WeightLayout,
             siren: SirenConfig, extent: torch.Tensor, cfg: FitConfig, *, chunk: int,
             autocast: contextlib.AbstractContextManager, pool: PoolLights | None = None,
             pool_draw: tuple[torch.Tensor, torch.Tensor] | None = None, held: torch.Tensor | None = None,
             keep_grads: bool = False) -> torch.Tensor:
    """One Adam step of all K SIRENs on their points; returns each SIREN's mean squared error (K,) before it.
    With `pool`, `pool_draw` is `draw_pool`'s (lights, points) on the device; `held` (H, n_params): SIRENs the pool's
    blends take after the K (rows K.., `blend_pool`'s `held`), not fitted. `keep_grads` zeroes the gradient in
    place instead of dropping it (what a replayed CUDA graph needs: its kernels write to fixed addresses)."""
    k = len(weights)
    opt.zero_grad(set_to_none=not keep_grads)
    per_siren = torch.zeros(k, device=weights.device)
    for c0 in range(0, cfg.points, chunk):
        model = BatchedSiren(weights, layout, siren.blocks)
        with autocast:
            pred = model(box_to_siren(pts[:, c0:c0 + chunk], extent)).float()
        # sum over SIRENs of each one's mean: every SIREN gets exactly its own gradient
        sq = ((pred - target[:, c0:c0 + chunk]) ** 2).sum(dim=1) / cfg.points
        sq.sum().backward()
        per_siren += sq.detach()
    if pool is not None:
        rows = weights if held is None else torch.cat([weights, held])
        _blend_loss(rows, pool, layout, siren, extent, cfg, len(rows), *pool_draw)
    opt.step()
    return per_siren


class Watch:
    """The fit's health and progress: non-finite losses (kept on the device, read at log lines and
    checkpoints), divergence judged once at the end against the init's loss, and the log line every tenth."""

    def __init__(self, k: int, cfg: FitConfig, siren: SirenConfig, light_index: list[int], start: int,
                 initial: torch.Tensor | None, device: torch.device, log: Callable[[str], None]):
        self.k, self.cfg, self.width, self.light_index = k, cfg, siren.width, light_index
        self.start, self.log = start, log
        self.initial = initial  # each SIREN's loss at the init, before any update
        self.nonfinite = FirstNonFinite((k,), device)
        self.window, self.window_steps = torch.zeros(k, device=device), 0
        self.t0 = time.perf_counter()

    def record(self, per_siren: torch.Tensor, step: int) -> None:
        self.nonfinite.record(per_siren, step)
        if self.initial is None:
            self.initial = per_siren.clone()
        self.window += per_siren
        self.window_steps += 1

    def check(self) -> None:
        if (found := self.nonfinite.first()) is not None:
            step, at_step, _ = found
            which = [self.light_index[i] for i in torch.nonzero(at_step).flatten().tolist()]
            raise FitError(f"fit diverged at step {step}: loss is not finite for light(s) {which}; "
                           f"lower fit.lr (now {self.cfg.lr}) or check the targets")

    def report(self, done: int) -> None:
        cfg, recent = self.cfg, self.window / self.window_steps
        # Judged at the end only: from a pre-optimised init, Adam's first steps lift the init light's
        # loss 100x before it recovers (nucleon: 41 -> 21 -> 35 dB), a rise that is no divergence.
        if done == cfg.steps and (bad := diverged(self.initial, recent)).any():
            rows = ", ".join(f"light {self.light_index[i]}: {float(self.initial[i]):.2e} -> {float(recent[i]):.2e}"
                             for i in torch.nonzero(bad).flatten().tolist())
            raise FitError(f"fit diverged: over the last {self.window_steps} steps the training loss rose far above "
                           f"its starting value ({rows}); lower fit.lr (now {cfg.lr})")
        rate = (done - self.start) * self.k * cfg.points / (time.perf_counter() - self.t0)
        self.log(f"step {done}/{cfg.steps}  lr {cosine_lr(done - 1, cfg, self.width):.2e}  median PSNR(train batch) "
                 f"{float(-10 * torch.log10(recent).median()):.1f} dB  {rate:,.0f} points/s  "
                 f"{eta(done, cfg.steps, self.t0, start=self.start)}")
        self.window, self.window_steps = torch.zeros_like(self.window), 0


@dataclass
class FitDraw:
    """One step's random draws, made on the host from the step's seeds and moved to the device: the inputs of
    `SubsetFit.update` (and of its CUDA graph)."""
    pts: torch.Tensor  # (K, N, 3) points in volume coordinates
    pool_lights: torch.Tensor | None  # (K,) the pool lights the blend loss scores (with a pool)
    pool_points: torch.Tensor | None  # (K, M) their presampled points
    target: torch.Tensor | None = None  # (K, N) the targets at `pts`, from a table (fit.target_store)


def fit_graphs(cfg: FitConfig, device: torch.device, log: Callable[[str], None] = print) -> StepGraphs | None:
    """The fit's CUDA graphs where `fit.cuda_graph` asks for them ("auto" or True) and the device and targets allow
    them (exact transmittance targets march with host reads)."""
    unsupported = "fit.target transmittance marches with host reads" if cfg.target == "transmittance" else ""
    return requested(cfg.cuda_graph, "fit.cuda_graph", device, log, unsupported=unsupported)


class SubsetFit:
    """The K SIRENs of one light subset being fitted, and one optimiser step of them (`step`): the loop body of
    `fit_sirens`, which `bench stages` times as it is. The step's draws are made on the host and copied to the
    device without waiting for it; the update (`update`) then reads nothing back and copies nothing from the host
    (tests/test_syncs.py), so that it can be one replayed CUDA graph (`fit.cuda_graph`); its loss stays on the
    device for `Watch`."""

    def __init__(self, init: torch.Tensor, layout: WeightLayout, siren: SirenConfig, volume: Volume,
                 tf: TransferFunction, lights: np.ndarray, cfg: FitConfig, *, stream: int = 0,
                 pool: PoolLights | None = None, held: torch.Tensor | None = None, device: torch.device,
                 log: Callable[[str], None] = print):
        self.layout, self.siren, self.cfg, self.stream, self.k = layout, siren, cfg, stream, len(lights)
        self.sampler = PointSampler(volume, tf, cfg.visible_fraction)
        self.targets = Targets(volume, tf, lights, cfg, device, log)
        self.weights = init.to(device=device, dtype=torch.float32).expand(self.k, -1).clone().requires_grad_(True)
        self.graphs = fit_graphs(cfg, device, log)
        # graphed or not is in a checkpoint's fingerprint: an optimizer never resumes the other kind's state
        self.opt = Adam([self.weights], cfg.lr, capturable=self.graphs is not None)
        self.pool = pool.to(device) if pool is not None else None
        self.held = held.to(device=device, dtype=torch.float32) if held is not None and len(held) else None
        self.chunk = points_per_pass(cfg.chunk, cfg.points, device)
        self.autocast = forward_precision(cfg.precision, device)
        self.device, self.log = device, log

    def step(self, step: int) -> torch.Tensor:
        """Optimiser step `step` (its points depend only on the seed, the subset's stream and `step`); each SIREN's
        mean squared error before it (K,), on the device."""
        set_lr(self.opt, cosine_lr(step, self.cfg, self.siren.width))
        draw = self.draw(step)
        return self.update(draw) if self.graphs is None else self.graphs(self.update, draw)

    def prepare(self, start: int) -> None:
        """Where the targets are a table (fit.target_store), make it for steps `start` on: each light's grid in
        turn, looked up at every step's points. `draw` makes it if needed; the fit calls it first, so that the
        loop's rate and time left are its steps' (on a 256³ volume the table took 196 s of a 308 s fit, and the
        first log line said ~1,868 s left with 100 s to go)."""
        if not self.targets.tabled or self.targets.table is not None:
            return
        t0 = time.perf_counter()
        self.targets.table_from(start, self.sampler)
        self.log(f"targets: {self.k} shadow grids looked up at the points of steps {start} to {self.cfg.steps - 1} "
                 f"({time.perf_counter() - t0:.1f} s)")

    def draw(self, step: int) -> FitDraw:
        """Step `step`'s points (and pool picks), drawn on the host and on the device without waiting for it."""
        cfg, k = self.cfg, self.k
        target = None
        if self.targets.tabled:  # the step's points and targets, drawn and looked up before the first step
            self.prepare(step)
            shared, target = self.targets.at_step(step)
            pts, target = to_device(shared[None], self.device).expand(k, -1, -1), to_device(target, self.device)
        elif cfg.shared_points:  # one draw, moved once, seen by every SIREN
            pts = to_device(shared_points(self.sampler, cfg, step), self.device).expand(k, -1, -1)
        else:
            pts = to_device(self.sampler.sample(k, cfg.points, seeded(cfg.seed, self.stream, step)), self.device)
        if self.pool is None:
            return FitDraw(pts, None, None, target)
        gen = seeded(cfg.seed, Stream.FIT_POOL_PICK - self.stream, step)
        # as many pool lights as the blends have rows, held ones too: holding a light changes how it is treated,
        # not how much of the pool a step scores (scoring only the fitted rows' share cost 0.3 dB inside subsets)
        rows = k + (0 if self.held is None else len(self.held))
        j, pick = draw_pool(len(self.pool.lights), self.pool.points.shape[1], rows, cfg, gen)
        return FitDraw(pts, to_device(j, self.device), to_device(pick, self.device), target)

    def update(self, draw: FitDraw) -> torch.Tensor:
        """The optimiser step on `draw`: each SIREN's mean squared error before it (K,)."""
        pool_draw = None if self.pool is None else (draw.pool_lights, draw.pool_points)
        target = self.targets(draw.pts) if draw.target is None else draw.target
        return fit_step(self.weights, self.opt, draw.pts, target, self.layout, self.siren,
                        self.targets.extent, self.cfg, chunk=self.chunk, autocast=self.autocast, pool=self.pool,
                        pool_draw=pool_draw, held=self.held, keep_grads=self.graphs is not None)


def fit_sirens(
    init: torch.Tensor,
    layout: WeightLayout,
    siren: SirenConfig,
    volume: Volume,
    tf: TransferFunction,
    lights: np.ndarray,
    cfg: FitConfig,
    *,
    stream: int = 0,
    light_index: list[int] | None = None,
    checkpoint: Path | None = None,
    pool: PoolLights | None = None,
    held: torch.Tensor | None = None,
    device: torch.device | str = "cpu",
    log: Callable[[str], None] = print,
    between_steps: Callable[[], object] | None = None,
) -> torch.Tensor:
    """Fit K = len(lights) SIRENs jointly from `init` (n_params,) → (K, n_params) float32.

    `stream` separates the random points of different subsets. With `checkpoint`, progress is saved
    every `cfg.checkpoint_every` steps and a rerun resumes from it (same result as an uninterrupted run:
    the points of step s depend only on (seed, stream, s)). With `pool` (`blend_pool`), each step also
    scores K of its lights, at half as many points as a SIREN gets, with their blends of these SIRENs'
    weights, weighted by `cfg.blend_weight`; its blends' rows past K are `held` (H, n_params), not fitted.
    `between_steps` is called after every step.
    """
    device = torch.device(device)
    lights = np.asarray(lights, dtype=np.float64)
    k = len(lights)
    light_index = list(range(k)) if light_index is None else list(light_index)
    run = SubsetFit(init, layout, siren, volume, tf, lights, cfg, stream=stream, pool=pool, held=held, device=device,
                    log=log)
    weights, opt = run.weights, run.opt
    cfg = replace(cfg, cuda_graph=run.graphs is not None)  # what was done: the checkpoint's fingerprint
    fingerprint = _fingerprint(init, lights, cfg, siren, stream, pool, volume, tf, held)
    start, initial = 0, None
    if state := resume(checkpoint, fingerprint, log=log, map_location=device, weights_only=True):
        with torch.no_grad():
            weights.copy_(state["weights"])
        opt.load_state_dict(state["optimizer"])
        start = int(state["step"])
        initial = state["initial_loss"].to(device) if start and "initial_loss" in state else None
        log(f"resuming from {checkpoint} at step {start}/{cfg.steps}")
    run.prepare(start)
    watch = Watch(k, cfg, siren, light_index, start, initial, device, log)
    with stop_signals(checkpoint is not None) as stop:
        for step in range(start, cfg.steps):
            watch.record(run.step(step), step)
            if between_steps is not None:  # e.g. runtime.SpareThreads.poll: the step's threads change no byte
                between_steps()
            done = step + 1
            stopping = stop.requested and done < cfg.steps
            saving = checkpoint is not None and (done % cfg.checkpoint_every == 0 and done < cfg.steps or stopping)
            logging = done % max(1, cfg.steps // 10) == 0 or done == cfg.steps
            if saving or logging:
                watch.check()
            if saving:
                atomic_torch_save(checkpoint, {"fingerprint": fingerprint, "step": done,
                                               "weights": weights.detach().cpu(), "optimizer": opt.state_dict(),
                                               "initial_loss": watch.initial.cpu()})
            if stopping:
                raise stop.stopped(f"at step {done}/{cfg.steps}", checkpoint)
            if logging:
                watch.report(done)
    if checkpoint is not None and checkpoint.exists():
        checkpoint.unlink()
    return weights.detach().cpu()


def draw_pool(n_lights: int, n_points: int, k: int, cfg: FitConfig,
              gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The blend loss's draw for one step: K random pool lights (of `n_lights`) and cfg.points / 2 random points
    each (of the `n_points` presampled), on `gen`'s device."""
    j = torch.randperm(n_lights, generator=gen, device=gen.device)[:k]
    return j, torch.randint(0, n_points, (len(j), max(1, cfg.points // 2)), generator=gen, device=gen.device)


def _blend_loss(weights: torch.Tensor, pool: PoolLights, layout: WeightLayout, siren: SirenConfig,
                extent: torch.Tensor, cfg: FitConfig, k: int, j: torch.Tensor, pick: torch.Tensor) -> None:
    """Backpropagate the blend loss of pool lights `j` at their points `pick` (`draw_pool`, on the device)."""
    pts, truth = pool.samples(j, pick)
    pred = BatchedSiren(pool.x0(weights, j), layout, siren.blocks)(box_to_siren(pts, extent)).float()
    # a mean per pool light, summed and scaled to K lights: weight 1 gives the pool the training lights' say
    (cfg.blend_weight * ((pred - truth) ** 2).mean(dim=1).sum() * (k / len(j))).backward()


def _fingerprint(init, lights, cfg, siren, stream, pool: PoolLights | None, volume: Volume,
                 tf: TransferFunction, held: torch.Tensor | None = None) -> str:
    """What a checkpoint must have been written for to be resumed: the targets (volume, TF) as well as the
    init, lights and settings (a fit resumed onto a changed volume would mix two scenes' shadows)."""
    h = hashlib.sha256()
    h.update(init.detach().cpu().numpy().astype(np.float32).tobytes())
    h.update(np.ascontiguousarray(volume.data, dtype=np.float32).tobytes())
    h.update(json.dumps([np.asarray(volume.extent, np.float64).tolist(), tf.to_config()]).encode())
    h.update(np.asarray(lights, np.float64).tobytes())
    if pool is not None:
        h.update(pool.lights.cpu().numpy().astype(np.float64).tobytes())
    if held is not None and len(held):  # the earlier rounds' SIRENs, refitted since: start again
        h.update(held.detach().cpu().numpy().astype(np.float32).tobytes())
    settings = changed_settings("fit", asdict(cfg))
    settings.pop("target_store", None)  # where the targets are kept: the same values, so a resume may change it
    h.update(json.dumps([settings, siren.to_config(), stream], sort_keys=True).encode())
    return h.hexdigest()


def evaluate_psnr(
    weights: torch.Tensor,
    layout: WeightLayout,
    siren: SirenConfig,
    volume: Volume,
    tf: TransferFunction,
    lights: np.ndarray,
    *,
    n_points: int,
    seed: int,
    device: torch.device | str = "cpu",
) -> tuple[np.ndarray, np.ndarray]:
    """Voxel PSNR of each SIREN against `transmittance` at fresh random points: (over the box, visible)."""
    device = torch.device(device)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32, device="cpu")  # points drawn on the CPU
    field = ShadowField.build(volume, tf, device=device)
    gen = seeded(seed, Stream.HELD_OUT, len(lights))
    box = torch.rand(len(lights), n_points, 3, generator=gen, device=gen.device) * extent
    vis_sampler = PointSampler(volume, tf, 1.0)
    vis = vis_sampler.sample(len(lights), n_points, gen) if vis_sampler.visible_fraction else box
    out = []
    with torch.no_grad():
        model = BatchedSiren(weights.to(device), layout, siren.blocks)
        for pts in (box, vis):
            pts = pts.to(device)  # once, for the SIRENs and the march
            pred = model(box_to_siren(pts, extent.to(device)))
            truth = transmittance_per_light(field, tf, lights, pts)
            out.append(psnr(pred, truth, dim=1).cpu().numpy())
    return out[0], out[1]




@dataclass
class Stage1Layout:
    """preoptimize's result: the shared initial weights, the SIREN size, the fit steps and points a step every
    subset uses, and the record of the sizes tried (`capacity.Choice`)."""

    init: torch.Tensor
    siren: SirenConfig
    steps: int
    points: int
    choice: Choice

    @property
    def layout(self) -> WeightLayout:
        return WeightLayout.for_siren(self.siren)


def probe_light(lights: np.ndarray) -> int:
    """The training light farthest from light 0 (the pre-optimised one): the hardest fit from its init."""
    lights = np.asarray(lights, dtype=np.float64)
    return int(np.argmin(lights @ lights[0])) if len(lights) > 1 else 0


def choose_layout(volume: Volume, tf: TransferFunction, lights: np.ndarray, siren: SirenConfig, cfg: FitConfig, *,
                  preoptimize_steps: int, preoptimize_lr: float, device: torch.device | str = "cpu",
                  log: Callable[[str], None] = print) -> Stage1Layout:
    """The shared init (one SIREN fitted to light 0) and one SIREN size for every subset of the scene.

    With `cfg.target_psnr` > 0, a probe fits the light farthest from light 0 from the init as a subset would,
    but alone (a one-light subset has no blend loss, which costs a light ~1 dB in its subset: docs/performance.md,
    stage 1), and its held-out PSNR decides: below the target, the fit steps double, then the width does, its
    steps' points with it (capacity.ladder). Without a target, the configured size is kept and nothing is probed.
    """
    lights = np.asarray(lights, dtype=np.float64)
    pre = replace(cfg, steps=int(preoptimize_steps), lr=float(preoptimize_lr))
    probe = probe_light(lights)
    inits: dict[int, torch.Tensor] = {}

    def init_for(rung: Rung) -> torch.Tensor:
        width = rung.width
        if width not in inits:
            s = SirenConfig(width, siren.blocks)
            layout = WeightLayout.for_siren(s)
            init = layout.flatten(init_siren(s, seeded(cfg.seed, Stream.PREOPTIMIZE)))
            if pre.steps > 0:
                # in steps of the rung's points: the batch that width's fits take
                log(f"pre-optimising one SIREN of width {width} on light 0 for {pre.steps} steps of {rung.points} "
                    f"points")
                init = fit_sirens(init, layout, s, volume, tf, lights[:1], replace(pre, points=rung.points),
                                  stream=Stream.PREOPTIMIZE, light_index=[0], device=device, log=log)[0]
            inits[width] = init
        return inits[width]

    def attempt(rung: Rung) -> tuple[Rung, float]:
        if cfg.target_psnr <= 0:
            init_for(rung)
            return rung, float("nan")
        s = SirenConfig(rung.width, siren.blocks)
        init = init_for(rung)
        layout = WeightLayout.for_siren(s)
        log(f"probe: fitting light {probe} (the farthest from light 0) at {rung.describe()}")
        w = fit_sirens(init, layout, s, volume, tf, lights[probe:probe + 1],
                       replace(cfg, steps=rung.steps, points=rung.points),
                       stream=Stream.PROBE, light_index=[probe], device=device,
                       log=lambda m: log(f"probe: {m}"))  # at the paper's sizes minutes on a CPU: not silent
        box, _ = evaluate_psnr(w, layout, s, volume, tf, lights[probe:probe + 1], n_points=cfg.eval_points,
                               seed=cfg.seed + PROBE_HELD_OUT_SEED, device=device)
        log(f"probe: light {probe} held-out PSNR {float(box[0]):.2f} dB (target {cfg.target_psnr:g} dB)")
        return rung, float(box[0])

    rungs = ladder(siren.width, cfg.steps, max(cfg.max_width, siren.width), cfg.points)
    rung, choice = climb(rungs, cfg.target_psnr, attempt, log=log, what="stage-1 probe")
    if warning := choice.warning(f"stage 1's probe light {probe}", "fit.max_width or fit.steps"):
        log(warning)
    return Stage1Layout(inits[rung.width], SirenConfig(rung.width, siren.blocks), rung.steps, rung.points, choice)

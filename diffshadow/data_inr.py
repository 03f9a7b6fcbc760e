"""The data INR: one SIREN of the scalar field (the same module as the shadow INRs), which the renderer
queries instead of the raw volume. Its worst voxel error widens the macro-cell ranges so that empty-space
skipping never drops a sample the INR would draw.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from diffshadow.adam import Adam, set_lr
from diffshadow.capacity import Rung, climb, ladder
from diffshadow.config import ConfigError, changed_settings, section
from diffshadow.graphs import requested
from diffshadow.grid import cell_ranges, cell_slabs, lattice_axes, lattice_points, lookup_grids
from diffshadow.io import atomic_torch_save, resume
from diffshadow.metrics import psnr
from diffshadow.progress import FirstNonFinite, Ticker, eta
from diffshadow.sampling import PointSampler, Stream, seeded, to_device
from diffshadow.siren import Siren, SirenConfig, box_to_siren, cosine_lr
from diffshadow.stopping import stop_signals
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume


@dataclass(frozen=True)
class DataInrConfig:
    width: int
    blocks: int
    steps: int
    points: int  # per step
    lr: float
    lr_final: float  # cosine decay to lr · lr_final
    visible_fraction: float  # share of points near voxels the TF makes visible
    checkpoint_every: int
    seed: int
    target_psnr: float = 0.0  # voxel PSNR to reach by doubling the width (capacity.ladder); 0: fixed size
    max_width: int = 256
    error_fraction: float = 0.0  # share of points near the voxels the INR gets most wrong (ErrorSampler)
    error_every: int = 300  # steps between scorings of the voxels
    # each optimiser step as a replayed CUDA graph (diffshadow.graphs): "auto" where the device is CUDA, True also
    # asked for elsewhere (the fit then steps eagerly, saying so), False never (docs/performance.md: H200 timings)
    cuda_graph: bool | str = "auto"

    def __post_init__(self):
        if self.visible_fraction + self.error_fraction > 1:
            raise ConfigError(f"data_inr: visible_fraction ({self.visible_fraction}) + error_fraction "
                              f"({self.error_fraction}) must be at most 1 (the rest are uniform box points)")

    @classmethod
    def from_config(cls, d: dict | None = None) -> DataInrConfig:
        """defaults.yaml's `data_inr` section overridden by `d`."""
        return section(cls, "data_inr", d)

    @property
    def siren(self) -> SirenConfig:
        return SirenConfig(self.width, self.blocks)


@dataclass
class DataInr:
    model: Siren
    extent: np.ndarray
    psnr: float  # over every voxel
    max_error: float  # worst |INR − voxel|
    config: dict
    cell_lo: np.ndarray | None = None  # the INR's own range per RENDER_CELL macro-cell (renderer skipping)
    cell_hi: np.ndarray | None = None
    volume: str | None = None  # the grid it was fitted to (Volume.checksum); None: a file from before it was kept

    @property
    def n_params(self) -> int:
        return self.model.layout.n_params


def voxel_errors(model: Siren, volume: Volume, *, chunk: int = 1 << 16,
                 device: torch.device | str = "cpu", log: Callable[[str], None] | None = None) -> tuple[float, float]:
    """(PSNR, max |error|) of the INR over every voxel of `volume`; `log`: a line a minute while it runs."""
    device = torch.device(device)
    axes = lattice_axes(volume, device=device)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32, device=device)
    truth = torch.as_tensor(volume.data, device=device).reshape(-1)
    with torch.no_grad():
        pred = torch.cat(list(lattice_values(model, axes, extent, chunk, log=log, what="data INR: voxel PSNR")))
    return float(psnr(pred, truth)), float((pred - truth).abs().max())


def lattice_values(model: Siren, axes: list[torch.Tensor], extent: torch.Tensor, chunk: int, *,
                   log: Callable[[str], None] | None = None, what: str = "") -> Iterator[torch.Tensor]:
    """The INR at every point of the lattice of `axes` (`grid.lattice_points`), in its (Z, Y, X) order, `chunk`
    points at a time: each chunk's points made as it is evaluated, not 12 bytes a point at once (a caller that
    wants no graph asks for none). `log`: `what`, how far and how long is left, a line a minute (a 512³ volume's
    renderer ranges are 1 G points: ~16 min on one CPU thread)."""
    total = math.prod(len(a) for a in axes)
    tick = Ticker(f"{what} ({total:,} points)", total, log=log) if log is not None else None
    for i in range(0, total, chunk):
        if tick is not None:
            tick(i)
        yield model(box_to_siren(lattice_points(axes, i, min(i + chunk, total)), extent))


def values_at(model: Siren, pts: torch.Tensor, extent: torch.Tensor, chunk: int = 1 << 16) -> torch.Tensor:
    """The INR at (N, 3) box points, `chunk` points at a time, without a graph → (N,)."""
    with torch.no_grad():
        return torch.cat([model(box_to_siren(pts[i:i + chunk], extent)) for i in range(0, len(pts), chunk)])


# voxels scored per refresh at most; larger volumes are scored every 2nd (3rd, ...) voxel along each axis, which
# kept the gain on tooth and hydrogen_atom at a fraction of a full scoring's time
ERROR_VOXELS = 1 << 18


class ErrorSampler:
    """Points where the INR errs most. Every `every` steps the INR is scored at the voxels of a lattice (every
    voxel, or every `stride`-th along each axis on volumes larger than ERROR_VOXELS), and until the next
    scoring points are drawn around lattice voxels in proportion to their squared error plus a tenth of its
    mean (no region starves), uniformly over the voxel block each stands for.

    Voxel PSNR is set by the few voxels at sharp features (neghip jumps from 0 to 1 between neighbours), which
    uniform and visible-voxel points rarely visit: on neghip this sampling is worth four times the steps
    (docs/performance.md). Drawn on the CPU like PointSampler; the scoring runs on the model's device."""

    def __init__(self, volume: Volume, every: int):
        dims = volume.data.shape  # (Z, Y, X)
        self.stride = 1
        while math.prod(math.ceil(n / self.stride) for n in dims) > ERROR_VOXELS:
            self.stride += 1
        z, y, x = torch.meshgrid(*(torch.arange(0, n, self.stride) for n in dims), indexing="ij")
        self.voxel = torch.as_tensor(volume.voxel_size, dtype=torch.float32)
        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32)
        self.lattice = torch.stack([x, y, z], dim=-1).reshape(-1, 3).float() * self.voxel  # box coordinates
        self.truth = torch.as_tensor(volume.data)[z, y, x].reshape(-1).float()
        self.every = int(every)
        self.weights: torch.Tensor | None = None  # (lattice,) squared error plus floor, from the last scoring
        self._cdf: torch.Tensor | None = None

    def score(self, model: Siren, device: torch.device) -> None:
        pred = values_at(model, self.lattice.to(device), self.extent.to(device))
        e2 = (pred.float().cpu() - self.truth) ** 2
        self.set_weights(e2 + 0.1 * e2.mean())

    def set_weights(self, weights: torch.Tensor) -> None:
        self.weights = weights
        cdf = torch.cumsum(weights.double(), 0)
        if not cdf[-1] > 0:  # an INR exact at every scored voxel (a constant volume): draw uniformly
            cdf = torch.arange(1, len(cdf) + 1, dtype=torch.float64)
        self._cdf = cdf / cdf[-1]

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """(n, 3) box points."""
        u = torch.rand(n, generator=generator, dtype=torch.float64)
        idx = torch.searchsorted(self._cdf, u).clamp(max=len(self.lattice) - 1)
        jitter = (torch.rand(n, 3, generator=generator) * self.stride - 0.5) * self.voxel
        return torch.minimum(torch.clamp(self.lattice[idx] + jitter, min=0), self.extent)


def fit_data_inr(volume: Volume, tf: TransferFunction, cfg: DataInrConfig, *, checkpoint: Path | None = None,
                 device: torch.device | str = "cpu", log: Callable[[str], None] = print) -> DataInr:
    """The data INR of the configured size, grown (its width doubled) until its voxel PSNR reaches
    `cfg.target_psnr`; `config["capacity"]` records every size tried."""
    # widths only: the old ladder's (w, s/2) rung, kept only where it met the target, cost its images 0.9-1.3 dB
    # (docs/performance.md, "The data INR"); everywhere else the same sizes are tried
    rungs = ladder(cfg.width, cfg.steps, cfg.max_width, double_steps=False)  # max_width below width: width

    def attempt(rung: Rung) -> tuple[DataInr, float]:
        sized = replace(cfg, width=rung.width, steps=rung.steps)
        ckpt = None if checkpoint is None else checkpoint.with_name(f"{checkpoint.name}.w{rung.width}s{rung.steps}")
        inr = fit_data_inr_once(volume, tf, sized, checkpoint=ckpt, device=device, log=log)
        return inr, inr.psnr

    inr, choice = climb(rungs, cfg.target_psnr, attempt, log=log, what="data INR")
    # the renderer's ranges for the size kept alone: 8 INR evaluations a voxel, once a rung they were most of a large
    # volume's job (512³: ~13 min a rung on one thread)
    model = inr.model.to(device)
    inr.cell_lo, inr.cell_hi = inr_cell_ranges(model, volume, device=device, log=log)
    inr.model = model.cpu()
    inr.config = {**inr.config, "capacity": choice.to_dict()}  # the stored size, and how it was chosen
    if warning := choice.warning("the data INR's voxel PSNR", "data_inr.steps or data_inr.max_width"):
        log(warning)
    return inr


@dataclass
class DataInrDraw:
    """One step's points (box, visible and error-driven), drawn on the host and moved to the device: the input of
    `DataInrFit.update` (and of its CUDA graph)."""
    pts: torch.Tensor  # (1, N, 3) in volume coordinates


class DataInrFit:
    """A data INR being fitted, and one optimiser step of it (`step`): the loop body of `fit_data_inr_once`, which
    `bench stages` times as it is. The step draws its points on the host (`draw`; the error-driven sampler rescores
    the voxels there every `error_every` steps, the one place it reads the device) and copies them without
    waiting; the update (`update`) reads nothing back and copies nothing from the host (tests/test_syncs.py), so
    that it can be one replayed CUDA graph (`data_inr.cuda_graph`)."""

    def __init__(self, volume: Volume, tf: TransferFunction, cfg: DataInrConfig, *, device: torch.device,
                 log: Callable[[str], None] = print):
        self.cfg, self.device = cfg, device
        self.model = Siren(cfg.siren, seeded(cfg.seed, Stream.DATA_INR_INIT)).to(device)
        self.graphs = requested(cfg.cuda_graph, "data_inr.cuda_graph", device, log)
        self.opt = Adam(self.model.parameters(), cfg.lr, capturable=self.graphs is not None)
        self.grid = torch.as_tensor(volume.data, device=device)[None]
        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32, device=device)
        self.n_error = int(round(cfg.points * cfg.error_fraction))
        # the visible share is of all points; PointSampler draws the points left after the error-driven ones
        share = cfg.visible_fraction
        if self.n_error:
            share = min(1.0, cfg.visible_fraction * cfg.points / max(1, cfg.points - self.n_error))
        self.sampler = PointSampler(volume, tf, share)
        self.hard = ErrorSampler(volume, cfg.error_every) if self.n_error else None

    def step(self, step: int) -> torch.Tensor:
        """Optimiser step `step` (its points depend only on the seed and `step`); the loss before it, on the
        device."""
        set_lr(self.opt, cosine_lr(step, self.cfg, self.cfg.width))
        draw = self.draw(step)
        return self.update(draw) if self.graphs is None else self.graphs(self.update, draw)

    def draw(self, step: int) -> DataInrDraw:
        """Step `step`'s points, on the device without waiting for it (on CUDA a blocking copy from ordinary host
        memory waits for the previous step's kernels)."""
        cfg, hard = self.cfg, self.hard
        gen = seeded(cfg.seed, Stream.DATA_INR_STEP, step)
        pts = self.sampler.sample(1, cfg.points - self.n_error, gen)
        if hard is not None:
            if step % hard.every == 0:  # a resumed run starts with the scores its checkpoint kept
                hard.score(self.model, self.device)
            pts = torch.cat([pts, hard.sample(self.n_error, gen)[None]], dim=1)
        return DataInrDraw(to_device(pts, self.device))

    def update(self, draw: DataInrDraw) -> torch.Tensor:
        """The optimiser step on `draw`: the loss before it."""
        with torch.no_grad():
            target = lookup_grids(self.grid, draw.pts, self.extent)[0]
        loss = ((self.model(box_to_siren(draw.pts[0], self.extent)) - target) ** 2).mean()
        self.opt.zero_grad(set_to_none=self.graphs is None)  # a graph's kernels write to fixed addresses
        loss.backward()
        self.opt.step()
        return loss.detach()


def fit_data_inr_once(volume: Volume, tf: TransferFunction, cfg: DataInrConfig, *, checkpoint: Path | None = None,
                      device: torch.device | str = "cpu", log: Callable[[str], None] = print) -> DataInr:
    """Fit a data INR of exactly cfg's size to trilinear samples of the volume (Adam, cosine decay,
    resumable); without its macro-cell ranges, which `fit_data_inr` makes for the size it keeps."""
    device = torch.device(device)
    run = DataInrFit(volume, tf, cfg, device=device, log=log)
    model, opt, hard = run.model, run.opt, run.hard
    cfg = replace(cfg, cuda_graph=run.graphs is not None)  # what was done: the checkpoint's and the INR's record
    fingerprint = _fingerprint(volume, cfg)
    start = 0
    if state := resume(checkpoint, fingerprint, log=log, map_location=device, weights_only=True):
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start = int(state["step"])
        if hard is not None:
            hard.set_weights(state["error_weights"].cpu())  # loaded onto `device`; points are drawn on the CPU
        log(f"resuming from {checkpoint} at step {start}/{cfg.steps}")
    nonfinite = FirstNonFinite((), device)  # read where the host reads anyway: checkpoints and log lines
    t0 = time.perf_counter()
    with stop_signals(checkpoint is not None) as stop:
        for step in range(start, cfg.steps):
            loss = run.step(step)
            nonfinite.record(loss, step)
            done = step + 1
            stopping = stop.requested and done < cfg.steps
            saving = checkpoint is not None and (done % cfg.checkpoint_every == 0 and done < cfg.steps or stopping)
            logging = done % max(1, cfg.steps // 10) == 0 or done == cfg.steps
            if (saving or logging) and (found := nonfinite.first()) is not None:
                raise ValueError(f"data INR fit diverged at step {found[0]} (loss {float(found[2])}); lower "
                                 f"data_inr.lr (now {cfg.lr})")
            if saving:
                state = {"fingerprint": fingerprint, "step": done, "model": model.state_dict(),
                         "optimizer": opt.state_dict()}
                if hard is not None:
                    state["error_weights"] = hard.weights
                atomic_torch_save(checkpoint, state)
            if stopping:
                raise stop.stopped(f"at step {done}/{cfg.steps}", checkpoint)
            if logging:
                rate = (done - start) * cfg.points / (time.perf_counter() - t0)
                log(f"step {done}/{cfg.steps}  PSNR(batch) {float(-10 * torch.log10(loss)):.1f} dB  "
                    f"{rate:,.0f} points/s  {eta(done, cfg.steps, t0, start=start)}")
    if checkpoint is not None and checkpoint.exists():
        checkpoint.unlink()
    value, worst = voxel_errors(model, volume, device=device, log=log)
    log(f"data INR: {model.layout.n_params} parameters, voxel PSNR {value:.2f} dB, max error {worst:.4f}")
    return DataInr(model.cpu(), np.asarray(volume.extent), value, worst, asdict(cfg), volume=volume.checksum)


# lattice points of inr_cell_ranges' values held at once (a slab of macro-cells, ~4 bytes each and its max pools)
RANGE_SLAB_POINTS = 1 << 24


def inr_cell_ranges(model: Siren, volume: Volume, *, cell: int = 16, refine: int = 2, margin: float = 0.01,
                    chunk: int = 1 << 16, device: torch.device | str = "cpu",
                    log: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The INR's (min, max) per `cell`³-voxel macro-cell, from the INR itself on a lattice `refine`× finer
    than the voxels, widened by `margin` for the values between lattice points.

    Ranges of the raw volume would not do: where the INR overshoots a sharp feature (its worst voxel
    error), a cell the volume calls empty can hold visible INR values, and the renderer would drop them.

    The lattice is `refine`³ times the voxels: its points and values were made whole (~200 bytes a voxel, 3.9 GiB
    for a 256³ volume). They are made `chunk` points at a time in the lattice's order, as before, and each slab of
    macro-cells is reduced as soon as its lattice planes are in, so only a slab is held; the same values, the same
    ranges (a cell's range is its own points' min and max). `log`: a line a minute while it runs.
    """
    device = torch.device(device)
    axes = lattice_axes(volume, refine, device)
    depth, rows, cols = (len(a) for a in axes)
    plane, total, m = rows * cols, depth * rows * cols, cell * refine
    extent = torch.as_tensor(volume.extent, dtype=torch.float32, device=device)
    held, start, made = [], 0, 0  # values of lattice points start.. made (flat, in (z, y, x) order)
    los, his = [], []
    chunks = lattice_values(model, axes, extent, chunk, log=log, what="data INR: the renderer's macro-cell ranges")
    with torch.no_grad():
        for z0, z1 in cell_slabs(depth, m, max(1, RANGE_SLAB_POINTS // (plane * m))):
            while made < z1 * plane:
                held.append(next(chunks))
                made = min(made + chunk, total)
            values = torch.cat(held)
            lo, hi = cell_ranges(values[z0 * plane - start:z1 * plane - start].view(z1 - z0, rows, cols), m)
            los.append(lo.cpu())
            his.append(hi.cpu())
            held, start = [values[z1 * plane - plane - start:]], z1 * plane - plane
    lo, hi = torch.cat(los), torch.cat(his)
    return (lo - margin).numpy(), (hi + margin).numpy()


def _fingerprint(volume: Volume, cfg: DataInrConfig) -> str:
    h = hashlib.sha256(volume.data.tobytes())
    h.update(json.dumps([changed_settings("data_inr", asdict(cfg)), np.asarray(volume.extent).tolist()]).encode())
    return h.hexdigest()

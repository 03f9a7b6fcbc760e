"""`diffshadow bench stages`: the per-step cost of every heavy stage at a config's sizes, on this device, and
each stage's time projected to that config's steps, epochs and lights.

Every stage is timed through the loop body it runs (`fit.SubsetFit.step`, `data_inr.DataInrFit.step`,
`diffusion.train.train_batch`, `diffusion.finetune.train_step`, `diffusion.sample.generate`,
`truth.transmittance_per_light`) on synthetic inputs of the config's shapes: random weights, points and
shadows, so that no earlier stage is needed. Only the volume is the scene's own (the shadow march and the
point sampler read it). Per stage: seconds per step (the median of timed steps after a warm-up, a device
sync around each), kernel-launching ops, host syncs and tensors built from host data per step
(`bench.profile.op_counts`, counts that do not drift with load), peak memory (CUDA's allocator, or the
process's sampled resident set added while the stage was built and run on a CPU), and the projection. The
projection multiplies the step by the config's count of such steps; it leaves out start-up, checkpoints,
logging and the periodic checks (validation, the seen-light gap), which the workflow's phase timings
(stage_costs.tsv) show.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import platform
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from diffshadow.bench.profile import OPTIMIZER_STEP, op_counts
from diffshadow.bench.render import _sync
from diffshadow.hpc import device_name
from diffshadow.io import atomic_write_text

if TYPE_CHECKING:  # the stages import what they time inside themselves
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import Volume

STAGES = ("fit_siren", "preoptimize", "train_data_inr", "train_diffusion", "fit_correction", "finetune_render",
          "sample_shadows", "eval_truth")


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _trim() -> None:
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class PeakMemory:
    """Context manager: peak bytes the enclosed code added (CUDA allocator, or sampled CPU RSS)."""

    def __init__(self, device: torch.device, interval: float = 0.002):
        self.device, self.interval = device, interval
        self.peak = 0

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
            return self
        _trim()
        self.base = _rss()
        self._max = self.base
        self._stop = threading.Event()

        def poll():
            while not self._stop.is_set():
                self._max = max(self._max, _rss())
                self._stop.wait(self.interval)

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak = torch.cuda.max_memory_allocated(self.device) - self.base
        else:
            self._max = max(self._max, _rss())
            self._stop.set()
            self._thread.join()
            self.peak = self._max - self.base


@dataclass
class Timed:
    """One stage's step, ready to run: `step(i)` runs step i; `per` says what one step is, `count` how many the
    config runs, `note` how that count was reached."""

    step: Callable[[int], object]
    per: str
    count: float
    note: str
    units: float = 1.0  # work units (SIRENs, lights) one step covers, for "seconds per SIREN/light"


def _lights(n: int, center, gen: np.random.Generator) -> np.ndarray:
    """`n` unit directions scattered in a 30-degree cap around `center`."""
    c = np.asarray(center, dtype=np.float64)
    c = c / np.linalg.norm(c)
    v = c[None] + 0.3 * gen.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _halo(cfg: dict, fit) -> tuple[int, int]:
    """The mean halo a subset of the config's lights fits (`fit.halo`) and the mean it holds (`fit.rounds`),
    rounded: 0 for one subset, or no halo."""
    from diffshadow.lights import configured_light_sets
    from diffshadow.seams import halo_size

    sets = configured_light_sets(cfg["lights"])
    fitted, held = halo_size(np.asarray(sets["train"]["cartesian"]), sets["center"], int(cfg["subset_size"]), fit)
    return round(fitted), round(held)


def _pool(m: int, points: int, n_train: int, cfg: dict, volume, *, seed: int):
    """`m` synthetic pool lights with `points` random points and shadows each, blended from up to 4 of `n_train`
    training rows: a step's cost depends on these shapes, not on the values."""
    from diffshadow.lights import PoolLights

    g, k = torch.Generator().manual_seed(seed), min(4, n_train)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    return PoolLights(lights=torch.as_tensor(_lights(m, cfg["lights"]["center"], np.random.default_rng(seed))),
                      points=torch.rand(m, points, 3, generator=g) * extent, values=torch.rand(m, points, generator=g),
                      neighbours=torch.randint(0, n_train, (m, k), generator=g), blend=torch.full((m, k), 1.0 / k))


def _scene(cfg: dict):
    from diffshadow.volume import scene_volume

    return scene_volume(cfg)


def _captured(graphs, step: Callable[[int], object]) -> str:
    """With `graphs` (a stage's `StepGraphs`), the eager warm-up steps and the capture run before any step is
    timed; the words the step's description gets for it."""
    if graphs is None:
        return ""
    for i in range(graphs.warmup + 1):
        step(i)
    return "; CUDA graph"


def fit_siren(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction, *, subset: bool = True) -> Timed:
    """A fit step of one subset (K SIRENs jointly), or (`subset` False) preoptimize's single-light step."""
    from diffshadow.fit import FitConfig, SubsetFit
    from diffshadow.siren import SirenConfig, WeightLayout, init_siren

    fit = FitConfig.from_config(cfg["fit"])
    siren = SirenConfig.from_config(cfg["siren"])
    layout = WeightLayout.for_siren(siren)
    n_lights = int(cfg["lights"]["count"])
    k = min(int(cfg["subset_size"]), n_lights) if subset else 1
    # fitted beside the subset's lights and discarded; held at stored SIRENs in the blend loss (here: any weights)
    halo, held = _halo(cfg, fit) if subset else (0, 0)
    lights = _lights(k + halo, cfg["lights"]["center"], np.random.default_rng(0))
    init = layout.flatten(init_siren(siren, torch.Generator().manual_seed(0)))
    pool = None
    if subset and fit.blend_weight > 0 and k >= 2:
        # a pool of the size one subset takes (blend_per_light pool lights per training light, ~all of them its own)
        pool = _pool(fit.blend_per_light * k, fit.blend_points, k + halo + held, cfg, volume, seed=1)
    if not subset:
        fit = replace(fit, lr=float(cfg["preoptimize"]["lr"]))
    stored = init.expand(held, -1).clone() if held and pool is not None else None
    run = SubsetFit(init, layout, siren, volume, tf, lights, fit, pool=pool, held=stored, device=device,
                    log=lambda m: None)
    graphed = _captured(run.graphs, run.step)
    if subset:
        jobs = math.ceil(n_lights / int(cfg["subset_size"]))
        with_halo = f" and a halo of {halo}" if halo else ""
        with_halo += f" fitted and {held} held" if held else ""
        return Timed(run.step, f"step of {k + halo} SIRENs{graphed}", fit.steps,
                     f"{fit.steps} steps per job ({jobs} jobs of up to {cfg['subset_size']} lights{with_halo}, one GPU "
                     f"each)", k)
    steps = int(cfg["preoptimize"]["steps"])
    return Timed(run.step, f"step of 1 SIREN{graphed}", steps,
                 f"{steps} steps at siren.width (capacity growth not counted)")


def train_data_inr(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction) -> Timed:
    from diffshadow.data_inr import DataInrConfig, DataInrFit

    dcfg = DataInrConfig.from_config(cfg["data_inr"])
    run = DataInrFit(volume, tf, dcfg, device=device, log=lambda m: None)
    # the error-driven sampler rescores every voxel every error_every steps (periodic, like a checkpoint): scored
    # once here, then only the steps between rescorings are timed
    if run.hard is not None:
        run.hard.score(run.model, device)

    def step(i: int) -> torch.Tensor:
        return run.step(i + 1 + (i // max(1, dcfg.error_every - 1)))

    return Timed(step, f"step of {dcfg.points} points{_captured(run.graphs, step)}",
                 dcfg.steps, f"{dcfg.steps} steps at data_inr.width (capacity growth and voxel rescoring not counted)")


def _training_data(cfg: dict, volume, device: torch.device):
    """Synthetic geometry-stage inputs of the config's shapes: weights near a common init (as stage 1's are),
    presampled points and shadows, pool lights."""
    from diffshadow.diffusion.config import DiffusionConfig
    from diffshadow.diffusion.train import TrainingData
    from diffshadow.siren import SirenConfig, WeightLayout, init_siren

    dcfg = DiffusionConfig.from_config(cfg["diffusion"])
    siren = SirenConfig.from_config(cfg["siren"])
    dcfg = dcfg.for_siren(siren.width).for_device(device)
    layout = WeightLayout.for_siren(siren)
    n, g = int(cfg["lights"]["count"]), torch.Generator().manual_seed(2)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    init = layout.flatten(init_siren(siren, g))
    weights = init + 0.01 * torch.randn(n, layout.n_params, generator=g)
    lights = torch.as_tensor(_lights(n, cfg["lights"]["center"], np.random.default_rng(2)))
    pool = None
    if dcfg.pool_lights > 0:
        pool = _pool(dcfg.pool_lights, dcfg.pool_points, n, cfg, volume, seed=3)
    data = TrainingData(weights=weights, lights=lights,
                        points=torch.rand(n, dcfg.presample_points, 3, generator=g) * extent,
                        values=torch.rand(n, dcfg.presample_points, generator=g), extent=extent, layout=layout,
                        siren=siren, pool=pool)
    return dcfg, data


def train_diffusion(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction) -> Timed:
    from diffshadow.diffusion.config import build_model, make_optimizer
    from diffshadow.diffusion.schedule import Schedule
    from diffshadow.diffusion.standardize import Standardizer
    from diffshadow.diffusion.train import Ema, draw_batch, step_graphs, train_batch
    from diffshadow.progress import FirstNonFinite
    from diffshadow.sampling import Stream, seeded, to_device

    dcfg, data = _training_data(cfg, volume, device)
    model = build_model(data.layout, dcfg).to(device)
    std = Standardizer.fit(data.layout, data.weights, dcfg.standardize)
    z_all = std.standardize(data.weights).float().to(device)
    on_device = data.to(device)
    pool = on_device.pool if dcfg.pool_lights > 0 else None
    graphs = step_graphs(dcfg, device, log=lambda message: None)
    opt = make_optimizer(model.parameters(), dcfg.lr, dcfg.weight_decay, capturable=graphs is not None)
    ema = Ema(model, dcfg.ema) if dcfg.ema > 0 else None
    schedule, nonfinite = Schedule(), FirstNonFinite((), device)
    n = len(z_all)
    per_epoch = math.ceil(n / dcfg.batch_size)

    def step(i: int):
        gen = seeded(dcfg.seed, Stream.DIFFUSION_EPOCH, i)
        idx = to_device(torch.randperm(n, generator=gen, device=gen.device)[:dcfg.batch_size], device)
        batch = draw_batch(gen, idx, on_device, pool, dcfg, schedule.steps, device)
        return train_batch(model, opt, ema, std, on_device, z_all, pool, batch, dcfg, schedule, nonfinite, 0, i,
                           graphs)

    graphed = _captured(graphs, step)
    grows = dcfg.target_gap > 0 and dcfg.max_epochs > dcfg.epochs
    epochs = dcfg.max_epochs if grows else dcfg.epochs
    return Timed(step, f"step of {dcfg.batch_size} lights ({model.n_params():,}-parameter '{dcfg.preset}' model"
                 f"{dcfg.products}{graphed})",
                 per_epoch * epochs, f"{per_epoch} steps per epoch x {epochs} epochs"
                 + (" (max_epochs: the gap check may stop sooner)" if grows else ""))


def finetune_render(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction) -> Timed:
    from diffshadow.diffusion.config import build_model, make_optimizer
    from diffshadow.diffusion.finetune import FinetuneConfig, FinetuneData, step_graphs, train_step
    from diffshadow.diffusion.schedule import Schedule
    from diffshadow.diffusion.standardize import Standardizer
    from diffshadow.progress import FirstNonFinite
    from diffshadow.render.bundle import build_bundle
    from diffshadow.render.camera import fibonacci_views

    fcfg = FinetuneConfig.from_config(cfg["finetune"])
    dcfg, data = _training_data(cfg, volume, device)
    cameras = fibonacci_views(volume.extent, fcfg.views, size=fcfg.image_size, fov=fcfg.fov)
    bundle = build_bundle(volume, tf, cameras, step=fcfg.step)  # the real views' samples: their count sets the cost
    n = len(data.weights)
    g = torch.Generator().manual_seed(4)
    targets = torch.rand(n, fcfg.views, bundle.pix.shape[1], 3, generator=g)  # the foreground pixels' colours
    fdata = FinetuneData(data, bundle, targets).to(device)
    model = build_model(data.layout, dcfg).to(device)
    std = Standardizer.fit(data.layout, data.weights, dcfg.standardize)
    z_all = std.standardize(data.weights).float().to(device)
    graphs = step_graphs(fcfg, fcfg.nproc, device, log=lambda message: None)  # as the run: one process only
    opt = make_optimizer(model.parameters(), fcfg.lr, dcfg.weight_decay, capturable=graphs is not None)
    schedule, nonfinite = Schedule(), FirstNonFinite((), device)
    per_rank = math.ceil(fcfg.batch_size / fcfg.nproc)

    def step(i: int):
        batch = [(i * fcfg.batch_size + j) % n for j in range(fcfg.batch_size)]
        return train_step(model, model, opt, std, fdata, z_all, batch, 0, fcfg.nproc, i, fcfg, dcfg, schedule,
                          nonfinite, graphs)

    per_epoch = math.ceil(n / fcfg.batch_size)
    return Timed(step, f"step of one process ({per_rank} of {fcfg.batch_size} lights; {fcfg.nproc} process"
                 f"{'es' if fcfg.nproc > 1 else ''}"
                 f"{dcfg.products}{_captured(graphs, step)})",
                 per_epoch * fcfg.epochs, f"{per_epoch} steps per epoch x {fcfg.epochs} epochs, each process in "
                 f"parallel (DDP's all-reduce not counted)")


def sample_shadows(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction) -> Timed:
    from diffshadow.diffusion.config import build_model
    from diffshadow.diffusion.sample import generate
    from diffshadow.diffusion.standardize import Standardizer

    dcfg, data = _training_data(cfg, volume, device)
    model = build_model(data.layout, dcfg).to(device).eval()
    std = Standardizer.fit(data.layout, data.weights, dcfg.standardize)
    batch = min(64, len(data.weights))  # generate's batch of lights
    lights = data.lights[:batch].numpy()

    def step(i: int):
        with torch.no_grad():
            return generate(model, std, lights, steps=dcfg.ddim_steps, seed=i, temperature=dcfg.temperature,
                            device=device)

    total = int(cfg["lights"]["count"]) + int(cfg["lights"]["unseen"])
    # a model share other than 1 also samples the validation lights it is chosen on (`auto`): the march and the
    # scoring of that choice are left out (5.3 s of the README run's 9.1 s on 2 CPU cores, DDIM included)
    mix = cfg.get("mix", {})
    val = int(mix.get("val_lights", 0)) if str(mix.get("model_share", 1)) == "auto" else 0
    return Timed(step, f"DDIM ({dcfg.ddim_steps} steps) of {batch} SIRENs", (total + val) / batch,
                 f"{total} lights (training and unseen)" + (f" and {val} validation lights" if val else "")
                 + f" in batches of {batch}", batch)


def fit_correction(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction) -> Timed:
    """A step of the blend's correction: the config's stored SIRENs (near a common init) corrected at synthetic
    lights of the config's shapes (`_pool`: a step's cost depends on the shapes, not on the values)."""
    from diffshadow.correction import CorrectionConfig, CorrectionFit, CorrectionLights
    from diffshadow.siren import SirenConfig, WeightLayout, init_siren

    ccfg = CorrectionConfig.from_config(cfg.get("correction"))
    siren = SirenConfig.from_config(cfg["siren"])
    layout = WeightLayout.for_siren(siren)
    n, g = int(cfg["lights"]["count"]), torch.Generator().manual_seed(4)
    weights = layout.flatten(init_siren(siren, g)) + 0.01 * torch.randn(n, layout.n_params, generator=g)
    pool = _pool(max(1, ccfg.lights), 2 * max(1, ccfg.points), n, cfg, volume, seed=4)
    train = _lights(n, cfg["lights"]["center"], np.random.default_rng(4))
    fit = CorrectionFit(weights, CorrectionLights(pool, torch.as_tensor(volume.extent, dtype=torch.float32),
                                                  max(1, ccfg.points)), train, layout, siren, ccfg, device)
    return Timed(fit.step, f"step of {ccfg.batch_lights} lights x {ccfg.batch_points} points", ccfg.steps,
                 f"{ccfg.steps} steps (the march of its {ccfg.lights} lights and the held-out checks not counted)")


def eval_truth(cfg: dict, device: torch.device, volume: Volume, tf: TransferFunction) -> Timed:
    from diffshadow.shadow import ShadowField, transmittance_per_light

    points = int(cfg.get("evaluate", {}).get("points", 16384))
    field = ShadowField.build(volume, tf, device=device)
    g = torch.Generator().manual_seed(5)
    pts = torch.rand(2 * points, 3, generator=g) * torch.as_tensor(volume.extent, dtype=torch.float32)
    total = int(cfg["lights"]["count"]) + int(cfg["lights"]["unseen"])
    group = max(1, min(total // 10, 32))  # TruthPoints marches ~10 groups of lights together
    lights = _lights(group, cfg["lights"]["center"], np.random.default_rng(5))
    return Timed(lambda i: transmittance_per_light(field, tf, lights, pts), f"exact shadows of {group} lights at "
                 f"{2 * points} points", total / group, f"{total} lights in groups of {group}", group)


BUILDERS = {"fit_siren": fit_siren, "preoptimize": lambda c, d, v, t: fit_siren(c, d, v, t, subset=False),
            "train_data_inr": train_data_inr, "train_diffusion": train_diffusion, "finetune_render": finetune_render,
            "fit_correction": fit_correction, "sample_shadows": sample_shadows, "eval_truth": eval_truth}


def measure(timed: Timed, device: torch.device, *, warmup: int, budget_s: float, max_steps: int) -> dict:
    """Seconds per step (median of timed steps, synced), and ops and syncs of one step."""
    for i in range(warmup):
        timed.step(i)
    _sync(device)
    times: list[float] = []
    start = time.perf_counter()
    i = warmup
    while len(times) < max_steps and (len(times) < 2 or time.perf_counter() - start < budget_s):
        t0 = time.perf_counter()
        timed.step(i)
        _sync(device)
        times.append(time.perf_counter() - t0)
        i += 1
    counts = op_counts(lambda: timed.step(i), host_scopes=(OPTIMIZER_STEP,))
    step_s = float(np.median(times))
    return {"step_s": step_s, "steps_timed": len(times), **counts}


def bench_stages(cfg: dict, out: Path, *, device: torch.device, stages: list[str] | None = None,
                 budget_s: float = 2.0, warmup: int = 2, max_steps: int = 50, config_name: str = "",
                 log: Callable[[str], None] = print) -> dict:
    """Measure each stage of `stages` (default all) at `cfg`'s sizes; write `out` (JSON) and print a table."""
    if max_steps < 1:  # no timed step: a NaN time per step, projected to a NaN
        raise ValueError(f"bench stages: --max-steps: expected at least 1 timed step, got {max_steps}")
    stages = list(stages or STAGES)
    unknown = [s for s in stages if s not in BUILDERS]
    if unknown:
        raise ValueError(f"bench stages: unknown stage {unknown[0]!r}; expected some of {', '.join(STAGES)}")
    volume, tf = _scene(cfg)
    rows = {}
    for name in stages:
        t0 = time.perf_counter()
        with PeakMemory(device) as mem:
            timed = BUILDERS[name](cfg, device, volume, tf)
            row = measure(timed, device, warmup=warmup, budget_s=budget_s, max_steps=max_steps)
        row.update(per=timed.per, steps=timed.count, count_note=timed.note, peak_memory_mib=mem.peak / 2 ** 20,
                   projected_s=row["step_s"] * timed.count, units=timed.units,
                   seconds_per_unit=row["step_s"] / timed.units,
                   bench_s=time.perf_counter() - t0)
        rows[name] = row
        log(f"{name:16s} {row['step_s'] * 1e3:9.2f} ms/{timed.per}: {row['ops']} ops, {row['syncs']} host syncs "
            f"({row['host_reads']} host reads), {row['host_tensors']} host tensors, peak "
            f"{row['peak_memory_mib']:.0f} MiB; projected {_duration(row['projected_s'])} ({timed.note})")
    result = {"config": config_name, "device": device_name(device), "device_type": device.type,
              "torch": torch.__version__,
              "cuda": torch.version.cuda, "threads": torch.get_num_threads(), "host": platform.node(),
              "peak_memory": "CUDA allocator peak" if device.type == "cuda" else "resident set added (sampled)",
              "stages": rows}
    atomic_write_text(out, json.dumps(result, indent=1) + "\n")
    log(f"wrote {out}")
    return result


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"

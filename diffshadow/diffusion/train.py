"""Training the weight-space diffusion model (paper §3.3): x0 MSE + geometry loss, resumable. The model sees
standardised weights (`diffusion.standardize`); one loss (`batch_loss`) serves this stage and fine-tuning.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from diffshadow.adam import Adam, step_lr
from diffshadow.config import changed_settings
from diffshadow.diffusion.config import DiffusionConfig, DiffusionError, build_model, make_optimizer
from diffshadow.diffusion.geometry import geometry_error
from diffshadow.diffusion.model import WeightTransformer
from diffshadow.diffusion.sample import generate
from diffshadow.diffusion.schedule import Schedule
from diffshadow.diffusion.standardize import Standardizer
from diffshadow.graphs import StepGraphs, requested
from diffshadow.io import atomic_torch_save, resume
from diffshadow.lights import PoolLights
from diffshadow.metrics import psnr
from diffshadow.progress import FirstNonFinite, eta, resumed_at
from diffshadow.sampling import Stream, seeded, to_device
from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout, box_to_siren, forward_precision
from diffshadow.stopping import stop_signals
from diffshadow.truth import check_rows

# (largest SIREN width, preset) for `preset: auto`: the model widens with the SIREN, so a scene whose stage 1
# chose width 64 spends more (tooth: seen / unseen +1.1 / +1.2 dB for 2x the time) and nucleon's width 32 keeps
# its cost. Wider SIRENs also get "medium": the step beyond it is not measured (docs/performance.md).


_geometry_error = geometry_error  # indirection so tests can inject a failure mid-run


def pool_noised(pool: PoolLights, z_all: torch.Tensor, j: torch.Tensor, t: torch.Tensor, noise: torch.Tensor,
                schedule: Schedule) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pool lights `j` as model input beside the training lights: their x0 targets, noised x_t, directions."""
    x0 = pool.x0(z_all, j)
    return x0, schedule.q_sample(x0, t, noise), pool.lights[j].float()


@dataclass
class TrainingData:
    weights: torch.Tensor  # (N, n_params)
    lights: torch.Tensor  # (N, 3)
    points: torch.Tensor  # (N, M, 3) box coordinates
    values: torch.Tensor  # (N, M) true shadow
    extent: torch.Tensor  # (3,)
    layout: WeightLayout
    siren: SirenConfig
    pool: PoolLights | None = None
    # held-out points (C, 3) and the true shadow there (R, C) of the training lights geometry.check_rows picks:
    # where the seen-light gap is measured (diffusion.target_gap); never trained on
    check: tuple[torch.Tensor, torch.Tensor] | None = None
    region: dict | None = None  # the training lights' region (lights.LightRegion), saved with the checkpoint
    extinction: str | None = None  # the scene's extinction field (volume.extinction_id), saved with the checkpoint

    def to(self, device: torch.device | str) -> TrainingData:
        return dataclasses.replace(self, weights=self.weights.to(device), lights=self.lights.to(device),
                                   points=self.points.to(device), values=self.values.to(device),
                                   extent=self.extent.to(device),
                                   pool=self.pool.to(device) if self.pool is not None else None,
                                   check=tuple(t.to(device) for t in self.check) if self.check is not None else None)


def _fingerprint(data: TrainingData, cfg: DiffusionConfig) -> str:
    h = hashlib.sha256()
    tensors = [data.weights, data.lights, data.points, data.values]
    if data.pool is not None and cfg.pool_lights > 0:
        p = data.pool
        tensors += [p.lights, p.points, p.values, p.neighbours, p.blend]
    if data.check is not None and cfg.target_gap > 0:
        tensors += list(data.check)
    for t in tensors:
        h.update(t.detach().cpu().numpy().tobytes())
    h.update(json.dumps(changed_settings("diffusion", asdict(cfg)), sort_keys=True).encode())
    return h.hexdigest()


def ema_decay(target: float, step: int) -> float:
    """The EMA decay at optimizer step `step` (0-based): (1 + step) / (10 + step) until that reaches `target`.
    Without the warm-up the average keeps the untrained initial weights for ~1/(1 - target) steps: at 0.999
    over tooth's 1200 steps, seen lights came out at 18.6 dB against 34.1 without an EMA (bec80e7)."""
    return min(target, (1 + step) / (10 + step))


PLATEAU_CHECKS = 3  # growth stops when these many checks in a row gain under 0.1 dB on the best before them


@torch.no_grad()
def seen_gap_db(model: WeightTransformer, std: Standardizer, data: TrainingData, cfg: DiffusionConfig) -> float:
    """How far the SIRENs `model` generates for training lights lie under their stage-1 SIRENs, in dB: the median
    over the lights `check_rows` picks of stage-1 PSNR minus generated PSNR at the held-out check points
    (positive: generated worse). Sampled as `sample_shadows` does (DDIM, cfg.ddim_steps, cfg.temperature), scored
    as `evaluate_voxels` scores the "box" set, so it estimates the seen-light gap the run will report."""

    if data.check is None:
        raise DiffusionError("diffusion.target_gap needs held-out check points in the geometry points; rerun "
                             "presample (or set diffusion.target_gap: 0)")
    points, values = data.check
    device = points.device
    rows = check_rows(len(data.weights)).to(device)
    if len(values) != len(rows):
        raise DiffusionError(f"the geometry points hold check values for {len(values)} lights, not the "
                             f"{len(rows)} training lights checked; rerun presample")
    was_training = model.training
    model.eval()
    generated = generate(model, std, data.lights[rows].cpu().numpy(), steps=cfg.ddim_steps, seed=cfg.seed,
                         temperature=cfg.temperature, device=device)
    model.train(was_training)
    at_checks = box_to_siren(points.expand(len(rows), -1, -1), data.extent)
    stage1, ours = (psnr(BatchedSiren(w.to(device).float(), data.layout, data.siren.blocks)(at_checks), values, dim=1)
                    for w in (data.weights[rows], generated))
    return float((stage1 - ours).median())


class Ema:
    """An exponential moving average of the model's weights, warmed up by `ema_decay`: what sampling uses."""

    def __init__(self, model: WeightTransformer, target: float):
        self.target = target
        self.model = copy.deepcopy(model).requires_grad_(False)

    @torch.no_grad()
    def update(self, model: WeightTransformer, step: int) -> None:
        # one multi-tensor op, not a lerp per parameter tensor: on a GPU one launch for the model's 153 tensors
        # (the 'small' preset), the same bits (per-tensor lerp on the CPU, the same lerp on CUDA)
        torch._foreach_lerp_(list(self.model.parameters()), list(model.parameters()),
                             1 - ema_decay(self.target, step))


class Growth:
    """How long the geometry stage trains: past `cfg.epochs`, on while the generated seen lights lie more than
    `cfg.target_gap` dB under stage 1, checked every `checkpoint_every` epochs, up to `max_epochs` or until the gap
    stops closing. Its state (`state`, `best`) is saved with each checkpoint, so a resumed run decides the same.
    A run that stops over the target keeps the weights of its best check: at a held lr the gap wanders (tooth:
    2.15 dB at epoch 1100, 2.45 at 1200)."""

    def __init__(self, cfg: DiffusionConfig, state: dict | None = None, best: dict | None = None):
        self.cfg = cfg
        self.max_epochs = max(cfg.epochs, cfg.max_epochs)
        self.state = state if state is not None else {"checks": [], "finished": False, "reason": None}
        self.best = best  # {"epoch", "weights"} of the best check so far (its gap: in state["checks"])

    @property
    def finished(self) -> bool:
        return self.state["finished"]

    def due(self, done: int) -> bool:
        return done >= self.cfg.epochs and (done - self.cfg.epochs) % self.cfg.checkpoint_every == 0

    def check(self, done: int, sampled: WeightTransformer, gap_db: Callable[[], float], log: Callable[[str], None],
              last_good: str) -> None:
        """At epoch `done`: measure the gap (`gap_db()`) and decide whether to train on."""
        cfg, growth = self.cfg, self.state
        if cfg.target_gap <= 0 or self.max_epochs <= cfg.epochs:
            why = "diffusion.target_gap is 0" if cfg.target_gap <= 0 else "max_epochs is not past epochs"
            growth.update(finished=True, epochs=done, reason=f"fixed length ({why})")
            return
        gap = gap_db()
        if not math.isfinite(gap):
            raise DiffusionError(f"train_diffusion: the generated seen lights' PSNR is not finite at epoch {done} "
                                 f"(NaN SIREN weights?); keeping {last_good}")
        checks = growth["checks"]
        checks.append({"epoch": done, "gap_db": gap})
        best_before = min((c["gap_db"] for c in checks[:-PLATEAU_CHECKS]), default=math.inf)
        top = min(checks, key=lambda c: c["gap_db"])  # the first of equal gaps
        if top is checks[-1]:
            self.best = {"epoch": done, "weights": {k: v.detach().clone() for k, v in sampled.state_dict().items()}}
        if gap <= cfg.target_gap:
            side = "under" if gap >= 0 else "over"  # a gap can be negative: generated better than stage 1
            reason = f"generated seen lights {abs(gap):.2f} dB {side} stage 1, within the target {cfg.target_gap:g} dB"
        elif done >= self.max_epochs:
            reason = (f"reached diffusion.max_epochs {self.max_epochs} with the generated seen lights {gap:.2f} "
                      f"dB under stage 1 (target {cfg.target_gap:g} dB)")
        elif len(checks) > PLATEAU_CHECKS and min(c["gap_db"] for c in checks[-PLATEAU_CHECKS:]) > best_before - 0.1:
            reason = (f"the gap stopped closing ({gap:.2f} dB under stage 1, target {cfg.target_gap:g} dB; under 0.1 "
                      f"dB gained in the last {PLATEAU_CHECKS * cfg.checkpoint_every} epochs)")
        else:
            log(f"epoch {done}: generated seen lights {gap:.2f} dB under stage 1 (target {cfg.target_gap:g} dB at "
                f"held-out points): training on, up to epoch {self.max_epochs}")
            return
        if top["epoch"] != done:
            sampled.load_state_dict(self.best["weights"])
            reason += f"; kept the model of epoch {top['epoch']} ({top['gap_db']:.2f} dB under stage 1)"
        growth.update(finished=True, epochs=done, reason=reason, kept_epoch=top["epoch"])
        missed = top["gap_db"] > cfg.target_gap
        log(("WARNING: " if missed else "") + f"geometry stage done at epoch {done}: {reason}"
            + ("; a wider diffusion.preset or more lights.count may close it" if missed else ""))


@dataclass
class Batch:
    """One step's random draws, in a fixed order from the epoch's generator (the seed decides every one): rows
    `idx` of the training lights, their timesteps and noise and geometry points; with pool lights, as many pool
    lights `j` with theirs."""

    idx: torch.Tensor
    t: torch.Tensor
    noise: torch.Tensor
    pick: torch.Tensor | None
    j: torch.Tensor | None = None
    tp: torch.Tensor | None = None
    noise_p: torch.Tensor | None = None
    pick_p: torch.Tensor | None = None


def draw_batch(gen: torch.Generator, idx: torch.Tensor, data: TrainingData, pool: PoolLights | None,
               cfg: DiffusionConfig, steps: int, device: torch.device) -> Batch:
    b, n_params = len(idx), data.weights.shape[1]

    def randint(high: int, shape: tuple) -> torch.Tensor:
        return to_device(torch.randint(0, high, shape, generator=gen, device=gen.device), device)

    def randn(shape: tuple) -> torch.Tensor:
        return to_device(torch.randn(shape, generator=gen, device=gen.device), device)

    geometry = cfg.geometry_weight > 0
    batch = Batch(idx, randint(steps, (b,)), randn((b, n_params)),
                  randint(data.points.shape[1], (b, cfg.geometry_points)) if geometry else None)
    if pool is not None:
        batch.j, batch.tp, batch.noise_p = randint(len(pool.lights), (b,)), randint(steps, (b,)), randn((b, n_params))
        if geometry:
            batch.pick_p = randint(pool.points.shape[1], (b, cfg.geometry_points))
    return batch


def batch_loss(model: WeightTransformer, std: Standardizer, data: TrainingData, z_all: torch.Tensor,
               pool: PoolLights | None, batch: Batch, cfg: DiffusionConfig,
               schedule: Schedule) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The training loss of one batch (x0 MSE, the pool lights' x0 prior, the geometry loss of both), its x0
    and geometry parts for the log, and the model's standardised prediction (training lights first, then the
    pool's). `data` is on the model's device. The geometry stage's loss, and fine-tuning's before its rendering
    term (`finetune.step_loss`)."""
    b, x0 = len(batch.idx), z_all[batch.idx]
    x_t, t_in, light_in = schedule.q_sample(x0, batch.t, batch.noise), batch.t, data.lights[batch.idx].float()
    if pool is not None:  # one forward for both: a batch of 2b costs 0.75 of two batches of b
        x0p, x_tp, light_p = pool_noised(pool, z_all, batch.j, batch.tp, batch.noise_p, schedule)
        x_t, t_in, light_in = torch.cat([x_t, x_tp]), torch.cat([t_in, batch.tp]), torch.cat([light_in, light_p])
    with forward_precision(cfg.precision, z_all.device):
        pred_all = model(x_t, t_in, light_in)
    pred_all = pred_all.float()  # the losses and the generated SIRENs' geometry error stay float32
    loss_x0 = mean((pred_all[:b] - x0) ** 2)
    loss = loss_x0
    loss_geo = torch.zeros((), device=z_all.device)
    if pool is not None:
        loss = loss + cfg.pool_x0_weight * mean((pred_all[b:] - x0p) ** 2)
    if cfg.geometry_weight > 0:
        pts = torch.gather(data.points[batch.idx], 1, batch.pick[..., None].expand(-1, -1, 3))
        vals = torch.gather(data.values[batch.idx], 1, batch.pick)
        if pool is not None:
            pts_p, vals_p = pool.samples(batch.j, batch.pick_p)
            pts, vals = torch.cat([pts, pts_p]), torch.cat([vals, vals_p])
        err = _geometry_error(std.destandardize(pred_all), data.layout, data.siren, pts, vals, data.extent)
        loss_geo = err[:b].mean()
        loss = loss + cfg.geometry_weight * err.sum() / b  # training and pool lights, each a mean over b
    return loss, loss_x0, loss_geo, pred_all


def mean(x: torch.Tensor) -> torch.Tensor:
    """x.mean(); on a CPU summed row by row, then over the rows: PyTorch's CPU mean of a whole large tensor adds
    per-thread parts, so its last bits depend on the thread count, where each row's sum is one thread's."""
    if x.device.type != "cpu":
        return x.mean()
    return x.reshape(len(x), -1).sum(dim=1).sum() / x.numel()


def optimizer_step(model: WeightTransformer, opt: Adam, std: Standardizer, data: TrainingData,
                   z_all: torch.Tensor, pool: PoolLights | None, batch: Batch, cfg: DiffusionConfig,
                   schedule: Schedule, *, keep_grads: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Loss, backward, gradient clip and AdamW on one batch: the loss and its x0 and geometry parts, detached, on
    the device. `keep_grads` zeroes the gradients in place instead of dropping them: a CUDA graph's replays write
    the same gradient tensors every time (`diffshadow.graphs`)."""
    loss, loss_x0, loss_geo, _ = batch_loss(model, std, data, z_all, pool, batch, cfg, schedule)
    opt.zero_grad(set_to_none=not keep_grads)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    opt.step()
    return loss.detach(), loss_x0.detach(), loss_geo.detach()


def train_batch(model: WeightTransformer, opt: Adam, ema: Ema | None, std: Standardizer,
                data: TrainingData, z_all: torch.Tensor, pool: PoolLights | None, batch: Batch, cfg: DiffusionConfig,
                schedule: Schedule, nonfinite: FirstNonFinite, epoch: int, step: int,
                graphs: StepGraphs | None = None) -> torch.Tensor:
    """One optimiser step of the geometry stage (the loop body of `train_diffusion`, which `bench stages` times
    as it is); the batch's summed (x0, geometry) losses, on the device. It reads nothing back to the host
    (tests/test_syncs.py): the loss's finiteness goes to `nonfinite`, read at log lines and checkpoints. With
    `graphs` (`diffusion.cuda_graph`) the optimizer step is a CUDA graph's replay; the EMA (whose weight warms
    up step by step) and the record of a non-finite loss (which names the epoch) run outside it."""
    def optimize(b: Batch):
        return optimizer_step(model, opt, std, data, z_all, pool, b, cfg, schedule, keep_grads=graphs is not None)

    loss, loss_x0, loss_geo = optimize(batch) if graphs is None else graphs(optimize, batch)
    nonfinite.record(loss, epoch)
    if ema is not None:
        ema.update(model, step)
    return torch.stack([loss_x0, loss_geo]).double() * len(batch.idx)


def step_graphs(cfg: DiffusionConfig, device: torch.device, log: Callable[[str], None] = print) -> StepGraphs | None:
    """The geometry stage's CUDA graphs where `diffusion.cuda_graph` asks for them ("auto" or True) and the device
    has them."""
    return requested(cfg.cuda_graph, "diffusion.cuda_graph", device, log)


def train_diffusion(data: TrainingData, cfg: DiffusionConfig, checkpoint: Path, *,
                    device: torch.device | str = "cpu", log: Callable[[str], None] = print,
                    stop_after_epoch: int | None = None) -> dict:
    """Train (or resume) and return the final state; the checkpoint file holds it when done.

    `stop_after_epoch` ends the run early (as if killed after that epoch's checkpoint): tests use it.
    """
    device = torch.device(device)
    cfg = cfg.for_siren(data.siren.width).for_device(device)
    torch.manual_seed(cfg.seed)
    model = build_model(data.layout, cfg).to(device)
    log(f"weight-space transformer '{cfg.preset}': {model.n_params():,} parameters, "
        f"{len(model.sizes)} weight tokens, {len(data.weights)} training lights{cfg.products}")
    std = Standardizer.fit(data.layout, data.weights, cfg.standardize)
    z_all = std.standardize(data.weights).float().to(device)
    on_device = data.to(device)  # the training set moved once, not per step
    pool = on_device.pool if cfg.pool_lights > 0 else None
    have = 0 if data.pool is None else len(data.pool.lights)
    if cfg.pool_lights > 0 and have != cfg.pool_lights:
        raise DiffusionError(f"train_diffusion: diffusion.pool_lights is {cfg.pool_lights} but the geometry points "
                             f"hold {have} pool lights; rerun presample with this config")
    schedule = Schedule()
    graphs = step_graphs(cfg, device, log)
    # what was done, not what was asked: the checkpoint's config and fingerprint (eager steps train the same
    # bytes whatever the setting, so a CPU run resumes a checkpoint whichever it was asked)
    cfg = dataclasses.replace(cfg, cuda_graph=graphs is not None)
    opt = make_optimizer(model.parameters(), cfg.lr, cfg.weight_decay, capturable=graphs is not None)
    ema = Ema(model, cfg.ema) if cfg.ema > 0 else None
    sampled = ema.model if ema is not None else model  # the weights that sampling uses: checked, and the best kept
    fingerprint = _fingerprint(data, cfg)
    start, good, growth = 0, None, Growth(cfg)  # good: the epoch of the checkpoint resumed from or last saved
    within = None  # where a stop inside an epoch left it: {"batches" done, the epoch's "generator", "totals"}
    if state := resume(checkpoint, fingerprint, log=log, map_location=device):
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])  # its learning rate is StepLR's, reached at `epoch`
        if ema is not None:
            ema.model.load_state_dict(state["ema"])
        start = good = int(state["epoch"])
        within = state.get("within_epoch")
        growth = Growth(cfg, state["growth"], state.get("best"))
        log(f"resuming from {checkpoint} at {resumed_at(start, cfg.epochs, within)}")

    def save(epoch: int, inside: dict | None = None) -> dict:
        state = {"fingerprint": fingerprint, "epoch": epoch, "model": model.state_dict(),
                 "optimizer": opt.state_dict(),
                 "ema": ema.model.state_dict() if ema is not None else None, "standardizer": std.state(),
                 "layout": data.layout.to_config(), "siren": data.siren.to_config(), "config": asdict(cfg),
                 "extent": data.extent.tolist(), "train_lights": data.lights.tolist(),
                 "pool_lights": pool.lights.tolist() if pool is not None else [], "growth": growth.state,
                 "region": data.region, "extinction": data.extinction,
                 "best": None if growth.finished else growth.best}
        if inside is not None:
            state["within_epoch"] = inside
        atomic_torch_save(checkpoint, state)
        return state

    def last_good() -> str:
        return (f"the last good checkpoint {checkpoint} (epoch {good})" if good is not None
                else "no checkpoint (none was written yet)")

    def raise_if_not_finite() -> None:
        if (found := nonfinite.first()) is not None:
            raise DiffusionError(f"train_diffusion: loss became {float(found[2])} at epoch {found[0]}; keeping "
                                 f"{last_good()}; lower diffusion.lr (now {cfg.lr}) or check the weight store")

    n, t0, epoch, state = len(z_all), time.perf_counter(), start, None
    per_epoch = math.ceil(n / cfg.batch_size)  # optimizer steps, for the EMA's warm-up
    nonfinite = FirstNonFinite((), device)  # read at log lines, checks and checkpoints, not every step
    with stop_signals() as stop:
        while not growth.finished:
            gen = seeded(cfg.seed, Stream.DIFFUSION_EPOCH, epoch)
            order = torch.randperm(n, generator=gen, device=gen.device)
            totals = torch.zeros(2, dtype=torch.float64, device=device)  # summed on the device: no sync per step
            first = 0
            if within is not None:  # resumed inside this epoch: its draws go on from where the stop left them
                gen.set_state(within["generator"])
                first, totals, within = within["batches"], within["totals"].to(device), None
            for k in range(first, per_epoch):
                b0 = k * cfg.batch_size
                batch = draw_batch(gen, to_device(order[b0:b0 + cfg.batch_size], device), on_device, pool, cfg,
                                   schedule.steps, device)
                totals += train_batch(model, opt, ema, std, on_device, z_all, pool, batch, cfg, schedule,
                                      nonfinite, epoch, epoch * per_epoch + k, graphs)
                if stop.requested and k + 1 < per_epoch:  # an epoch at the paper's sizes outlasts a kill delay
                    raise_if_not_finite()
                    save(epoch, {"batches": k + 1, "generator": gen.get_state(), "totals": totals.cpu()})
                    raise stop.stopped(f"at step {k + 1} of epoch {epoch + 1}", checkpoint)
            done = epoch = epoch + 1
            if done <= cfg.epochs:  # growth past `epochs` keeps the lr reached there (decayed on, tooth plateaued)
                step_lr(opt, done, cfg.lr_step_epochs, cfg.lr_gamma)
            stopping = stop_after_epoch is not None and done >= stop_after_epoch
            logging = done % max(1, cfg.epochs // 20) == 0 or growth.due(done)
            saving = done % cfg.checkpoint_every == 0 or stop.requested
            if logging or saving or stopping:
                raise_if_not_finite()
            if logging:
                _log_epoch(log, done, (totals / n).cpu().tolist(), cfg, growth, float(opt.param_groups[0]["lr"]),
                           t0, start)
            if growth.due(done):
                growth.check(done, sampled, lambda: seen_gap_db(sampled, std, on_device, cfg), log, last_good())
            if stop.requested and not saving:  # it came during the log line or the check: this epoch is saved too
                raise_if_not_finite()
                saving = True
            if saving or growth.finished:
                state, good = save(done), done
            if stop.requested and not growth.finished:
                raise stop.stopped(f"at epoch {done}", checkpoint)
            if stopping:
                return state
    if state is None:  # resumed from the final checkpoint: nothing left to train
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    return state


def _log_epoch(log: Callable[[str], None], done: int, losses: list[float], cfg: DiffusionConfig, growth: Growth,
               lr: float, t0: float, start: int) -> None:
    lx, lg = losses
    # past `epochs` the stage grows towards max_epochs, which is then an upper bound, not a forecast
    total = cfg.epochs if done <= cfg.epochs else growth.max_epochs
    log(f"epoch {done}/{total}  loss x0 {lx:.4e}  geometry {lg:.4e} (≈{-10 * math.log10(max(lg, 1e-30)):.1f} dB)  "
        f"lr {lr:.2e}  {eta(done, total, t0, start=start)}")

"""Rendering-loss fine-tuning of the diffusion model (paper §3.3 "Rendering loss"), data-parallel.

Target images: the renderer's `gt` mode for every training light from V views. The colour of a pixel is

    C = Σ_k w_k c_k (0.1 + 0.9 g_k) + T·background,     w_k = T_k α_k,

where only g (the shadow) depends on the light: the sample points, w_k c_k and T of each view are the
same for every light. `RayBundle` stores them once per view (foreground pixels, samples with w > 0), so
a rendering-loss step is one batched evaluation of the predicted shadow SIRENs at the samples of P random
pixels per view, and a weighted sum: exact with respect to the renderer, differentiable, no marching.

Data parallelism: every random draw of a step (timestep, noise, geometry points, pixels) comes from a
generator seeded by (seed, epoch, light index), never by rank, and each rank's loss is scaled so that
DDP's gradient average equals the single-process gradient of the same global batch.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from diffshadow.adam import Adam
from diffshadow.config import changed_settings, section
from diffshadow.diffusion.config import DiffusionConfig, build_model, make_optimizer
from diffshadow.diffusion.model import WeightTransformer
from diffshadow.diffusion.sample import generate, load_sampler, sampler_weights
from diffshadow.diffusion.schedule import Schedule
from diffshadow.diffusion.standardize import Standardizer
from diffshadow.diffusion.train import Batch, TrainingData, batch_loss
from diffshadow.graphs import StepGraphs, requested
from diffshadow.io import atomic_torch_save, resume
from diffshadow.progress import FirstNonFinite, eta, resumed_at
from diffshadow.render.bundle import RayBundle, bundle_colors
from diffshadow.sampling import Stream, seeded, to_device
from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout, box_to_siren
from diffshadow.stopping import StopRequest, stop_signals
from diffshadow.truth import EvalTruth, psnr_per_light


@dataclass(frozen=True)
class FinetuneConfig:
    enabled: bool
    views: int  # authors 7 (Fibonacci views, fov 60°)
    image_size: int  # paper 128
    fov: float
    pixels: int  # random foreground pixels per view per light per step (paper 24 of 128²)
    render_weight: float
    epochs: int  # paper 2000
    lr: float  # paper 2e-4: too high after our geometry stage (README)
    batch_size: int  # global, over all ranks
    nproc: int  # DDP processes (local: CPU + gloo; Polaris: 4 GPUs + NCCL)
    checkpoint_every: int
    step: float  # renderer step (voxels)
    timeout_s: int  # collective timeout: a dead rank ends the job instead of hanging it
    seed: int
    # random lights in the training cap (lights.validation_lights), scored at every checkpoint: the model
    # kept is the last one whose median voxel PSNR there is not below the geometry stage's (0: no check)
    val_lights: int = 64  # medians over 16 lights drew 0.5-1.2 dB apart between draws (eebef00)
    val_points: int = 4096
    # validated checkpoints in a row under the geometry stage's before fine-tuning stops (0: never stops early)
    patience: int = 2
    # shadow grid of the target images: "sweep" (on the volume refined fit.grid_upsample times: the grid stage 1
    # fits to) or "march" (the renderer's gt). Foreground pixels agree to 50-53 dB (nucleon, tooth); the
    # sweep is 3-5x faster (docs/performance.md)
    targets: str = "sweep"
    # each step (one process) a replayed CUDA graph where the device is CUDA: "auto" / True; False steps eagerly,
    # the default until a GPU has timed it (docs/performance.md)
    cuda_graph: bool | str = False

    @classmethod
    def from_config(cls, d: dict | None = None) -> FinetuneConfig:
        """defaults.yaml's `finetune` section overridden by `d`."""
        return section(cls, "finetune", d)


# -------------------------------------------------------------------------------------------- training

# The model's only buffers are index tables derived from the SIREN layout, the same on every rank: DDP need not
# sync them before each forward. PyTorch 2.13 renamed the switch (the old name warns in every fine-tuning log);
# 2.3-2.12 know only the old one.
NO_BUFFER_SYNC = ({"forward_sync_buffers": False}
                  if "forward_sync_buffers" in inspect.signature(torch.nn.parallel.DistributedDataParallel).parameters
                  else {"broadcast_buffers": False})


@dataclass
class FinetuneData:
    train: TrainingData
    bundle: RayBundle
    targets: torch.Tensor  # (L, V, F, 3): the target images' `render.bundle.foreground`, in its row order
    val: EvalTruth | None = None  # exact shadows at validation lights (random in the training cap)

    def to(self, device: torch.device | str) -> FinetuneData:
        # the validation set stays on the CPU: it is scored there, between epochs
        return FinetuneData(self.train.to(device), self.bundle.to(device), self.targets.to(device), self.val)


@torch.no_grad()
def validation_psnr(model: torch.nn.Module, std: Standardizer, val: EvalTruth, layout: WeightLayout,
                    dcfg: DiffusionConfig, siren_cfg: SirenConfig, device: torch.device) -> float:
    """Median voxel PSNR (box points) of DDIM-generated SIRENs at the validation lights."""
    was_training = model.training
    model.eval()
    try:
        weights = generate(model, std, val.lights, method="ddim", steps=dcfg.ddim_steps, seed=dcfg.seed,
                           temperature=dcfg.temperature, device=device).numpy()
    finally:
        model.train(was_training)
    pred = val.sirens(weights, layout, siren_cfg)
    return float(np.median(psnr_per_light(pred, val.of(val.lights))["box"]))


def _draws(cfg: FinetuneConfig, dcfg: DiffusionConfig, epoch: int, light: int, n_params: int, n_points: int,
           n_views: int, steps: int, pool: tuple[int, int] = (0, 0)):
    """Every random draw for one light in one epoch: rank-independent by construction. With `pool` (pool
    lights, points per pool light), also one pool light and its timestep, noise and points."""
    gen = seeded(cfg.seed, Stream.FINETUNE_LIGHT, epoch, light)
    cpu = gen.device  # the same numbers on every device: drawn here, moved by the caller
    t = torch.randint(0, steps, (1,), generator=gen, device=cpu)
    noise = torch.randn(1, n_params, generator=gen, device=cpu)
    pick = torch.randint(0, n_points, (dcfg.geometry_points,), generator=gen, device=cpu)
    u = torch.rand(n_views, cfg.pixels, generator=gen, device=cpu)  # scaled to each view's pixel count later
    if not pool[0]:
        return t, noise, pick, u, None
    j = torch.randint(0, pool[0], (1,), generator=gen, device=cpu)
    tp = torch.randint(0, steps, (1,), generator=gen, device=cpu)
    noise_p = torch.randn(1, n_params, generator=gen, device=cpu)
    pick_p = torch.randint(0, pool[1], (dcfg.geometry_points,), generator=gen, device=cpu)
    return t, noise, pick, u, (j, tp, noise_p, pick_p)


def _pool(tr: TrainingData, dcfg: DiffusionConfig):
    """The pool lights a step draws and scores, if the geometry stage had them. Pool lights (no fitted SIREN, exact
    shadows) keep their geometry loss here too: the rendering loss sees training lights only and, alone, lowered
    the lights between them (nucleon: 32.46 -> 31.87 dB)."""
    return tr.pool if dcfg.pool_lights > 0 and tr.pool is not None else None


@dataclass
class FinetuneBatch(Batch):
    """One step's draws for this rank's lights (`draw_step`): the geometry stage's (`train.Batch`) and `u`, the
    pixels' positions in [0, 1) per view, scaled to each view's foreground count inside the step. On the device:
    a CUDA graph's inputs (`finetune.cuda_graph`)."""

    u: torch.Tensor | None = None  # (B, V, P)


def draw_step(data: FinetuneData, local: list[int], epoch: int, cfg: FinetuneConfig, dcfg: DiffusionConfig,
              steps: int, device: torch.device) -> FinetuneBatch:
    """Every random draw of the `local` lights' step, made on the host (rank-independent: `_draws`) and copied
    to `device` without blocking."""
    tr = data.train
    pool = _pool(tr, dcfg)
    sizes = (len(pool.lights), pool.points.shape[1]) if pool is not None else (0, 0)
    draws = [_draws(cfg, dcfg, epoch, i, tr.weights.shape[1], tr.points.shape[1], len(data.bundle.count), steps,
                    sizes) for i in local]

    def stacked(i: int, cat=torch.cat) -> torch.Tensor:
        return to_device(cat([d[i] for d in draws]), device)

    def pooled(i: int, cat=torch.cat) -> torch.Tensor:
        return to_device(cat([d[4][i] for d in draws]), device)

    batch = FinetuneBatch(to_device(torch.tensor(local, device="cpu"), device), stacked(0), stacked(1),
                          stacked(2, torch.stack), u=stacked(3, torch.stack))
    if pool is not None:
        batch.j, batch.tp, batch.noise_p, batch.pick_p = pooled(0), pooled(1), pooled(2), pooled(3, torch.stack)
    return batch


def step_loss(model: torch.nn.Module, std: Standardizer, data: FinetuneData, z_all: torch.Tensor,
              batch: FinetuneBatch, cfg: FinetuneConfig, dcfg: DiffusionConfig, schedule: Schedule,
              scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The geometry stage's loss of the batch's lights (`train.batch_loss`: x0, pool prior, geometry) plus the
    rendering loss, summed over the lights and times `scale`; and the parts (x0, geometry, rendering) summed.
    `data` is on the device; nothing is read back or copied from the host (a CUDA graph replays it)."""
    device = z_all.device
    tr = data.train
    b = data.bundle
    nv, p, n_light = len(b.count), cfg.pixels, len(batch.idx)
    loss, l_x0, l_geo, pred_all = batch_loss(model, std, tr, z_all, _pool(tr, dcfg), batch, dcfg, schedule)
    siren = BatchedSiren(std.destandardize(pred_all[:n_light]), tr.layout, tr.siren.blocks)
    count = b.count[None, :, None]
    pix = (batch.u * count.float()).long().clamp(max=(count - 1).clamp_min(0))  # (B, V, P) rows of the bundle
    views = torch.arange(nv, device=device)[None, :, None].expand_as(pix)
    spts = b.pts[views, pix]  # (B, V, P, N, 3)
    n = spts.shape[-2]
    g = siren(box_to_siren(spts.reshape(n_light, -1, 3), tr.extent)).view(n_light, nv, p, n)
    color = bundle_colors(b, g, views, pix)
    target = data.targets[batch.idx[:, None, None], views, pix]
    l_render = ((color - target) ** 2).mean((1, 2, 3))
    # batch_loss is a mean over the lights: times their count, the per-light sum DDP's scale expects
    total = (loss + cfg.render_weight * l_render.mean()) * (n_light * scale)
    parts = torch.stack([l_x0.detach() * n_light, l_geo.detach() * n_light, l_render.detach().sum()]).double()
    return total, parts


def fingerprint(state: dict, cfg: FinetuneConfig, data: FinetuneData) -> str:
    h = hashlib.sha256(str(state.get("fingerprint")).encode())
    h.update(json.dumps(changed_settings("finetune", asdict(cfg)), sort_keys=True).encode())
    # the first MiB of the targets' bytes, without copying all of them first
    h.update(np.ascontiguousarray(data.targets.numpy()).reshape(-1).view(np.uint8)[:1 << 20])
    h.update(str(tuple(data.targets.shape)).encode())
    return h.hexdigest()


class Selection:
    """Which fine-tuned model is kept, and when fine-tuning gives up (rank 0 scores; the verdict is shared).

    Every checkpoint is scored by the median voxel PSNR of DDIM-generated SIRENs at the validation lights; the
    geometry stage's sampler, scored first, is the floor. The model kept is the last one not below the floor,
    and `patience` checkpoints in a row under it end fine-tuning. Without validation lights the last model is
    kept and nothing stops early. `record` ({history: [[epoch, PSNR]], kept_epoch, stopped_epoch}) is saved
    with each checkpoint and in the final one."""

    def __init__(self, val: EvalTruth | None, sampler: dict, patience: int, log: Callable[[str], None]):
        self.val, self.patience, self.log = val, patience, log
        self.record: dict = {"history": [], "kept_epoch": 0}
        self.kept = {k: v.detach().cpu().clone() for k, v in sampler.items()}

    def resume(self, state: dict) -> None:
        self.record = state.get("selection") or self.record
        self.kept = state.get("kept_model") or self.kept

    def score(self, epoch: int, model: torch.nn.Module | None,
              psnr_of: Callable[[torch.nn.Module | None], float]) -> None:
        """`psnr_of(model)`: the validation PSNR; epoch 0 is the floor."""
        if self.val is None:
            return
        value = psnr_of(model)
        self.record["history"].append([epoch, value])
        floor = self.record["history"][0][1]
        if value >= floor and epoch > 0:
            self.record["kept_epoch"] = epoch
            self.kept = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
        self.log(f"validation: epoch {epoch}, median voxel PSNR {value:.2f} dB at {len(self.val.lights)} validation "
                 f"lights (geometry stage {floor:.2f} dB); keeping epoch {self.record['kept_epoch']}")

    def give_up(self) -> bool:
        """The last `patience` checkpoints all scored under the floor (rank 0's own verdict)."""
        scores = [v for _, v in self.record["history"]]
        return (self.val is not None and self.patience > 0 and len(scores) > self.patience
                and max(scores[-self.patience:]) < scores[0])

    def agreed_give_up(self, world: int, device: torch.device) -> bool:
        """`give_up`, rank 0's verdict broadcast to every rank (only rank 0 validates)."""
        verdict = self.give_up()
        if world > 1:
            import torch.distributed as dist

            flag = torch.tensor([int(verdict)], device=device)
            dist.broadcast(flag, 0)
            verdict = bool(flag.item())
        return verdict

    @property
    def stopped(self) -> bool:
        return bool(self.record.get("stopped_epoch"))


class Halt:
    """Where a stop signal ends fine-tuning: after a step, the same step on every rank. A process alone stops after
    the step it was signalled in. The ranks of a DDP job each see the signal at their own moment and must stop at
    one step (a rank's next all-reduce would wait for a peer that left): after each step a rank posts its flag to a
    sum over the ranks on the host (its own gloo group: no wait on the GPU) and reads the sum it posted a step
    before, so all read the same sums at the same steps and stop one step after the first of them was
    signalled."""

    def __init__(self, signalled: StopRequest, world: int):
        self.signalled, self.world, self.posted = signalled, world, None
        if world > 1:
            import torch.distributed as dist

            self.group = dist.new_group(backend="gloo")

    def now(self) -> bool:
        """Whether to stop after the step just taken (called once a step on every rank)."""
        if self.world == 1:
            return self.signalled.requested
        import torch.distributed as dist

        if self.posted is not None:
            work, total = self.posted
            work.wait()
            self.posted = None
            if int(total[0]) > 0:
                return True
        flag = torch.tensor([int(self.signalled.requested)], dtype=torch.int32)
        self.posted = dist.all_reduce(flag, group=self.group, async_op=True), flag
        return False

    def close(self) -> None:
        """The last sum waited for: every rank's, before the process group ends."""
        if self.posted is not None:
            self.posted[0].wait()
            self.posted = None


class FinetuneCheckpoint:
    """Fine-tuning's progress as one resumable checkpoint, written by rank 0 (every rank waits for it): before
    the end the running model and the one `Selection` keeps; at the end, with validation, the kept one as the
    model (what sample_shadows samples from)."""

    def __init__(self, path: Path, geometry_state: dict, cfg: FinetuneConfig, fp: str, selection: Selection,
                 validated: bool, rank: int, world: int):
        self.path, self.geometry_state, self.cfg, self.fp = path, geometry_state, cfg, fp
        self.selection, self.validated, self.rank, self.world = selection, validated, rank, world

    def save(self, epoch: int, model: WeightTransformer, opt: Adam, *, last: bool, inside: dict | None = None) -> dict:
        """The state after `epoch` epochs, and `inside` the next where a stop came in it ({"batches" done,
        their loss "totals"})."""
        final = self.validated and last
        kept = self.selection.kept
        state = {**self.geometry_state, "model": kept if final else model.state_dict(), "ema": None,
                 "optimizer": opt.state_dict(), "finetune_fingerprint": self.fp, "finetune_epoch": epoch,
                 "finetune": asdict(self.cfg), "selection": self.selection.record,
                 "kept_model": kept if self.validated and not final else None}
        if inside is not None:
            state["within_epoch"] = inside
        if self.rank == 0:
            atomic_torch_save(self.path, state)
        if self.world > 1:
            import torch.distributed as dist

            dist.barrier()
        return state


def train_step(model: torch.nn.Module, base: WeightTransformer, opt: Adam, std: Standardizer, data: FinetuneData,
               z_all: torch.Tensor, batch: list[int], rank: int, world: int, epoch: int, cfg: FinetuneConfig,
               dcfg: DiffusionConfig, schedule: Schedule, nonfinite: FirstNonFinite,
               graphs: StepGraphs | None = None) -> torch.Tensor:
    """One optimiser step on this rank's share of the global `batch` (one CPU process of `finetune.nproc` 2: both
    ranks' shares in turn, `_two_ranks_in_turn`); returns the loss parts (summed). The loss's
    finiteness is recorded in `nonfinite` on the device, read once an epoch: the step reads nothing back to the
    host (tests/test_syncs.py). With `graphs` (`finetune.cuda_graph`, one process) the update — loss, backward,
    gradient clip, AdamW — is a CUDA graph's replay, its draws the graph's inputs."""
    if world == 1 and cfg.nproc == 2 and z_all.device.type == "cpu" and graphs is None:
        return _two_ranks_in_turn(base, opt, std, data, z_all, batch, epoch, cfg, dcfg, schedule, nonfinite)
    has_lights, drawn, scale = _share(data, batch, rank, world, epoch, cfg, dcfg, schedule, z_all.device)

    def update(b: FinetuneBatch) -> tuple[torch.Tensor, torch.Tensor]:
        loss, parts = step_loss(model, std, data, z_all, b, cfg, dcfg, schedule, scale)
        opt.zero_grad(set_to_none=graphs is None)  # a graph's replays write the gradients where they are
        loss.backward()
        _clip_and_step(base, opt, dcfg)
        return loss.detach(), parts

    loss, parts = update(drawn) if graphs is None else graphs(update, drawn)
    nonfinite.record(loss, epoch)
    return parts if has_lights else torch.zeros_like(parts)


def _share(data: FinetuneData, batch: list[int], rank: int, world: int, epoch: int, cfg: FinetuneConfig,
           dcfg: DiffusionConfig, schedule: Schedule, device: torch.device) -> tuple[bool, FinetuneBatch, float]:
    """Rank `rank`'s share of the global `batch` among `world`: whether it has lights, its draws and its loss scale.
    A rank with no light in this batch (a last batch shorter than the ranks) still runs the model forward and
    backward, where DDP all-reduces the gradients: on the batch's first light, weighed by zero. One process always
    has lights, so its scale follows from the batch's shape, for which a graph is captured."""
    local = batch[rank::world]
    drawn = draw_step(data, local or batch[:1], epoch, cfg, dcfg, schedule.steps, device)
    return bool(local), drawn, world / len(batch) if local else 0.0


def _clip_and_step(base: WeightTransformer, opt: Adam, dcfg: DiffusionConfig) -> None:
    torch.nn.utils.clip_grad_norm_(base.parameters(), dcfg.grad_clip)
    opt.step()


def _two_ranks_in_turn(base: WeightTransformer, opt: Adam, std: Standardizer, data: FinetuneData,
                       z_all: torch.Tensor, batch: list[int], epoch: int, cfg: FinetuneConfig, dcfg: DiffusionConfig,
                       schedule: Schedule, nonfinite: FirstNonFinite) -> torch.Tensor:
    """`train_step` of the two DDP ranks `finetune.nproc` asks for, taken in turn by one process on a CPU (where
    `-j1` leaves one core): each rank's share of the batch, its loss and backward as the rank's, the gradients
    added (as gloo adds two ranks' gradients, in either order) and halved (DDP's average; a power of two, so
    exact). Two processes and one write the same bytes (tests/test_finetune.py), where one backward over the whole
    batch summed the lights in another order."""
    opt.zero_grad(set_to_none=True)
    parts = torch.zeros(3, dtype=torch.float64, device=z_all.device)
    for rank in range(2):
        has_lights, drawn, scale = _share(data, batch, rank, 2, epoch, cfg, dcfg, schedule, z_all.device)
        loss, own = step_loss(base, std, data, z_all, drawn, cfg, dcfg, schedule, scale)
        loss.backward()
        nonfinite.record(loss.detach(), epoch)
        if has_lights:
            parts += own
    torch._foreach_div_([p.grad for p in base.parameters() if p.grad is not None], 2.0)
    _clip_and_step(base, opt, dcfg)
    return parts


def step_graphs(cfg: FinetuneConfig, world: int, device: torch.device,
                log: Callable[[str], None] = print) -> StepGraphs | None:
    """Fine-tuning's CUDA graphs where `finetune.cuda_graph` asks for them ("auto" or True), the device is CUDA
    and one process trains: DDP all-reduces the gradients from hooks inside the backward, which these graphs do
    not capture."""
    return requested(cfg.cuda_graph, "finetune.cuda_graph", device, log,
                     unsupported=f"DDP over {world} processes is not captured" if world > 1 else "")


def finetune(geometry_state: dict, data: FinetuneData, cfg: FinetuneConfig, checkpoint: Path, *,
             rank: int = 0, world: int = 1, device: torch.device | str = "cpu",
             log: Callable[[str], None] = print, stop_after_epoch: int | None = None) -> dict:
    """Fine-tune from the geometry-stage checkpoint state; resumable; only rank 0 writes. `Selection` decides
    which model is kept and when to stop, `FinetuneCheckpoint` what is written; this loop runs the steps."""
    import torch.distributed as dist

    device = torch.device(device)
    dcfg = DiffusionConfig.of_checkpoint(geometry_state)
    layout = WeightLayout.from_config(geometry_state["layout"])
    siren_cfg = SirenConfig.from_config(geometry_state["siren"])
    torch.manual_seed(cfg.seed)
    base = build_model(layout, dcfg)
    # Fine-tuning steps from the raw weights. With diffusion.ema the geometry stage's sampler is their average,
    # and steps taken from the average lost validation PSNR at once (nucleon 33.38 -> 33.12 dB at epoch 20,
    # against 33.57 -> 33.88 from the raw weights): the average is the floor to beat and the model kept until
    # fine-tuning beats it.
    sampler = sampler_weights(geometry_state)
    base.load_state_dict(geometry_state["model"])
    base.to(device)
    std = Standardizer(layout, geometry_state["standardizer"]["mean"], geometry_state["standardizer"]["std"])
    graphs = step_graphs(cfg, world, device, log if rank == 0 else lambda message: None)
    # what was done, not what was asked: the checkpoint's config and fingerprint (eager steps train the same bytes
    # whatever the setting, so a CPU run resumes a checkpoint whichever it was asked)
    cfg = dataclasses.replace(cfg, cuda_graph=graphs is not None)
    opt = make_optimizer(base.parameters(), cfg.lr, dcfg.weight_decay, capturable=graphs is not None)
    fp = fingerprint(geometry_state, cfg, data)
    selection = Selection(data.val if rank == 0 else None, sampler, cfg.patience, log)
    start, within = 0, None  # within: where a stop inside an epoch left it ({"batches" done, "totals"})
    if state := resume(checkpoint, fp, log=lambda m: log(f"rank {rank}: {m}"), map_location=device,
                       key="finetune_fingerprint"):
        base.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start, within = int(state["finetune_epoch"]), state.get("within_epoch")
        selection.resume(state)
        log(f"rank {rank}: resuming from {checkpoint} at {resumed_at(start, cfg.epochs, within)}")

    def psnr_of(model) -> float:
        return validation_psnr(model, std, data.val, layout, dcfg, siren_cfg, device)

    def floor_model():  # the geometry stage's sampler
        model = build_model(layout, dcfg)
        model.load_state_dict(sampler)
        return model.to(device)

    writer = FinetuneCheckpoint(checkpoint, geometry_state, cfg, fp, selection, data.val is not None, rank, world)

    model = base
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(base, device_ids=[device.index] if device.type == "cuda" else None,
                                        **NO_BUFFER_SYNC)
    schedule = Schedule()
    z_all = std.standardize(data.train.weights).float().to(device)
    data = data.to(device)  # the training set on the device once, not per step
    n = len(z_all)
    if rank == 0:
        log(f"fine-tuning with the rendering loss: {world} process(es) on {device.type}, global batch "
            f"{cfg.batch_size} ({cfg.batch_size // world}+ per rank), lr {cfg.lr:g}, {cfg.pixels} pixels x "
            f"{len(data.bundle.count)} views per light, {cfg.epochs} epochs")
    if start == 0 and within is None:
        selection.score(0, floor_model() if selection.val is not None else None, psnr_of)
    state = None
    nonfinite = FirstNonFinite((), device)
    t_start = t_step = time.perf_counter()
    step_times: list[float] = []
    end = start if selection.stopped else cfg.epochs  # a run that stopped early has finished
    per_epoch = math.ceil(n / cfg.batch_size)

    def raise_if_not_finite() -> None:
        if (found := nonfinite.first()) is not None:
            raise ValueError(f"finetune: loss became {float(found[2])} at epoch {found[0]} on rank {rank}; "
                             f"lower finetune.lr (now {cfg.lr})")

    with stop_signals() as signalled:
        halt = Halt(signalled, world)
        for epoch in range(start, end):
            gen = seeded(cfg.seed, Stream.FINETUNE_EPOCH, epoch)
            order = torch.randperm(n, generator=gen, device=gen.device).tolist()
            totals = torch.zeros(3, dtype=torch.float64, device=device)  # summed on the device: no sync per step
            first, halting = 0, False
            if within is not None:  # resumed inside this epoch (its steps' draws depend on the epoch and light)
                first, totals, within = within["batches"], within["totals"].to(device), None
            for k in range(first, per_epoch):
                b0 = k * cfg.batch_size
                totals += train_step(model, base, opt, std, data, z_all, order[b0:b0 + cfg.batch_size], rank, world,
                                     epoch, cfg, dcfg, schedule, nonfinite, graphs)
                step_times.append(time.perf_counter() - t_step)
                t_step = time.perf_counter()
                halting = halt.now()
                if halting and k + 1 < per_epoch:  # an epoch at the paper's sizes outlasts a kill delay
                    raise_if_not_finite()
                    writer.save(epoch, base, opt, last=False, inside={"batches": k + 1, "totals": totals.cpu()})
                    raise signalled.stopped(f"at step {k + 1} of epoch {epoch + 1}/{cfg.epochs}", checkpoint)
            raise_if_not_finite()
            if world > 1:
                dist.all_reduce(totals)
            done = epoch + 1
            if done % cfg.checkpoint_every == 0 or done == cfg.epochs:
                selection.score(done, base, psnr_of)
                stop = done < cfg.epochs and selection.agreed_give_up(world, device)
                if stop:
                    if rank == 0:
                        log(f"validation: the last {cfg.patience} checkpoints scored under the geometry stage; "
                            f"stopping at epoch {done}/{cfg.epochs} and keeping epoch "
                            f"{selection.record['kept_epoch']}")
                    selection.record["stopped_epoch"] = done
                state = writer.save(done, base, opt, last=stop or done == cfg.epochs)
                if stop:
                    break
            elif halting:
                state = writer.save(done, base, opt, last=False)
            if halting and done < cfg.epochs:
                raise signalled.stopped(f"at epoch {done}/{cfg.epochs}", checkpoint)
            if rank == 0 and (done % max(1, cfg.epochs // 10) == 0 or done == cfg.epochs):
                lx, lg, lr_ = (totals.cpu() / n).tolist()
                log(f"epoch {done}/{cfg.epochs}  x0 {lx:.3e}  geometry {lg:.3e}  render {lr_:.3e} "
                    f"(≈{-10 * math.log10(max(lr_, 1e-30)):.1f} dB)  {eta(done, end, t_start, start=start)}")
            if stop_after_epoch is not None and done >= stop_after_epoch:
                halt.close()
                return state
        halt.close()
    if state is None:
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    # per-rank cost, gathered to every rank: median seconds per step and peak memory
    mine = {"rank": rank, "median_step_s": float(np.median(step_times)) if step_times else None,
            "peak_mem_bytes": _peak_memory(device)}
    ranks = [mine]
    if world > 1:
        ranks = [None] * world
        dist.all_gather_object(ranks, mine)
    return {**state, "finetune_ranks": ranks}


def keep_if_images_improve(geometry_state: dict, state: dict, before: np.ndarray,
                           after: np.ndarray) -> tuple[dict, str]:
    """The state to write (`state` itself unless it gives way) and which model it holds, "fine-tuned" or
    "geometry stage" (also when validation kept none of the fine-tuning checkpoints): fine-tuning is for the
    images, so a model that renders the training lights worse on average (`after` against `before`, image
    PSNR per light and view) gives way to the geometry stage's sampler. Validation alone had kept one that a
    0.1 dB voxel gain on validation lights carried over a 1.3 dB image loss (nucleon, docs/performance.md)."""
    if float(np.mean(after)) >= float(np.mean(before)):
        selection = state.get("selection") or {}
        validated_none = bool(selection.get("history")) and selection.get("kept_epoch") == 0
        return state, "geometry stage" if validated_none else "fine-tuned"
    sampler = sampler_weights(geometry_state)
    validated = state.get("selection") or {}
    selection = {**validated, "kept_epoch": 0, "images_worse": True,
                 "validated_epoch": validated.get("kept_epoch", 0)}
    return {**state, "model": sampler, "ema": None, "kept_model": None, "selection": selection}, "geometry stage"


def _peak_memory(device: torch.device) -> int:
    """CUDA: the allocator's peak; CPU: the process's peak resident set (torch itself included)."""
    if device.type == "cuda":
        return int(torch.cuda.max_memory_allocated(device))
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def same_sampler(a: dict, b: dict) -> bool:
    """Whether two checkpoints sample alike: the same weights bit for bit, standardizer, layout, SIREN and diffusion
    config. Fine-tuning whose validation kept none of its epochs holds the geometry stage's sampler, and scoring it
    again renders every training light a second time for the same numbers (0.5 s of the README run's 14)."""
    wa, wb = sampler_weights(a), sampler_weights(b)
    if wa.keys() != wb.keys() or any(not torch.equal(wa[k], wb[k]) for k in wa):
        return False
    std_a, std_b = a["standardizer"], b["standardizer"]
    return (all(torch.equal(torch.as_tensor(std_a[k]), torch.as_tensor(std_b[k])) for k in ("mean", "std"))
            and all(a[k] == b[k] for k in ("layout", "siren"))
            and DiffusionConfig.of_checkpoint(a) == DiffusionConfig.of_checkpoint(b))


@torch.no_grad()
def image_psnr_of_model(state: dict, data: FinetuneData, *,
                        device: torch.device | str = "cpu", chunk: int = 512) -> np.ndarray:
    """Per training light: foreground image PSNR (all target views) of the DDIM-generated shadow SIREN."""
    model, std, layout, siren_cfg = load_sampler(state, device)
    dcfg = DiffusionConfig.of_checkpoint(state)
    lights = data.train.lights.numpy()
    weights = generate(model, std, lights, method="ddim", steps=dcfg.ddim_steps, seed=dcfg.seed,
                       temperature=dcfg.temperature, device=device)
    b = data.bundle
    extent = data.train.extent
    out = []
    for i in range(len(lights)):
        siren = BatchedSiren(weights[i:i + 1], layout, siren_cfg.blocks)
        se, count = 0.0, 0
        for v in range(len(b.count)):
            f = int(b.count[v])
            for j0 in range(0, f, chunk):
                rows = torch.arange(j0, min(f, j0 + chunk))
                pts = b.pts[v, rows]
                g = siren(box_to_siren(pts.reshape(1, -1, 3), extent)).view(len(rows), -1).clamp(0, 1)
                vv = torch.full_like(rows, v)
                color = bundle_colors(b, g, vv, rows)
                target = data.targets[i, v, rows]
                se += float(((color - target) ** 2).sum())
                count += color.numel()
        out.append(10 * math.log10(1.0 / max(se / max(count, 1), 1e-30)))
    return np.asarray(out)

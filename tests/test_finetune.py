"""Rendering-loss fine-tuning: the ray-bundle colour equals the renderer's, and a DDP step over 2 gloo
processes equals one single-process step on the same global batch."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp
from conftest import default_device_meta

from diffshadow.analytic import gaussian_blob
from diffshadow.diffusion.config import DiffusionConfig
from diffshadow.diffusion.finetune import (
    FinetuneConfig,
    FinetuneData,
    Schedule,
    Standardizer,
    build_model,
    draw_step,
    finetune,
    step_loss,
)
from diffshadow.diffusion.train import TrainingData, train_diffusion
from diffshadow.lights import PoolLights
from diffshadow.metrics import psnr
from diffshadow.render import GridShadow, fibonacci_views
from diffshadow.render.bundle import build_bundle, bundle_colors, foreground, render_targets
from diffshadow.shadow import shadow_grid
from diffshadow.siren import SirenConfig, WeightLayout, init_siren
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

TF = TransferFunction.from_config({"opacity": [[0, 0], [0.2, 0], [1, 0.8]],
                                   "color": [[0, 0.2, 0.4, 0.9], [1, 1, 0.3, 0.2]], "density_scale": 20})
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
FT = FinetuneConfig.from_config(dict(views=2, image_size=16, pixels=5, epochs=1, batch_size=4,
                                     checkpoint_every=1, lr=2e-4))


@pytest.fixture(scope="module")
def volume():
    return Volume(data=gaussian_blob(17, 0.3), extent=np.ones(3), name="blob")


@pytest.fixture(scope="module")
def setup(volume, tmp_path_factory):
    return make_setup(volume, tmp_path_factory.mktemp("geo"))


def make_setup(volume, workdir):
    """Cameras, ray bundle, target images, FinetuneData and a geometry-stage state for LIGHTS."""
    cams = fibonacci_views(volume.extent, FT.views, size=FT.image_size)
    bundle = build_bundle(volume, TF, cams, step=FT.step)
    images = render_targets(volume, TF, LIGHTS, cams, step=FT.step, log=lambda m: None)
    cfg = SirenConfig(8, 1)
    layout = WeightLayout.for_siren(cfg)
    gen = torch.Generator().manual_seed(0)
    weights = torch.stack([layout.flatten(init_siren(cfg, gen)) for _ in LIGHTS])
    # two pool lights (exact shadows, no fitted SIREN): every fine-tuning test runs their loss too
    pool = PoolLights(lights=torch.nn.functional.normalize(torch.as_tensor(LIGHTS[:2] + LIGHTS[1:3],
                                                                           dtype=torch.float32)),
                      points=torch.rand(2, 32, 3, generator=gen), values=torch.rand(2, 32, generator=gen),
                      neighbours=torch.tensor([[0, 1], [1, 2]]), blend=torch.full((2, 2), 0.5))
    train = TrainingData(weights=weights, lights=torch.as_tensor(LIGHTS, dtype=torch.float32),
                         points=torch.rand(4, 64, 3, generator=gen), values=torch.rand(4, 64, generator=gen),
                         extent=torch.ones(3), layout=layout, siren=cfg, pool=pool)
    # float32 products: the DDP test compares sums in two orders at float32's rounding, not bfloat16's
    dcfg = DiffusionConfig.from_config(dict(preset="tiny", epochs=1, batch_size=4, geometry_points=16,
                                              checkpoint_every=1, pool_lights=2, target_gap=0.0, precision="float32"))
    state = train_diffusion(train, dcfg, workdir / "geo.ckpt", log=lambda m: None)
    data = FinetuneData(train, bundle, foreground(images.reshape(4, FT.views, -1, 3), bundle))
    return cams, bundle, images, data, state


def test_bundle_colour_equals_the_renderer(volume, setup):
    cams, bundle, images, _, _ = setup
    assert (bundle.count > 10).all()
    for i, light in enumerate(LIGHTS):
        g_of = GridShadow(shadow_grid(volume, TF, light, method=FT.targets), volume.extent)
        for v in range(len(cams)):
            rows = torch.arange(int(bundle.count[v]))
            pts = bundle.pts[v, rows]
            g = g_of(pts.reshape(-1, 3)).view(len(rows), -1)
            color = bundle_colors(bundle, g, torch.full_like(rows, v), rows)
            target = images[i, v].reshape(-1, 3)[bundle.pix[v, rows]]
            assert float((color - target).abs().max()) <= 1e-4


def test_targets_are_read_back_at_each_views_foreground_pixels(volume, setup, tmp_path):
    """targets.zarr holds whole images; fine-tuning reads only the foreground pixels, so they are read back (a few
    lights at a time) as (L, V, F, 3) in the bundle's row order: each row is its pixel's colour in the image."""
    from diffshadow.artifacts import read_targets, write_targets

    cams, bundle, images, data, _ = setup
    write_targets(tmp_path / "targets.zarr", images, bundle, cams, LIGHTS, step=FT.step, extent=volume.extent)
    targets, read_bundle, lights = read_targets(tmp_path / "targets.zarr")
    flat = images.reshape(len(LIGHTS), FT.views, -1, 3)
    assert targets.shape == (len(LIGHTS), FT.views, bundle.pix.shape[1], 3) and np.array_equal(lights, LIGHTS)
    assert torch.equal(read_bundle.pix, bundle.pix) and torch.equal(targets, data.targets)
    for v in range(FT.views):
        f = int(bundle.count[v])
        assert torch.equal(targets[:, v, :f], flat[:, v, bundle.pix[v, :f]])
    assert bundle.pix.shape[1] < flat.shape[2] / 2  # the foreground is what is kept: under half the pixels here


def test_sweep_targets_match_march_targets(volume, setup):
    cams, _, images, _, _ = setup
    assert FT.targets == "sweep"
    march = render_targets(volume, TF, LIGHTS, cams, step=FT.step, method="march", log=lambda m: None)
    assert 50.0 < float(psnr(images, march)) < float("inf")  # the grids differ by O(h²) in line spacing
    fine = render_targets(volume, TF, LIGHTS, cams, step=FT.step, upsample=2, log=lambda m: None)
    assert float(psnr(fine, march)) > float(psnr(images, march))  # stage 1's grid: lines half as far apart
    with pytest.raises(ValueError, match="finetune.targets: expected 'sweep' or 'march', got 'exact'"):
        render_targets(volume, TF, LIGHTS, cams, step=FT.step, method="exact")


def test_target_images_resume_where_an_interrupted_job_stopped(volume, setup, tmp_path):
    """A job stopped after two of four lights (saving after every light) resumes at the third: the same bytes
    as the images rendered in one go, the checkpoint gone at the end; one of other lights is not resumed."""
    cams, _, images, _, _ = setup
    ckpt, said = tmp_path / "targets.zarr.ckpt", []

    class Preempted(Exception):
        pass

    def stop_after_two(message):
        said.append(message)
        if message.startswith("target images: 2/4"):
            raise Preempted

    with pytest.raises(Preempted):
        render_targets(volume, TF, LIGHTS, cams, step=FT.step, checkpoint=ckpt, checkpoint_s=0, log=stop_after_two)
    assert ckpt.exists()
    said.clear()
    resumed = render_targets(volume, TF, LIGHTS, cams, step=FT.step, checkpoint=ckpt, checkpoint_s=0,
                             log=said.append)
    assert said[0] == f"resuming from {ckpt} at light 2/4" and not any("1/4" in m for m in said)
    assert torch.equal(resumed, images) and not ckpt.exists()
    with pytest.raises(Preempted):
        render_targets(volume, TF, LIGHTS, cams, step=FT.step, checkpoint=ckpt, checkpoint_s=0, log=stop_after_two)
    said.clear()
    other = render_targets(volume, TF, LIGHTS[::-1].copy(), cams, step=FT.step, checkpoint=ckpt, checkpoint_s=0,
                           log=said.append)
    assert said[0] == f"ignoring {ckpt}: it belongs to other inputs or settings"
    assert torch.equal(other, images.flip(0))


def _ddp_worker(rank, world, port, data, state, out_dir, cfg=FT):
    # the production path (runtime.distributed, as under torchrun): it ends with a barrier before the
    # teardown; without one, gloo can abort a rank whose peer is still writing ("terminate called
    # without an active exception"). The process then ends as a rank of `diffshadow torchrun` does (cli.run:
    # os._exit once its outputs are written), not through Python's finalization with gloo's threads about,
    # which aborted a rank the same way in 1 CI run of ~25, after its model was saved
    import os
    import warnings

    from diffshadow.cli import _end
    from diffshadow.runtime import CPU, distributed

    # PyTorch's deprecations would reach every fine-tuning log (2.13 renamed DDP's buffer switch): here they fail
    warnings.simplefilter("error", FutureWarning)
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    with distributed(CPU, timeout_s=120) as d:
        result = finetune(state, data, cfg, Path(out_dir) / "ddp.ckpt", rank=d.rank, world=d.world,
                          log=lambda m: None)
        if d.rank == 0:
            torch.save(result["model"], Path(out_dir) / "ddp_model.pt")
    _end(0)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("batch_size", [4, 3])
def test_ddp_steps_equal_single_process_steps(setup, tmp_path, batch_size):
    """Two processes take the steps one process takes. With 3 lights a batch, an epoch's second batch holds one
    light: the second rank has none, and still takes part in the gradient's all-reduce (it once waited in a
    collective the other rank never reached, and gloo aborted the job)."""
    _, _, _, data, state = setup
    cfg = replace(FT, batch_size=batch_size)
    torch.set_num_threads(1)
    single = finetune(state, data, cfg, tmp_path / "single.ckpt", log=lambda m: None)["model"]
    mp.spawn(_ddp_worker, args=(2, _free_port(), data, state, str(tmp_path), cfg), nprocs=2, join=True)
    ddp = torch.load(tmp_path / "ddp_model.pt", weights_only=True)
    start = state["model"]
    moved = max(float((single[k] - start[k]).abs().max()) for k in single)
    assert moved > 1e-4  # the step did something
    # one process takes the two ranks' steps in turn and adds their gradients as gloo does: the same bytes
    assert all(torch.equal(single[k], ddp[k]) for k in single)


def test_resume_skips_finished_epochs(setup, tmp_path):
    _, _, _, data, state = setup
    cfg = FinetuneConfig(**{**FT.__dict__, "epochs": 2})
    ckpt = tmp_path / "ft.ckpt"
    finetune(state, data, cfg, ckpt, log=lambda m: None, stop_after_epoch=1)
    messages = []
    resumed = finetune(state, data, cfg, ckpt, log=messages.append)["model"]
    whole = finetune(state, data, cfg, tmp_path / "whole.ckpt", log=lambda m: None)["model"]
    assert any("resuming" in m and "epoch 1/2" in m for m in messages)
    assert all(torch.equal(resumed[k], whole[k]) for k in whole)


def test_cuda_graph_off_cuda_steps_eagerly_to_the_same_bytes_and_the_same_fingerprint(setup, tmp_path):
    """`finetune.cuda_graph` on a CPU: False (the default) and "auto" step eagerly without a word; True says that
    the steps run eagerly, and all three train the same bytes. The checkpoint records what was done (no graph),
    and its fingerprint leaves that out: it is the one computed before the key existed, so a checkpoint resumes
    across the setting and the upgrade."""
    import hashlib
    import json
    from dataclasses import asdict

    _, _, _, data, state = setup
    assert FT.cuda_graph is False
    quiet, told = [], []
    plain = finetune(state, data, FT, tmp_path / "a.ckpt", log=quiet.append)
    auto = finetune(state, data, replace(FT, cuda_graph="auto"), tmp_path / "b.ckpt", log=quiet.append)
    assert not any("cuda_graph" in m for m in quiet), quiet
    graphed = finetune(state, data, replace(FT, cuda_graph=True), tmp_path / "c.ckpt", log=told.append)
    assert "finetune.cuda_graph: CUDA graphs need a CUDA device; stepping eagerly on cpu" in told
    for other in (auto, graphed):
        assert all(torch.equal(plain["model"][k], other["model"][k]) for k in plain["model"])
        assert other["finetune"]["cuda_graph"] is False
        assert other["finetune_fingerprint"] == plain["finetune_fingerprint"]
    before = hashlib.sha256(str(state.get("fingerprint")).encode())
    before.update(json.dumps({k: v for k, v in asdict(FT).items() if k != "cuda_graph"}, sort_keys=True).encode())
    before.update(np.ascontiguousarray(data.targets.numpy()).reshape(-1).view(np.uint8)[:1 << 20])
    before.update(str(tuple(data.targets.shape)).encode())
    assert plain["finetune_fingerprint"] == before.hexdigest()


class ReplayedOnTheCpu:
    """A CUDA graph's contract without CUDA (`graphs.StepGraphs`): after the warm-up calls, each input shape's step
    is "captured" once (that call's closure kept, with copies of its inputs), and every later call of the shape
    copies its inputs into those copies, runs the kept closure and writes its results into the captured ones."""

    def __init__(self, warmup: int = 3):
        self.warmup, self.calls, self.graphs = warmup, 0, {}

    def __call__(self, step, inputs):
        from diffshadow.graphs import shapes, tensor_fields

        self.calls += 1
        if self.calls <= self.warmup:
            return step(inputs)
        fields = tensor_fields(inputs)
        key = shapes(inputs)
        if key not in self.graphs:
            static = replace(inputs, **{k: None if v is None else v.clone() for k, v in fields.items()})
            self.graphs[key] = (step, static, step(static))
            return self.graphs[key][2]
        kept, static, out = self.graphs[key]
        for name, value in fields.items():
            if value is not None:
                getattr(static, name).copy_(value)
        for mine, new in zip(out, kept(static), strict=True):
            mine.copy_(new)
        return out


def test_a_replayed_step_trains_what_eager_steps_train(setup, tmp_path, monkeypatch):
    """What `finetune.cuda_graph` relies on, checked on the CPU: a step replayed as captured (the closure of the
    first call of its shape, on inputs copied in; `ReplayedOnTheCpu`) trains the bytes of the same steps run each
    time (the optimizer's rate a tensor, the gradients zeroed in place), and those are the eager steps' to float32
    rounding (the rate's tensor). Four lights in batches of 3: two shapes, each with its own loss scale. A step
    that read anything but its inputs from its own call (an epoch, a light index, the other batch's scale) would
    train other weights."""
    from diffshadow.diffusion import finetune as ft

    class EachTime:
        def __call__(self, step, inputs):
            return step(inputs)

    _, _, _, data, state = setup
    cfg = replace(FT, batch_size=3, epochs=4)
    eager = finetune(state, data, cfg, tmp_path / "eager.ckpt", log=lambda m: None)
    monkeypatch.setattr(ft, "step_graphs", lambda *a, **k: EachTime())
    stepped = finetune(state, data, cfg, tmp_path / "stepped.ckpt", log=lambda m: None)
    made = []
    monkeypatch.setattr(ft, "step_graphs", lambda *a, **k: made.append(ReplayedOnTheCpu()) or made[-1])
    replayed = finetune(state, data, cfg, tmp_path / "replayed.ckpt", log=lambda m: None)
    assert len(made) == 1 and made[0].calls == 8 and len(made[0].graphs) == 2
    assert replayed["finetune"]["cuda_graph"] is True  # what was done
    assert isinstance(replayed["optimizer"]["param_groups"][0]["lr"], torch.Tensor)
    assert all(torch.equal(stepped["model"][k], replayed["model"][k]) for k in eager["model"])
    moved = max(float((eager["model"][k] - state["model"][k]).abs().max()) for k in eager["model"])
    diff = max(float((eager["model"][k] - replayed["model"][k]).abs().max()) for k in eager["model"])
    assert moved > 1e-3 and diff <= 1e-6, (moved, diff)


def test_cuda_graph_says_that_ddp_steps_eagerly():
    """DDP all-reduces the gradients from hooks inside the backward, which a captured step would not replay: with
    more than one process fine-tuning steps eagerly, and says so where graphs were asked for ("auto" stays silent).
    One process on CUDA gets graphs. (Decided before any CUDA call: this runs on a CPU.)"""
    from diffshadow.diffusion.finetune import step_graphs
    from diffshadow.graphs import StepGraphs

    cuda, messages = torch.device("cuda"), []
    assert step_graphs(replace(FT, cuda_graph=True), 2, cuda, messages.append) is None
    assert step_graphs(replace(FT, cuda_graph="auto"), 4, cuda, messages.append) is None
    assert messages == ["finetune.cuda_graph: DDP over 2 processes is not captured; stepping eagerly"]
    assert isinstance(step_graphs(replace(FT, cuda_graph="auto"), 1, cuda, messages.append), StepGraphs)
    assert step_graphs(FT, 1, cuda, messages.append) is None and len(messages) == 1


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="unknown key"):
        FinetuneConfig.from_config({"epoch": 3})


# Two guards for the CUDA path, which CI cannot run. The stages' rule: a tensor is made on the device that
# uses it, or on the CPU by name (random draws, module initialisation) and then moved.

def test_a_finetune_step_runs_on_a_second_device_and_its_update_copies_nothing_from_the_host(setup):
    """Everything the step touches must have been moved to the working device: "meta" plays the GPU and
    the CPU the host, so a tensor left on the host (the training lights once were) fails here. Its nine draws
    (lights, timesteps, noise, points, pixels; the pool's four) are copied without blocking, and the update, what
    `finetune.cuda_graph` captures (loss, backward, gradient clip), copies nothing from the host after its first
    (which moves the schedule's and standardizer's tables once) and reads nothing back."""
    from test_syncs import HostTraffic

    _, _, _, data, state = setup
    dcfg = DiffusionConfig.from_config(state["config"])
    layout = WeightLayout.from_config(state["layout"])
    meta, schedule = torch.device("meta"), Schedule()
    model = build_model(layout, dcfg).to(meta)
    std = Standardizer(layout, state["standardizer"]["mean"], state["standardizer"]["std"])
    z_all = std.standardize(data.train.weights).float().to(meta)
    on_meta = data.to(meta)

    def update(epoch: int) -> tuple[int, int]:
        with (drawn := HostTraffic()):
            batch = draw_step(on_meta, [0, 2], epoch, FT, dcfg, schedule.steps, meta)
        assert (drawn.copies, drawn.blocking) == (9, 0)
        with (traffic := HostTraffic()):
            loss, parts = step_loss(model, std, on_meta, z_all, batch, FT, dcfg, schedule, scale=0.5)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), dcfg.grad_clip)
        assert loss.device == meta and loss.shape == () and parts.shape == (3,)
        return traffic.copies, traffic.reads

    assert update(0)[0] > 0
    assert update(1) == (0, 0)


def test_finetune_makes_no_tensor_on_the_implicit_default_device(setup, tmp_path):
    """With the default device "meta" and the working device the CPU, a tensor made without naming its
    device (the pixel draws once were: a CPU tensor beside CUDA counts) fails."""
    _, _, _, data, state = setup
    reference = finetune(state, data, FT, tmp_path / "a.ckpt", log=lambda m: None)["model"]
    with default_device_meta():
        guarded = finetune(state, data, FT, tmp_path / "b.ckpt", device="cpu", log=lambda m: None)["model"]
    assert all(torch.equal(reference[k], guarded[k]) for k in reference)


def test_the_model_kept_is_the_last_one_not_below_the_geometry_stage_on_validation_lights(volume, setup, tmp_path):

    from diffshadow.diffusion.finetune import validation_psnr
    from diffshadow.diffusion.sample import load_sampler
    from diffshadow.lights import validation_lights
    from diffshadow.truth import EvalTruth

    _, _, _, data, state = setup
    val = EvalTruth.compute(volume, TF, validation_lights(LIGHTS, LIGHTS[0], 3, seed=0), 128, seed=1)
    # a large lr: epochs differ on validation; patience 0: every epoch is scored
    cfg = FinetuneConfig(**{**FT.__dict__, "epochs": 4, "lr": 3e-3, "patience": 0})
    out = finetune(state, replace(data, val=val), cfg, tmp_path / "v.ckpt", log=lambda m: None)
    history = out["selection"]["history"]
    assert [e for e, _ in history] == [0, 1, 2, 3, 4]
    floor = history[0][1]
    assert out["selection"]["kept_epoch"] == max(e for e, v in history if v >= floor)
    # the model returned, and the one on disk, is the kept one: scored again it gives the value recorded for it
    model, std, layout, siren = load_sampler(out)
    dcfg = DiffusionConfig.from_config(out["config"])
    assert validation_psnr(model, std, val, layout, dcfg, siren, "cpu") == dict(history)[out["selection"]["kept_epoch"]]
    on_disk = torch.load(tmp_path / "v.ckpt", weights_only=False)["model"]
    assert all(torch.equal(on_disk[k], out["model"][k]) for k in on_disk)


def test_fine_tuning_stops_when_validation_stays_under_the_geometry_stage(volume, setup, tmp_path, monkeypatch):

    import diffshadow.diffusion.finetune as ft
    from diffshadow.lights import validation_lights
    from diffshadow.truth import EvalTruth

    _, _, _, data, state = setup
    val = EvalTruth.compute(volume, TF, validation_lights(LIGHTS, LIGHTS[0], 2, seed=0), 64, seed=1)
    scores = iter([30.0, 29.0, 31.0, 28.0, 27.5, 40.0, 40.0])  # epochs 0..6: under, over, under, under, ...
    monkeypatch.setattr(ft, "validation_psnr", lambda *a: next(scores))
    cfg = FinetuneConfig(**{**FT.__dict__, "epochs": 6, "patience": 2})
    messages = []
    out = finetune(state, replace(data, val=val), cfg, tmp_path / "s.ckpt", log=messages.append)
    sel = out["selection"]
    assert [e for e, _ in sel["history"]] == [0, 1, 2, 3, 4] and sel["stopped_epoch"] == 4
    assert sel["kept_epoch"] == 2 and any("stopping at epoch 4/6 and keeping epoch 2" in m for m in messages)
    # what is on disk is the kept model, and a rerun finds the run finished: no training, no scoring
    on_disk = torch.load(tmp_path / "s.ckpt", weights_only=False)
    assert on_disk["model"] is not None and all(torch.equal(on_disk["model"][k], out["model"][k]) for k in out["model"])
    again = finetune(state, replace(data, val=val), cfg, tmp_path / "s.ckpt", log=lambda m: None)
    assert all(torch.equal(again["model"][k], out["model"][k]) for k in out["model"])
    assert next(scores) == 40.0  # not one more validation was asked for


def test_fine_tuning_steps_from_the_raw_weights_and_keeps_the_ema_when_it_never_beats_it(volume, setup, tmp_path,
                                                                                       monkeypatch):

    import diffshadow.diffusion.finetune as ft
    from diffshadow.lights import validation_lights
    from diffshadow.truth import EvalTruth

    _, _, _, data, state = setup
    assert state["config"]["ema"] > 0
    assert any(not torch.equal(state["ema"][k], state["model"][k]) for k in state["model"])
    val = EvalTruth.compute(volume, TF, validation_lights(LIGHTS, LIGHTS[0], 2, seed=0), 64, seed=1)
    scored = []
    scores = iter([30.0, 29.0, 28.0])

    def fake(model, *a):
        scored.append({k: v.clone() for k, v in model.state_dict().items()})
        return next(scores)

    monkeypatch.setattr(ft, "validation_psnr", fake)
    cfg = FinetuneConfig(**{**FT.__dict__, "epochs": 4, "patience": 2})
    out = finetune(state, replace(data, val=val), cfg, tmp_path / "e.ckpt", log=lambda m: None)
    assert all(torch.equal(scored[0][k], state["ema"][k]) for k in state["ema"])  # the floor: the sampler
    assert out["selection"]["kept_epoch"] == 0
    assert all(torch.equal(out["model"][k], state["ema"][k]) for k in state["ema"])
    # epoch 1's model is one step from the raw weights, not from their average
    moved = {k: float((scored[1][k] - state["model"][k]).abs().max()) for k in state["model"]}
    from_avg = {k: float((scored[1][k] - state["ema"][k]).abs().max()) for k in state["ema"]}
    assert max(moved.values()) < max(from_avg.values())
    # what kept epoch 0 holds samples as the geometry stage does, so stage 2 scores its images once, not twice
    assert ft.same_sampler(state, out)
    assert np.array_equal(ft.image_psnr_of_model(out, data), ft.image_psnr_of_model(state, data))
    name = next(iter(state["ema"]))
    nudged = {**out["model"], name: torch.nextafter(out["model"][name], torch.tensor(math.inf))}
    assert not ft.same_sampler(state, {**out, "model": nudged})
    assert not ft.same_sampler(state, {**out, "config": {**out["config"], "temperature": 0.5}})
    assert not ft.same_sampler(state, out | {"standardizer": {**out["standardizer"],
                                                               "std": out["standardizer"]["std"] * 2}})


def test_pool_lights_add_their_loss_to_a_fine_tuning_step(setup):
    """The pool's loss is added (so the lights between the training ones are held), the training lights'
    own parts stay what they are without it."""

    _, _, _, data, state = setup
    dcfg = DiffusionConfig.from_config(state["config"])
    layout = WeightLayout.from_config(state["layout"])
    std = Standardizer(layout, state["standardizer"]["mean"], state["standardizer"]["std"])
    model = build_model(layout, dcfg)
    model.load_state_dict(state["model"])
    z_all = std.standardize(data.train.weights).float()
    cpu, no_pool, schedule = torch.device("cpu"), replace(dcfg, pool_lights=0), Schedule()
    with_pool, parts = step_loss(model, std, data, z_all, draw_step(data, [0, 2], 0, FT, dcfg, schedule.steps, cpu),
                                 FT, dcfg, schedule, scale=1.0)
    without, parts0 = step_loss(model, std, data, z_all, draw_step(data, [0, 2], 0, FT, no_pool, schedule.steps, cpu),
                                FT, no_pool, schedule, scale=1.0)
    assert float(with_pool.detach()) > float(without.detach()) > 0 and torch.allclose(parts, parts0)


def test_a_fine_tuned_model_that_renders_worse_gives_way_to_the_geometry_stage():
    from diffshadow.diffusion.finetune import keep_if_images_improve
    ema, raw, tuned = ({"w": torch.full((2,), v)} for v in (1.0, 2.0, 3.0))
    geometry = {"model": raw, "ema": ema}
    state = {"model": tuned, "ema": None, "selection": {"history": [[0, 30.0], [10, 30.1]], "kept_epoch": 10}}
    same, kept = keep_if_images_improve(geometry, state, np.array([50.0, 52.0]), np.array([51.0, 51.0]))
    assert kept == "fine-tuned" and same is state  # equal means: kept
    out, kept = keep_if_images_improve(geometry, state, np.array([50.0, 52.0]), np.array([50.0, 51.9]))
    assert kept == "geometry stage" and out["model"] is ema and out["ema"] is None
    assert out["selection"] == {"history": [[0, 30.0], [10, 30.1]], "kept_epoch": 0, "images_worse": True,
                                "validated_epoch": 10}
    assert state["selection"]["kept_epoch"] == 10  # the input is not changed
    out, _ = keep_if_images_improve({"model": raw, "ema": None}, state, np.array([50.0]), np.array([49.0]))
    assert out["model"] is raw  # a geometry stage without an EMA samples from its raw weights
    none_kept = {**state, "selection": {"history": [[0, 30.0], [10, 29.0]], "kept_epoch": 0}}
    assert keep_if_images_improve(geometry, none_kept, np.array([50.0]), np.array([50.0]))[1] == "geometry stage"
    unvalidated = {**state, "selection": {"history": [], "kept_epoch": 0}}  # no validation lights: the last one
    assert keep_if_images_improve(geometry, unvalidated, np.array([50.0]), np.array([50.0]))[1] == "fine-tuned"


def test_the_summary_says_when_fine_tuning_gave_way():
    from diffshadow.summary import _kept
    picked = {"history": [[0, 32.9], [10, 33.0], [20, 32.8]], "kept_epoch": 10}
    assert "Kept: epoch 10 of 20" in _kept(picked) and "Validation had picked" not in _kept(picked)
    gave_way = {**picked, "kept_epoch": 0, "images_worse": True, "validated_epoch": 10}
    text = _kept(gave_way)
    assert text.startswith(" Kept: epoch 0 of 20, the geometry-stage model.")
    assert "had picked epoch 10, the last whose median voxel PSNR (33.00 dB) is not below" in text
    assert text.endswith("so the geometry-stage model is used.")

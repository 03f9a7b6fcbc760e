"""On a CUDA device: each stage function agrees with the CPU, deterministic mode repeats bytes, DDP over
NCCL equals one process, and the tiny workflow runs end to end with fine-tuning. Skipped without CUDA
(CI has none: the CPU guards in test_finetune/test_fit/test_diffusion/test_render cover what they can).

Tolerances: TF32 is off (PyTorch's default for matmuls), so CPU and CUDA differ only in float32
summation order: ~1e-6 relative per op. A few optimiser steps of a SIREN (ω0 = 30) amplify that, hence
1e-3 on fitted SIREN outputs; renders and shadow grids, which have no training, are held to 1e-4.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp
from conftest import Killed, stop_at

from diffshadow.analytic import gaussian_blob
from diffshadow.data_inr import DataInrConfig, fit_data_inr
from diffshadow.diffusion.config import DiffusionConfig
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.train import TrainingData, train_diffusion
from diffshadow.fit import FitConfig, fit_sirens
from diffshadow.render import Camera, Networks, RenderScene
from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout, init_siren
from diffshadow.store import open_store
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")]

CUDA = torch.device("cuda")
TF = TransferFunction.from_config({"opacity": [[0, 0], [0.2, 0], [1, 0.8]],
                                   "color": [[0, 0.2, 0.4, 0.9], [1, 1, 0.3, 0.2]], "density_scale": 20})
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
SIREN = SirenConfig(16, 1)
LAYOUT = WeightLayout.for_siren(SIREN)
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def volume():
    a = gaussian_blob(33, 0.15)
    return Volume(data=np.maximum(a, np.roll(a, (6, -4, 8), axis=(0, 1, 2))), extent=np.ones(3), name="blobs")


def _init():
    return LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0)))


def recorded_graphs(monkeypatch) -> list:
    """The `StepGraphs` that the stages make from now on (through `graphs.requested`), in a list as made."""
    from diffshadow import graphs

    made = []

    class Recorded(graphs.StepGraphs):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(graphs, "StepGraphs", Recorded)
    return made


def runtime_calls(fn) -> list[str]:
    """The CUDA runtime calls (cudaLaunchKernel, cudaStreamSynchronize, ...) a profile of one call of `fn` records."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
    return [e.name for e in prof.events() if e.name.startswith("cuda")]


def test_fit_agrees_with_cpu(volume):
    cfg = FitConfig.from_config(dict(steps=20, points=2048, eval_points=512, grid_upsample=1, min_psnr=0.0,
                                     chunk=0))
    cpu = fit_sirens(_init(), LAYOUT, SIREN, volume, TF, LIGHTS, cfg, device="cpu", log=lambda m: None)
    gpu = fit_sirens(_init(), LAYOUT, SIREN, volume, TF, LIGHTS, cfg, device=CUDA, log=lambda m: None).cpu()
    pts = torch.rand(len(LIGHTS), 1000, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    a, b = BatchedSiren(cpu, LAYOUT, SIREN.blocks)(pts), BatchedSiren(gpu, LAYOUT, SIREN.blocks)(pts)
    assert float((a - b).abs().max()) <= 1e-3


def test_graphed_fit_steps_fit_what_eager_steps_fit(volume, tmp_path, monkeypatch):
    """fit.cuda_graph: a subset's steps replayed as CUDA graphs give eager steps' SIRENs, with the blend loss's pool
    (its picks are graph inputs), the cosine learning rate (a device tensor each step fills: a graph that kept its
    first lr would drift from eager) and a fit resumed from a checkpoint."""
    from dataclasses import replace

    from diffshadow.fit import blend_pool

    made = recorded_graphs(monkeypatch)
    cfg = FitConfig.from_config(dict(steps=24, points=1024, eval_points=512, grid_upsample=1, min_psnr=0.0,
                                     checkpoint_every=8, blend_weight=1.0, blend_per_light=4, blend_points=256,
                                     cuda_graph=False))  # eager: `auto`, the default, graphs on CUDA
    pool = blend_pool(volume, TF, LIGHTS, np.array([0.0, 0.0, 1.0]), [0, 1, 2, 3], cfg)
    run = {"pool": pool, "device": CUDA, "log": lambda m: None}
    eager = fit_sirens(_init(), LAYOUT, SIREN, volume, TF, LIGHTS, cfg, **run)
    graphed = fit_sirens(_init(), LAYOUT, SIREN, volume, TF, LIGHTS, replace(cfg, cuda_graph=True), **run)
    assert len(made) == 1 and made[0].calls == 24 and len(made[0].graphs) == 1
    ckpt, calls = tmp_path / "subset.ckpt", []

    def interrupt(msg):  # progress every 2 steps here (a tenth of the fit): stop after step 10, saved at 8
        calls.append(msg)
        if len(calls) == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_sirens(_init(), LAYOUT, SIREN, volume, TF, LIGHTS, replace(cfg, cuda_graph=True), checkpoint=ckpt,
                   pool=pool, device=CUDA, log=interrupt)
    resumed = fit_sirens(_init(), LAYOUT, SIREN, volume, TF, LIGHTS, replace(cfg, cuda_graph=True),
                         checkpoint=ckpt, **run)
    pts = torch.rand(len(LIGHTS), 1000, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    a = BatchedSiren(eager, LAYOUT, SIREN.blocks)(pts)
    for other in (graphed, resumed):
        assert float((a - BatchedSiren(other, LAYOUT, SIREN.blocks)(pts)).abs().max()) <= 1e-3


def test_data_inr_with_error_points_resumes_on_cuda(volume, tmp_path):
    """The error-driven points' scores ride in the checkpoint, which loads onto the GPU; the points are drawn on
    the CPU, so a resumed run must bring the scores back there."""
    cfg = DataInrConfig.from_config(dict(width=16, blocks=1, steps=60, points=512, checkpoint_every=20,
                                         error_every=30, target_psnr=0))

    with pytest.raises(Killed):
        fit_data_inr(volume, TF, cfg, checkpoint=tmp_path / "inr.ckpt", device=CUDA, log=stop_at("step 42/"))
    messages = []
    inr = fit_data_inr(volume, TF, cfg, checkpoint=tmp_path / "inr.ckpt", device=CUDA, log=messages.append)
    assert any("resuming" in m for m in messages)
    # 60 steps of a width-16 SIREN reach only ~11 dB (on the CPU too), so no absolute bar: the resumed CUDA run
    # must end where one uninterrupted CPU run ends. Measured on an H200: 3.6e-7 dB apart.
    whole = fit_data_inr(volume, TF, cfg, checkpoint=tmp_path / "cpu.ckpt", device="cpu", log=lambda m: None)
    assert np.isfinite(inr.psnr) and abs(inr.psnr - whole.psnr) < 0.01, (inr.psnr, whole.psnr)


def test_graphed_data_inr_steps_fit_what_eager_steps_fit(volume, tmp_path, monkeypatch):
    """data_inr.cuda_graph: the data INR's steps replayed as CUDA graphs end where eager steps end, with the
    error-driven points (rescored outside the graph), the cosine learning rate (a device tensor) and a resume."""
    from dataclasses import replace

    made = recorded_graphs(monkeypatch)
    cfg = DataInrConfig.from_config(dict(width=16, blocks=1, steps=60, points=512, checkpoint_every=20,
                                         error_every=30, target_psnr=0, cuda_graph=False))  # eager, not `auto`
    eager = fit_data_inr(volume, TF, cfg, device=CUDA, log=lambda m: None)
    graphed_cfg = replace(cfg, cuda_graph=True)
    graphed = fit_data_inr(volume, TF, graphed_cfg, device=CUDA, log=lambda m: None)
    assert len(made) == 1 and made[0].calls == 60 and len(made[0].graphs) == 1
    assert (eager.config["cuda_graph"], graphed.config["cuda_graph"]) == (False, True)

    with pytest.raises(Killed):
        fit_data_inr(volume, TF, graphed_cfg, checkpoint=tmp_path / "inr.ckpt", device=CUDA,
                     log=stop_at("step 42/"))
    resumed = fit_data_inr(volume, TF, graphed_cfg, checkpoint=tmp_path / "inr.ckpt", device=CUDA,
                           log=lambda m: None)
    for other in (graphed, resumed):
        assert abs(other.psnr - eager.psnr) < 0.01, (other.psnr, eager.psnr)


def _training_data():
    gen = torch.Generator().manual_seed(0)
    weights = _init() + 0.01 * torch.randn(len(LIGHTS), LAYOUT.n_params, generator=gen)
    return TrainingData(weights=weights, lights=torch.as_tensor(LIGHTS, dtype=torch.float32),
                        points=torch.rand(len(LIGHTS), 64, 3, generator=gen),
                        values=torch.rand(len(LIGHTS), 64, generator=gen), extent=torch.ones(3), layout=LAYOUT,
                        siren=SIREN)


DCFG = DiffusionConfig.from_config(dict(preset="tiny", epochs=4, batch_size=2, geometry_points=16, checkpoint_every=2,
                                             pool_lights=0, target_gap=0.0))


def test_diffusion_training_and_sampling_agree_with_cpu(tmp_path):
    data = _training_data()
    cpu = train_diffusion(data, DCFG, tmp_path / "cpu.ckpt", device="cpu", log=lambda m: None)
    gpu = train_diffusion(data, DCFG, tmp_path / "gpu.ckpt", device=CUDA, log=lambda m: None)
    diff = max(float((cpu["model"][k] - gpu["model"][k].cpu()).abs().max()) for k in cpu["model"])
    assert diff <= 1e-4, diff
    model, std, _, _ = load_sampler(cpu, "cpu")
    g_model, g_std, _, _ = load_sampler(cpu, CUDA)  # the same weights: sampling alone
    a = generate(model, std, LIGHTS, steps=10, seed=3, device="cpu")
    b = generate(g_model, g_std, LIGHTS, steps=10, seed=3, device=CUDA).cpu()
    assert float((a - b).abs().max() / a.abs().max()) <= 1e-4


def test_the_blend_correction_fits_on_cuda_what_it_fits_on_the_cpu(monkeypatch):
    """fit_correction's steps on CUDA: the same draws, the network within float rounding of the CPU's."""
    from diffshadow import correction as corr

    sys.path.insert(0, str(REPO / "tests"))
    import test_correction as tc

    monkeypatch.setattr(corr, "correction_lights", tc.synthetic_lights)
    fits = [corr.fit_correction(tc.store(), None, None, tc.TRAIN, tc.CENTER, tc.config(steps=30), k=4,
                                weighting="triangle", device=d, log=lambda m: None) for d in ("cpu", CUDA)]
    for a, b in zip(fits[0].net.parameters(), fits[1].net.parameters(), strict=True):
        assert b.device.type == "cpu" and torch.allclose(a, b, atol=1e-4), float((a - b).abs().max())


def test_graphed_sampling_generates_what_eager_sampling_generates(tmp_path):
    """`generate` on CUDA replays its denoiser as CUDA graphs (the default): DDIM and DDPM give eager sampling's
    weights; the graphs stay with the model (a later call of the batch captures none); a model whose parameters
    moved to new storage is captured again, not replayed on the freed old weights."""
    from diffshadow.diffusion import sample

    state = train_diffusion(_training_data(), DCFG, tmp_path / "m.ckpt", device="cpu", log=lambda m: None)
    model, std, _, _ = load_sampler(state, CUDA)

    def both(method, steps):
        eager = generate(model, std, LIGHTS, method=method, steps=steps, seed=3, device=CUDA, cuda_graph=False)
        graphed = generate(model, std, LIGHTS, method=method, steps=steps, seed=3, device=CUDA)
        assert float((eager - graphed).abs().max() / eager.abs().max()) <= 1e-6, (method, steps)
        return graphed

    both("ddim", 10)
    graphs = sample._GRAPHS[model][1]
    both("ddpm", 500)
    assert sample._GRAPHS[model][1] is graphs and len(graphs.graphs) == 1 and graphs.calls == 510
    before = both("ddim", 10)
    with torch.no_grad():
        for p in model.parameters():
            p.data = p.data * 1.01  # new storage: the old graph would read freed memory
    after = both("ddim", 10)
    assert sample._GRAPHS[model][1] is not graphs and not torch.equal(before, after)


def test_caches_model_rows_on_cuda_are_the_cpus_to_float_rounding(tmp_path):
    """evaluate.device: run samples caches' fp16 model on the GPU; its PSNRs (taken on the CPU) are the CPU run's
    to float rounding, and its rows name the GPU."""
    from types import SimpleNamespace

    from diffshadow.caches import cache_table
    from diffshadow.truth import EvalTruth

    data = _training_data()
    state = train_diffusion(data, DCFG, tmp_path / "m.ckpt", device="cpu", log=lambda m: None)
    train, unseen = LIGHTS[:3], LIGHTS[3:]
    g = torch.Generator().manual_seed(4)
    truth = EvalTruth(points={"box": torch.rand(128, 3, generator=g)}, lights=LIGHTS,
                      values={"box": torch.rand(len(LIGHTS), 128, generator=g)}, extent=torch.ones(3))
    store = SimpleNamespace(weights=data.weights[:3].numpy(), layout=LAYOUT, siren=SIREN)
    generated = SimpleNamespace(psnr=np.full(4, 30.0), seen=np.arange(4) < 3, config={})
    tables = [cache_table(store, truth, {"train": train, "unseen": unseen}, blend_k=3, weighting="inverse-angle",
                          model_state=state, generated=generated, device=d, log=lambda m: None)
              for d in ("cpu", CUDA)]
    cpu, gpu = ({r["cache"]: r for r in t["caches"]} for t in tables)
    row = "diffusion model fp16"
    assert gpu[row]["device"] == torch.cuda.get_device_name(CUDA) and cpu[row]["device"].startswith("cpu")
    for key in ("seen_psnr", "unseen_psnr"):
        assert abs(gpu[row][key] - cpu[row][key]) < 0.01, (key, gpu[row][key], cpu[row][key])


def test_graphed_geometry_steps_train_what_eager_steps_train(tmp_path, monkeypatch):
    """diffusion.cuda_graph: the geometry stage's steps replayed as CUDA graphs give eager steps' weights. Four
    lights in batches of 3: an epoch's short last batch gets a graph of its own; the lr, halved every epoch, reaches
    the replays (a graph that kept its first lr would drift from eager); a run resumed from a checkpoint (its
    optimizer state and tensor lr) graphs on to the same weights."""
    import dataclasses

    made = recorded_graphs(monkeypatch)
    data = _training_data()
    cfg = dataclasses.replace(DCFG, batch_size=3, epochs=6, lr_step_epochs=1, lr_gamma=0.5, checkpoint_every=3,
                              cuda_graph=False)
    graphed_cfg = dataclasses.replace(cfg, cuda_graph=True)
    eager = train_diffusion(data, cfg, tmp_path / "eager.ckpt", device=CUDA, log=lambda m: None)
    graphed = train_diffusion(data, graphed_cfg, tmp_path / "graph.ckpt", device=CUDA, log=lambda m: None)
    assert len(made) == 1 and made[0].calls == 12 and len(made[0].graphs) == 2  # batches of 3 and of 1
    assert (eager["config"]["cuda_graph"], graphed["config"]["cuda_graph"]) == (False, True)
    train_diffusion(data, graphed_cfg, tmp_path / "resumed.ckpt", device=CUDA, log=lambda m: None, stop_after_epoch=3)
    resumed = train_diffusion(data, graphed_cfg, tmp_path / "resumed.ckpt", device=CUDA, log=lambda m: None)
    for other in (graphed, resumed):
        for key in ("model", "ema"):
            diff = max(float((eager[key][k] - other[key][k]).abs().max()) for k in eager[key])
            assert diff <= 1e-4, (key, diff)  # as CUDA against the CPU (above): Adam lifts tiny gradients


def test_graphed_geometry_stage_stopped_inside_an_epoch_resumes_on_cuda(tmp_path, monkeypatch):
    """SIGTERM inside an epoch of the graphed geometry stage: the checkpoint holds the step, the rerun recaptures its
    graphs and goes on from the epoch generator's saved state to the uninterrupted run's weights."""
    import dataclasses
    import signal

    from test_stopping import signal_at

    from diffshadow.diffusion import train
    from diffshadow.stopping import Stopped

    data = _training_data()
    cfg = dataclasses.replace(DCFG, batch_size=3, epochs=6, lr_step_epochs=1, lr_gamma=0.5, checkpoint_every=3,
                              cuda_graph=True)
    whole = train_diffusion(data, cfg, tmp_path / "whole.ckpt", device=CUDA, log=lambda m: None)
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        with monkeypatch.context() as m:
            m.setattr(train, "train_batch", signal_at(train, "train_batch", 5))  # step 1 of epoch 3
            with pytest.raises(Stopped, match="at step 1 of epoch 3;"):
                train_diffusion(data, cfg, tmp_path / "b.ckpt", device=CUDA, log=lambda m: None)
    finally:
        signal.signal(signal.SIGTERM, previous)
    saved = torch.load(tmp_path / "b.ckpt", weights_only=False)
    assert saved["epoch"] == 2 and saved["within_epoch"]["batches"] == 1
    resumed = train_diffusion(data, cfg, tmp_path / "b.ckpt", device=CUDA, log=lambda m: None)
    for key in ("model", "ema"):
        diff = max(float((whole[key][k] - resumed[key][k]).abs().max()) for k in whole[key])
        assert diff <= 1e-6, (key, diff)


def test_graphed_finetune_steps_train_what_eager_steps_train(tmp_path, monkeypatch):
    """finetune.cuda_graph: one process's steps replayed as CUDA graphs give eager steps' weights. Four lights in
    batches of 3: an epoch's short last batch (its own loss scale) gets a graph of its own; a run resumed from a
    checkpoint (its optimizer state and tensor lr) graphs on to the same weights."""
    import dataclasses

    sys.path.insert(0, str(REPO / "tests"))
    import test_finetune as T

    vol = Volume(data=gaussian_blob(17, 0.3), extent=np.ones(3), name="blob")
    _, _, _, data, state = T.make_setup(vol, tmp_path)
    made = recorded_graphs(monkeypatch)
    cfg = dataclasses.replace(T.FT, batch_size=3, epochs=4, checkpoint_every=2)
    graphed_cfg = dataclasses.replace(cfg, cuda_graph=True)
    eager = T.finetune(state, data, cfg, tmp_path / "eager.ckpt", device=CUDA, log=lambda m: None)
    graphed = T.finetune(state, data, graphed_cfg, tmp_path / "graph.ckpt", device=CUDA, log=lambda m: None)
    assert len(made) == 1 and made[0].calls == 8 and len(made[0].graphs) == 2  # batches of 3 and of 1
    assert (eager["finetune"]["cuda_graph"], graphed["finetune"]["cuda_graph"]) == (False, True)
    T.finetune(state, data, graphed_cfg, tmp_path / "resumed.ckpt", device=CUDA, log=lambda m: None,
               stop_after_epoch=2)
    resumed = T.finetune(state, data, graphed_cfg, tmp_path / "resumed.ckpt", device=CUDA, log=lambda m: None)
    moved = max(float((eager["model"][k].cpu() - state["model"][k]).abs().max()) for k in state["model"])
    assert moved > 1e-4  # the steps did something
    for other in (graphed, resumed):
        diff = max(float((eager["model"][k] - other["model"][k]).abs().max()) for k in eager["model"])
        assert diff <= 1e-4, diff  # as the geometry stage's graphs (above)


@pytest.mark.parametrize("stage", ["train_diffusion", "fit_siren", "preoptimize", "train_data_inr",
                                   "finetune_render"])
def test_a_training_step_never_waits_for_the_gpu(stage):
    """A training step's draws, made on the host, are pinned and copied asynchronously (`sampling.to_device`): the
    CUDA profile of three steps has no stream or device synchronization beyond what an empty profile has. A
    blocking copy from ordinary host memory synchronizes the stream, and the geometry step had eight of them.
    Every stage's step, as `bench stages` times it (eager: the graphs are off)."""
    from diffshadow.bench.stages import BUILDERS
    from diffshadow.config import merge, run_config, scene_config
    from diffshadow.volume import scene_volume

    tiny = {"lights": {"count": 6, "unseen": 2}, "subset_size": 6,
            "fit": {"points": 128, "blend_per_light": 2, "blend_points": 32, "cuda_graph": False},
            "data_inr": {"points": 512, "width": 16, "blocks": 1, "cuda_graph": False},
            "finetune": {"views": 1, "image_size": 16, "pixels": 4, "batch_size": 4, "nproc": 2},
            "diffusion": {"presample_points": 64, "pool_lights": 4, "pool_points": 32, "geometry_points": 16,
                          "batch_size": 4, "epochs": 3, "max_epochs": 3, "cuda_graph": False}}
    cfg = scene_config(run_config(merge({}, tiny), "test"), "nucleon", scenes_dir=REPO / "config/scenes")
    timed = BUILDERS[stage](cfg, CUDA, *scene_volume(cfg))
    for i in range(3):  # the pinned blocks' cache fills
        timed.step(i)
    torch.cuda.synchronize()
    # the profiler may synchronize as it stops: what an empty profile records is the baseline
    base = [n for n in runtime_calls(lambda: None) if "Synchronize" in n]
    calls = runtime_calls(lambda: [timed.step(i) for i in range(3, 6)])
    assert any("Launch" in n for n in calls), sorted(set(calls))  # the profile sees the runtime's calls
    assert sorted(n for n in calls if "Synchronize" in n) == sorted(base), sorted(set(calls))


def test_a_march_waits_for_the_gpu_as_often_as_its_cpu_count_says(volume):
    """Each host sync a CPU count sees (scalar reads, nonzero) and each tensor built from host data is one stream
    synchronise on CUDA, and the march makes no other: the counts taken on a CPU are the GPU's waits. (Its
    lookup once built two tensors from host numbers at every iteration, waits no CPU count saw.)"""
    from diffshadow.bench.profile import op_counts
    from diffshadow.shadow import ShadowField, transmittance

    pts = torch.rand(4096, 3, generator=torch.Generator().manual_seed(0))

    def march(device):
        field = ShadowField.build(volume, TF, device=device)
        p = pts.to(device)
        return lambda: transmittance(field, TF, (0.3, -0.5, 0.8), p, skip_empty=True)

    on_cpu, on_cuda = march(torch.device("cpu")), march(CUDA)
    on_cpu(), on_cuda()  # a grid shape's constants are built once (`grid.lattice`)
    torch.cuda.synchronize()
    counts = op_counts(on_cpu)
    base = sum("Synchronize" in n for n in runtime_calls(lambda: None))  # the profiler may synchronize as it stops
    calls = runtime_calls(on_cuda)
    assert any("Launch" in n for n in calls), sorted(set(calls))  # the profile sees the runtime's calls
    waits = sum("Synchronize" in n for n in calls) - base
    assert counts["syncs"] > 10 and waits <= counts["syncs"] + counts["host_tensors"], (waits, counts)


def test_ema_update_on_cuda_is_one_op_with_each_parameters_lerp():
    """The EMA of the geometry stage's weights is one multi-tensor op a step on CUDA (not a lerp per parameter
    tensor), with the bits of the per-tensor lerp. The op count takes a multi-tensor op as one on every device,
    so the fast path is checked in the profile: no per-tensor lerp under it, as a CPU (or CUDA's fallback) has."""
    from torch.profiler import ProfilerActivity, profile

    from diffshadow.bench.profile import op_counts
    from diffshadow.diffusion.model import PRESETS, WeightTransformer
    from diffshadow.diffusion.train import Ema, ema_decay

    model = WeightTransformer(LAYOUT, PRESETS["tiny"]).to(CUDA)
    ema = Ema(model, 0.995)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.rand_like(p))
    expected = [e.lerp(p, 1 - ema_decay(0.995, 0)) for e, p in zip(ema.model.parameters(), model.parameters(),
                                                                   strict=True)]
    ops = op_counts(lambda: ema.update(model, 0))["ops"]
    assert all(torch.equal(e, p) for e, p in zip(expected, ema.model.parameters(), strict=True))
    assert ops < len(expected) / 4, (ops, len(expected))
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        ema.update(model, 1)
    names = [e.name for e in prof.events()]
    assert "aten::_foreach_lerp_" in names and "aten::lerp_" not in names, sorted(set(names))


@pytest.mark.parametrize("mode", ["noshadow", "gt", "naive", "inr"])
def test_render_agrees_with_cpu(volume, mode):
    cam = Camera.orbit(volume.extent, azimuth=40, elevation=20, size=48)
    gen = torch.Generator().manual_seed(0)
    siren = (LAYOUT.flatten(init_siren(SIREN, gen)), LAYOUT, SIREN.blocks) if mode == "inr" else None
    light = None if mode == "noshadow" else LIGHTS[1]
    # the eager path on both devices (on CUDA `auto` picks the fused kernels, whose TF32 rounding the tests
    # below bound)
    a = RenderScene(volume, TF, device="cpu").render(mode, cam, light=light, siren=siren)
    b = RenderScene(volume, TF, device=CUDA, networks=Networks("eager")).render(mode, cam, light=light, siren=siren)
    assert float(a.alpha.max()) > 0.3
    assert float((a.rgb - b.rgb.cpu()).abs().max()) <= 1e-4


@pytest.mark.parametrize("kernel", ["eager", "auto"])
def test_a_view_under_another_light_from_kept_samples_on_cuda_is_the_marched_image(volume, kernel):
    """On CUDA as on the CPU: a view drawn again under another light from its kept samples is the image a fresh
    scene marches, to the byte, with the shadow INR eager or fused (over the raw grid the frame is marched by the
    wavefront loop either way; with the fused data INR too, whole rays in one kernel, nothing is kept)."""
    cam = Camera.orbit(volume.extent, azimuth=40, elevation=20, size=48)
    siren = (LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0))), LAYOUT, SIREN.blocks)
    keeping = RenderScene(volume, TF, device=CUDA, networks=Networks(kernel), keep_samples=1 << 28)
    fresh = RenderScene(volume, TF, device=CUDA, networks=Networks(kernel))
    for mode in ("gt", "inr"):
        for i, light in enumerate(LIGHTS[1:]):
            kw = {"light": light, "siren": siren, "scalar": "grid"}
            img, want = keeping.render(mode, cam, **kw), fresh.render(mode, cam, **kw)
            assert img.replayed == ((mode, i) != ("gt", 0)) and not want.replayed, (mode, i)
            assert torch.equal(img.rgb, want.rgb), (mode, i)


def test_the_kernels_sine_on_cuda():
    """`_kernels.sine` compiled (the special-function unit after the exact reduction), against float64 sin,
    |x| <= 1e4 (tests/test_fused.py checks the reduction in the interpreter)."""
    triton = pytest.importorskip("triton")
    from diffshadow.render._kernels import sine_kernel
    from diffshadow.render.fused import FP_FUSION

    x = ((torch.rand(1_000_000, generator=torch.Generator().manual_seed(2)) * 2 - 1) * 1e4).to(CUDA)
    y = torch.empty_like(x)
    # as the renderer launches it (`fused._launch`)
    sine_kernel[(triton.cdiv(len(x), 1024),)](x, y, len(x), COPY=False, BLOCK=1024, enable_fp_fusion=FP_FUSION)
    assert float((y.double() - torch.sin(x.double())).abs().max()) <= 2e-6


def test_fused_siren_agrees_with_eager_on_cuda():
    """The Triton kernel compiled for the GPU (the CPU tests run its interpreter): the data INR's size and the
    shadow SIREN's, against the eager SIREN on the same device. TF32 rounds the hidden layers' inputs to 10
    mantissa bits; its image PSNR is what scripts/render_plans.py reports (78 dB on an H200)."""
    pytest.importorskip("triton")
    from diffshadow.render.fused import FusedSiren
    from diffshadow.siren import Siren

    for width in (32, 64):
        model = Siren(SirenConfig(width, 2), torch.Generator().manual_seed(width)).to(CUDA)
        x = torch.rand(100_003, 3, generator=torch.Generator().manual_seed(1)).to(CUDA) * 2 - 1
        with torch.no_grad():
            ref = model(x)
        got = FusedSiren(model.named_tensors(), 2)(x)
        assert float((got - ref).abs().max()) <= 2e-2, width


def test_fused_images_agree_with_eager_on_cuda(volume):
    """`inr` and `noshadow` with `render.kernel: fused` (whole primary rays in one compiled kernel) and `naive`'s
    secondary rays likewise, against the eager renderer on the same device. Nothing stops early
    (min_transmittance 0; naive's optical depth bound adds at most 0.9 exp(-10) < 5e-5), so the kernels'
    stopping rule does not enter."""
    pytest.importorskip("triton")
    from diffshadow.siren import Siren

    class DataInr:  # what RenderScene reads of a data INR
        model = Siren(SirenConfig(32, 2), torch.Generator().manual_seed(3))
        cell_lo = cell_hi = None

    siren = (LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0))), LAYOUT, SIREN.blocks)
    for mode in ("noshadow", "inr", "naive"):
        cam = Camera.orbit(volume.extent, azimuth=40, elevation=20, size=32 if mode == "naive" else 96)
        images = []
        for kernel in ("eager", "fused"):
            scene = RenderScene(volume, TF, DataInr(), device=CUDA, networks=Networks(kernel))
            assert scene.networks_used()["used"] == kernel
            images.append(scene.render(mode, cam, light=LIGHTS[1], siren=siren, min_transmittance=0.0).rgb)
        bound = 2e-2 + (5e-5 if mode == "naive" else 0.0)
        assert float((images[0] - images[1]).abs().max()) <= bound, mode


def test_warmed_kernels_leave_the_frames_nothing_to_compile(volume, monkeypatch):
    """render.warm_kernels: `fused.warm` compiles a scene's kernels ahead, all at once (Triton's `warmup` with the
    arguments' dtypes), and the frames of every mode and shading then ask Triton to compile nothing (its
    jit_cache_hook sees no request): the warm-up asked for the launches' own specialisations (pointer alignment,
    integer arguments, constants)."""
    pytest.importorskip("triton")
    knobs = pytest.importorskip("triton.knobs")
    from diffshadow.render import fused
    from diffshadow.siren import Siren

    class DataInr:  # a width no other test renders with, so its kernels are this test's own
        model = Siren(SirenConfig(64, 1), torch.Generator().manual_seed(3))
        cell_lo = cell_hi = None

    requests = []
    monkeypatch.setattr(knobs.runtime, "jit_cache_hook", lambda **kw: requests.append(kw["repr"]))
    siren = (LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0))), LAYOUT, SIREN.blocks)
    scene = RenderScene(volume, TF, DataInr(), device=CUDA, networks=Networks("fused", warm=True))
    variants = scene.kernel_variants(siren)
    assert len(set(variants)) == 5  # the data INR's SIREN, noshadow, naive, inr and the shadow SIREN alone
    # the shadow SIREN's kernel may have launched in a test before: warmed are the ones not yet launched
    fresh = len(set(variants) - fused._LAUNCHED - fused._WARMED)
    assert fresh >= 4 and fused.warm(variants, CUDA) == fresh
    asked = len(requests)
    cam = Camera.orbit(volume.extent, azimuth=40, elevation=20, size=32)
    for mode, phong in (("noshadow", False), ("inr", False), ("naive", False), ("inr", True)):
        scene.render(mode, cam, light=LIGHTS[1], siren=siren, phong=phong)
    assert scene.kernel_used == "fused" and len(requests) == asked, requests[asked:]


def test_deterministic_mode_repeats_bytes(tmp_path):
    """DIFFSHADOW_DETERMINISTIC=1 in a fresh process: two trainings on CUDA give the same bytes."""
    script = tmp_path / "twice.py"
    script.write_text(
        "import sys\nfrom pathlib import Path\nimport torch\n"
        "from diffshadow.runtime import set_deterministic_from_env\n"
        "assert set_deterministic_from_env()\n"
        "sys.path[:0] = [sys.argv[1], str(Path(sys.argv[1]).parent)]\nimport test_cuda as T\n"
        "s = [T.train_diffusion(T._training_data(), T.DCFG, Path(sys.argv[2]) / f'{i}.ckpt', device=T.CUDA,\n"
        "                       log=lambda m: None)['model'] for i in range(2)]\n"
        "assert all(torch.equal(s[0][k], s[1][k]) for k in s[0])\n")
    env = {**os.environ, "DIFFSHADOW_DETERMINISTIC": "1"}
    proc = subprocess.run([sys.executable, str(script), str(Path(__file__).parent), str(tmp_path)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_deterministic_mode_renders_and_sweeps(tmp_path):
    """DIFFSHADOW_DETERMINISTIC=1: every renderer mode and the exact shadows' sweep run on CUDA (torch raises
    for an op without a deterministic kernel, e.g. a floating-point cumsum) and repeat their bytes."""
    script = tmp_path / "render_twice.py"
    script.write_text(
        "import sys\nfrom pathlib import Path\nimport torch\n"
        "from diffshadow.runtime import set_deterministic_from_env\n"
        "assert set_deterministic_from_env()\n"
        "sys.path[:0] = [sys.argv[1], str(Path(sys.argv[1]).parent)]\nimport test_cuda as T\n"
        "from diffshadow.shadow import shadow_grid\n"
        "vol = T.Volume(data=T.gaussian_blob(33, 0.15), extent=T.np.ones(3), name='blob')\n"
        "cam = T.Camera.orbit(vol.extent, azimuth=40, elevation=20, size=32)\n"
        "siren = (T.LAYOUT.flatten(T.init_siren(T.SIREN, torch.Generator().manual_seed(0))), T.LAYOUT, 1)\n"
        "for mode in ('noshadow', 'gt', 'naive', 'inr'):\n"
        "    a, b = (T.RenderScene(vol, T.TF, device=T.CUDA).render(mode, cam, light=T.LIGHTS[1], siren=siren)\n"
        "            for _ in range(2))\n"
        "    assert torch.equal(a.rgb, b.rgb), mode\n"
        "g = [shadow_grid(vol, T.TF, T.LIGHTS[1], method='sweep', device=T.CUDA) for _ in range(2)]\n"
        "assert torch.equal(torch.as_tensor(g[0]), torch.as_tensor(g[1]))\n")
    env = {**os.environ, "DIFFSHADOW_DETERMINISTIC": "1"}
    proc = subprocess.run([sys.executable, str(script), str(Path(__file__).parent)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


def _nccl_worker(rank, port, data, state, ft, out_dir):
    from diffshadow.diffusion.finetune import finetune
    from diffshadow.runtime import distributed

    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE="2", MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    with distributed(CUDA, timeout_s=120) as d:
        result = finetune(state, data, ft, Path(out_dir) / "ddp.ckpt", rank=d.rank, world=d.world, device=d.device,
                          log=lambda m: None)
        if d.rank == 0:
            torch.save(result["model"], Path(out_dir) / "ddp_model.pt")


@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="NCCL DDP needs two GPUs")
def test_one_nccl_ddp_step_equals_one_single_process_step(tmp_path):
    sys.path.insert(0, str(REPO / "tests"))
    import test_finetune as T
    from test_finetune import _free_port

    vol = Volume(data=gaussian_blob(17, 0.3), extent=np.ones(3), name="blob")
    _, _, _, data, state = T.make_setup(vol, tmp_path)
    single = T.finetune(state, data, T.FT, tmp_path / "single.ckpt", device=CUDA, log=lambda m: None)["model"]
    mp.spawn(_nccl_worker, args=(_free_port(), data, state, T.FT, str(tmp_path)), nprocs=2, join=True)
    ddp = torch.load(tmp_path / "ddp_model.pt", weights_only=True, map_location="cpu")
    diff = max(float((single[k].cpu() - ddp[k]).abs().max()) for k in single)
    assert diff <= 1e-6, diff


def test_tiny_workflow_on_cuda_with_finetuning(tmp_path):
    sys.path.insert(0, str(REPO / "tests"))
    from test_workflow import TINY, snakemake

    # evaluate.device: run: eval_truth marches, evaluate_voxels and caches sample, and they and sample_shadows score
    # their SIRENs on the GPU too
    snakemake(tmp_path, config={**TINY, "device": "cuda", "evaluate": {**TINY.get("evaluate", {}), "device": "run"}})
    res = tmp_path / "results/nucleon"
    assert (res / "diffusion.ckpt").exists()  # the fine-tuned model
    assert (res / "voxel_metrics.json").exists()
    assert (res / "image_metrics.json").exists()
    gpu = torch.cuda.get_device_name(CUDA)
    assert open_store(res / "generated.zarr").config["scored_on"] == gpu
    assert {r.get("device") for r in json.loads((res / "caches.json").read_text())["caches"]} == {None, gpu}


def test_peak_memory_on_cuda_is_the_most_bytes_a_call_ever_held():
    """`bench render`'s peak memory on CUDA: 4 + 12 MiB held at once, then 12 + 2 (16 MiB), not counting what was
    allocated before the call."""
    from diffshadow.bench.profile import op_counts, peak_bytes

    def allocate_and_free():
        a = torch.empty(1 << 20, device=CUDA)
        b = torch.empty(3 << 20, device=CUDA)
        del a
        return b, torch.empty(1 << 19, device=CUDA)

    held = torch.empty(1 << 22, device=CUDA)  # noqa: F841 (the caller's, before the call)
    assert peak_bytes(allocate_and_free, CUDA) == 16 << 20
    assert op_counts(allocate_and_free, memory=CUDA)["peak_bytes"] == 16 << 20


@pytest.mark.parametrize("visible", [None, "0", "0,0"])
def test_the_drivers_gpu_count_is_torchs(visible):
    """finetune_render's `ddp-processes` counts the GPUs from the driver, without PyTorch (hpc.visible_nvidia_gpus):
    where it answers, torch.cuda.device_count() in a fresh process with the same CUDA_VISIBLE_DEVICES agrees."""
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    if visible is not None:
        env["CUDA_VISIBLE_DEVICES"] = visible
    code = "import torch; from diffshadow.hpc import visible_nvidia_gpus as v; print(v(), torch.cuda.device_count())"
    ours, torchs = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                  check=True).stdout.split()
    if visible == "0,0":
        assert ours == "None"  # an index twice: only PyTorch can tell
    else:
        assert ours == torchs, (visible, ours, torchs)

"""No host sync inside the inner step of a training loop: a GPU runs ahead of the host only while the host never
waits for a value. Each loop's step is counted as `bench stages` counts it (the loop body itself, through
`diffshadow.bench.stages`), on tiny synthetic inputs; a scalar read, a boolean mask or a `nonzero` added to any of
them fails here."""

from pathlib import Path

import pytest
import torch

from diffshadow.bench.profile import OPTIMIZER_STEP, op_counts
from diffshadow.bench.stages import BUILDERS, bench_stages
from diffshadow.config import merge, run_config, scene_config

REPO = Path(__file__).resolve().parents[1]
TRAINING = ("fit_siren", "preoptimize", "train_data_inr", "train_diffusion", "fit_correction", "finetune_render")
TINY = {"lights": {"count": 6, "unseen": 2}, "subset_size": 6,
        "fit": {"points": 64, "blend_per_light": 2, "blend_points": 32},
        "diffusion": {"presample_points": 64, "pool_lights": 4, "pool_points": 32, "geometry_points": 16,
                      "batch_size": 4, "epochs": 3, "max_epochs": 3},
        "finetune": {"views": 1, "image_size": 16, "pixels": 4, "batch_size": 4, "epochs": 2},
        "data_inr": {"points": 64, "width": 16}}


@pytest.fixture(scope="module")
def tiny():
    return scene_config(run_config(merge({}, TINY), "test"), "nucleon", scenes_dir=REPO / "config/scenes")


@pytest.fixture(scope="module")
def scene(tiny):
    from diffshadow.volume import scene_volume

    return scene_volume(tiny)


@pytest.mark.parametrize("stage", TRAINING)
def test_no_host_sync_inside_a_training_step(tiny, scene, stage):
    timed = BUILDERS[stage](tiny, torch.device("cpu"), *scene)
    timed.step(0)
    counts = op_counts(lambda: timed.step(1), host_scopes=(OPTIMIZER_STEP,))
    assert counts["ops"] > 20 and counts["syncs"] == 0, counts


def test_a_scalar_read_in_a_step_is_counted(tiny, scene):
    """The check can fail: the same step followed by the read the loops used to make (`if not isfinite(loss)`)."""
    timed = BUILDERS["train_data_inr"](tiny, torch.device("cpu"), *scene)

    def step_with_read():
        loss = timed.step(1)
        if not torch.isfinite(loss):
            raise AssertionError
    assert op_counts(step_with_read, host_scopes=(OPTIMIZER_STEP,))["syncs"] == 1


def test_bench_stages_measures_and_projects_every_stage(tiny, tmp_path):
    import json

    out = tmp_path / "stages.json"
    result = bench_stages(tiny, out, device=torch.device("cpu"), budget_s=0.0, warmup=1, max_steps=2,
                          log=lambda *a: None)
    assert json.loads(out.read_text()) == json.loads(json.dumps(result))
    assert set(result["stages"]) == set(BUILDERS)
    for name, row in result["stages"].items():
        assert row["step_s"] > 0 and row["ops"] > 0 and row["steps_timed"] == 2, name
        assert row["projected_s"] == pytest.approx(row["step_s"] * row["steps"]), name
    stages = result["stages"]
    assert stages["fit_siren"]["steps"] == tiny["fit"]["steps"]
    assert stages["train_diffusion"]["steps"] == 2 * 3  # 6 lights in batches of 4, 3 epochs
    assert stages["fit_correction"]["steps"] == tiny["correction"]["steps"]
    # per light, over the 8 training and unseen lights, and for the mix's choice (model share auto) its validation
    # lights as well
    val = tiny["mix"]["val_lights"]
    assert tiny["mix"]["model_share"] == "auto" and val > 0
    for name, lights in (("eval_truth", 8), ("sample_shadows", 8 + val)):
        assert stages[name]["seconds_per_unit"] * lights == pytest.approx(stages[name]["projected_s"]), name
    fixed = bench_stages(merge(tiny, {"mix": {"model_share": 1}}), tmp_path / "alone.json", device=torch.device("cpu"),
                         stages=["sample_shadows"], budget_s=0.0, warmup=1, max_steps=2, log=lambda *a: None)
    row = fixed["stages"]["sample_shadows"]
    assert row["seconds_per_unit"] * 8 == pytest.approx(row["projected_s"])  # the model alone: no choice to make
    with pytest.raises(ValueError, match="bench stages: unknown stage 'fit'"):
        bench_stages(tiny, out, device=torch.device("cpu"), stages=["fit"])


def test_the_bench_help_names_every_stage(capsys):
    from diffshadow.bench.stages import STAGES
    from diffshadow.cli import main

    with pytest.raises(SystemExit):
        main(["bench", "stages", "--help"])
    assert f"default: all ({' '.join(STAGES)})" in " ".join(capsys.readouterr().out.split())


def test_sampling_reads_the_host_once_per_batch_not_per_step():
    """DDIM keeps its finiteness check on the device: 2 and 20 steps read the host equally often."""
    from diffshadow.diffusion.model import PRESETS, WeightTransformer
    from diffshadow.diffusion.sample import generate
    from diffshadow.diffusion.standardize import Standardizer
    from diffshadow.siren import SirenConfig, WeightLayout

    layout = WeightLayout.for_siren(SirenConfig(8, 1))
    model = WeightTransformer(layout, PRESETS["tiny"]).eval()
    std = Standardizer.fit(layout, torch.randn(4, layout.n_params, generator=torch.Generator().manual_seed(0)),
                           "param")
    lights = [[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]]
    syncs = [op_counts(lambda n=n: generate(model, std, lights, steps=n, temperature=1.0))["syncs"] for n in (2, 20)]
    assert syncs[0] == syncs[1] <= 3, syncs


class HostTraffic(torch.utils._python_dispatch.TorchDispatchMode):
    """Counts, under it, tensors copied from the host onto the "meta" device (and of them, those copied blocking:
    on CUDA, PyTorch synchronizes the stream for one) and scalars read back: on a real device, what a CUDA graph
    cannot capture, and what keeps the host from running ahead."""

    def __init__(self):
        super().__init__()
        self.copies = self.blocking = self.reads = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is torch.ops.aten._to_copy.default and args[0].device.type == "cpu" \
                and str(kwargs.get("device")) == "meta":
            self.copies += 1
            self.blocking += not kwargs.get("non_blocking", False)
        if func is torch.ops.aten._local_scalar_dense.default:
            self.reads += 1
        return func(*args, **kwargs)


def test_a_geometry_step_copies_nothing_from_the_host_after_its_first(tiny, scene):
    """What `diffusion.cuda_graph` captures (loss, backward, gradient clip; AdamW is torch's own `capturable`),
    run on the "meta" device, where every tensor moved from the host shows as a copy: the first step moves the
    schedule's and the standardizer's tables once, later steps move nothing and read nothing back (six copies a
    step before the tables were kept on the device). Its eight draws are copied without blocking (on CUDA, eight
    stream syncs a step before `sampling.to_device`). A copy made inside, and a blocking one, are counted."""
    from diffshadow.bench.stages import _training_data
    from diffshadow.diffusion.config import build_model
    from diffshadow.diffusion.schedule import Schedule
    from diffshadow.diffusion.standardize import Standardizer
    from diffshadow.diffusion.train import batch_loss, draw_batch
    from diffshadow.sampling import to_device

    meta = torch.device("meta")
    dcfg, data = _training_data(tiny, scene[0], meta)
    model = build_model(data.layout, dcfg).to(meta)
    std = Standardizer.fit(data.layout, data.weights, dcfg.standardize)
    z_all, on_meta, schedule = std.standardize(data.weights).float().to(meta), data.to(meta), Schedule()

    def step(i: int, extra: bool = False):
        gen = torch.Generator().manual_seed(i)
        with (drawn := HostTraffic()):  # the batch's draws, made on the host: copied, but never blocking
            batch = draw_batch(gen, to_device(torch.arange(dcfg.batch_size), meta), on_meta, on_meta.pool, dcfg,
                               schedule.steps, meta)
        assert drawn.copies == 8 and drawn.blocking == 0, (drawn.copies, drawn.blocking)
        with (traffic := HostTraffic()):
            loss = batch_loss(model, std, on_meta, z_all, on_meta.pool, batch, dcfg, schedule)[0]
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), dcfg.grad_clip)
            if extra:
                loss = loss + torch.ones(()).to(meta)
        return traffic.copies, traffic.reads

    assert step(0)[0] > 0
    assert step(1) == (0, 0)
    assert step(2, extra=True) == (1, 0)
    with (plain := HostTraffic()):
        torch.ones(3).to(meta)
    assert plain.blocking == 1


def test_the_samplers_draw_their_noise_without_blocking():
    """DDPM draws fresh noise on the host at each of its 500 steps, and DDIM with eta > 0 at each of its steps (the
    same numbers on every device): on the "meta" device every draw shows as a copy, none of them blocking (a
    blocking copy synchronizes the stream on CUDA: 500 waits for the GPU a DDPM sample before), none read back."""
    from diffshadow.diffusion.schedule import Schedule

    meta, schedule = torch.device("meta"), Schedule()

    def denoise(x, t):
        return 0.5 * x

    with (ddpm := HostTraffic()):
        schedule.ddpm_sample(denoise, (2, 8), generator=torch.Generator().manual_seed(0), device=meta)
    with (ddim := HostTraffic()):
        schedule.ddim_sample(denoise, (2, 8), steps=10, eta=1.0, generator=torch.Generator().manual_seed(0),
                             device=meta)
    assert (ddpm.copies, ddpm.blocking, ddpm.reads) == (500, 0, 0)
    assert (ddim.copies, ddim.blocking, ddim.reads) == (10, 0, 0)


class _NoOptimizer:
    """Adam's place in a step counted on the "meta" device: Adam is torch's own `capturable` on CUDA."""

    param_groups = ({"lr": 0.0},)

    def zero_grad(self, set_to_none: bool = True) -> None:
        pass

    def step(self) -> None:
        pass


@pytest.mark.parametrize("store", ["grids", "table"])
def test_a_fit_update_copies_nothing_from_the_host_and_reads_nothing(tiny, scene, store):
    """What `fit.cuda_graph` captures (`SubsetFit.update`: the targets' lookup, the SIRENs' forward and backward,
    the blend loss), run on the "meta" device: nothing copied from the host, nothing read back. The step's draws
    (the shared points, the pool lights and their points; from a table, the targets too) are copied before it,
    without blocking."""
    cfg = merge(tiny, {"fit": {"target_store": store}})
    run = BUILDERS["fit_siren"](cfg, torch.device("cpu"), *scene).step.__self__
    assert run.pool is not None and (run.targets.grids is not None) == (store == "grids") and run.cfg.shared_points
    if store == "table":
        run.targets.table_from(1, run.sampler)  # made on the host, as on a GPU, before the device turns meta
    meta = torch.device("meta")
    run.weights = run.weights.detach().to(meta).requires_grad_(True)
    if store == "grids":
        run.targets.grids = run.targets.grids.to(meta)
    run.targets.extent = run.targets.extent.to(meta)
    run.pool, run.opt, run.device = run.pool.to(meta), _NoOptimizer(), meta
    with (drawn := HostTraffic()):
        draw = run.draw(1)
    assert (drawn.copies, drawn.blocking) == (3 if store == "grids" else 4, 0)
    assert draw.pts.shape == (run.k, run.cfg.points, 3) and draw.pts.device == meta
    run.update(draw)  # the first moves the SIREN layout's scales, once per device (`siren.layout_scales`)
    with (traffic := HostTraffic()):
        per_siren = run.update(draw)
    assert per_siren.shape == (run.k,)
    assert (traffic.copies, traffic.reads) == (0, 0)


def test_a_data_inr_step_never_blocks_on_its_points_and_its_update_copies_nothing(tiny, scene):
    """The data INR's step draws its points (box, visible and error-driven) on the host and copies them once,
    without blocking (on CUDA a blocking copy from ordinary host memory waits for the previous step's kernels),
    and reads nothing back between the error sampler's rescorings; its update, what `data_inr.cuda_graph`
    captures, copies nothing from the host and reads nothing. Counted on the "meta" device."""
    from diffshadow.data_inr import DataInrConfig, DataInrFit

    run = DataInrFit(*scene, DataInrConfig.from_config(tiny["data_inr"]), device=torch.device("cpu"))
    assert run.hard is not None and 1 % run.hard.every != 0  # step 1 draws error points without rescoring
    run.hard.score(run.model, torch.device("cpu"))  # as at step 0
    meta = torch.device("meta")
    run.model, run.grid, run.extent = run.model.to(meta), run.grid.to(meta), run.extent.to(meta)
    run.opt, run.device = _NoOptimizer(), meta
    with (traffic := HostTraffic()):
        loss = run.step(1)
    assert loss.shape == () and (traffic.copies, traffic.blocking, traffic.reads) == (1, 0, 0)
    with (drawn := HostTraffic()):
        draw = run.draw(2)
    with (traffic := HostTraffic()):
        run.update(draw)
    assert (drawn.copies, drawn.blocking, traffic.copies, traffic.reads) == (1, 0, 0, 0)


def test_the_fit_bench_times_a_subset_with_the_halo_it_fits(tiny, scene):
    """With several subsets, a fit job fits its halo too (`fit.halo`): the bench's step covers the subset's lights
    and the mean halo of the config's own light set, the part of it held at stored SIRENs (`fit.rounds`) in the
    blend loss only, and counts only the subset's as its SIRENs."""
    import numpy as np

    from diffshadow.fit import FitConfig
    from diffshadow.lights import make_light_sets
    from diffshadow.seams import halo_size

    cfg = merge(tiny, {"lights": {"count": 24, "sphere": 96}, "subset_size": 8})
    timed = BUILDERS["fit_siren"](cfg, torch.device("cpu"), *scene)
    sets = make_light_sets(96, 24, cfg["lights"]["center"], 2, cfg["lights"]["seed"], cfg["lights"]["layout"])
    train = np.asarray(sets["train"]["cartesian"])
    fitted, held = (round(n) for n in halo_size(train, sets["center"], 8, FitConfig.from_config(cfg["fit"])))
    run = timed.step.__self__
    assert fitted > 0 and held > 0 and run.k == 8 + fitted and len(run.held) == held and timed.units == 8
    assert f"3 jobs of up to 8 lights and a halo of {fitted} fitted and {held} held" in timed.note
    off = FitConfig.from_config({**cfg["fit"], "rounds": False})
    assert halo_size(train, sets["center"], 8, off)[1] == 0  # without rounds the whole halo is fitted
    apart = BUILDERS["fit_siren"](merge(cfg, {"fit": {"rounds": False}}), torch.device("cpu"), *scene)
    assert apart.step.__self__.k == 8 + round(halo_size(train, sets["center"], 8, off)[0])
    assert apart.step.__self__.held is None
    off = BUILDERS["fit_siren"](merge(cfg, {"fit": {"halo": 0}}), torch.device("cpu"), *scene)
    assert off.step.__self__.k == 8 and "halo" not in off.note

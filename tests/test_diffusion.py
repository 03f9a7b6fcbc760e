import dataclasses
import itertools

import numpy as np
import pytest
import torch
from conftest import default_device_meta

from diffshadow.diffusion.config import DiffusionConfig, DiffusionError
from diffshadow.diffusion.geometry import geometry_error
from diffshadow.diffusion.model import WeightTransformer
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.schedule import Schedule
from diffshadow.diffusion.standardize import Standardizer
from diffshadow.diffusion.train import TrainingData, train_diffusion
from diffshadow.lights import LightError, PoolLights
from diffshadow.siren import BatchedSiren, Siren, SirenConfig, WeightLayout, box_to_siren, init_siren

SIREN = SirenConfig(8, 1)
LAYOUT = WeightLayout.for_siren(SIREN)


def weights(n=6, seed=0):
    gen = torch.Generator().manual_seed(seed)
    base = LAYOUT.flatten(init_siren(SIREN, gen))
    return base + 0.01 * torch.randn(n, LAYOUT.n_params, generator=gen)


@pytest.mark.parametrize("mode", ["token", "param"])
def test_standardize_round_trip_is_exact(mode):
    w = weights() * torch.logspace(-3, 2, LAYOUT.n_params)  # tiny and huge scales
    std = Standardizer.fit(LAYOUT, w, mode)
    back = std.destandardize(std.standardize(w)).float()
    assert torch.equal(back, w)


@pytest.mark.parametrize("mode", ["token", "param"])
def test_zero_variance_tensor_gives_no_nan(mode):
    w = weights()
    w[:, :24] = 0.5  # first.weight constant across lights and within the tensor
    std = Standardizer.fit(LAYOUT, w, mode)
    z = std.standardize(w)
    assert torch.isfinite(z).all() and torch.isfinite(std.std).all()
    assert torch.equal(std.destandardize(z).float(), w)


def test_geometry_loss_batched_equals_one_by_one():
    w = weights(4)
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(4, 50, 3, generator=gen)
    vals = torch.rand(4, 50, generator=gen)
    extent = torch.ones(3)
    batched = geometry_error(w, LAYOUT, SIREN, pts, vals, extent).mean().detach()
    with torch.no_grad():
        separate = torch.stack([((Siren.from_flat(w[i], LAYOUT)(box_to_siren(pts[i], extent)) - vals[i]) ** 2)
                                .mean() for i in range(4)]).mean()
    assert abs(float(batched) - float(separate)) < 1e-6


def test_transformer_shapes_and_light_sensitivity():
    from diffshadow.diffusion.model import PRESETS
    model = WeightTransformer(LAYOUT, PRESETS["tiny"])
    for p in model.token_out:  # leave the zero init so the output depends on the input
        torch.nn.init.normal_(p.weight, std=0.02)
    x = torch.randn(3, LAYOUT.n_params)
    t = torch.tensor([0, 250, 499])
    a = model(x, t, torch.tensor([[0.0, 0, 1]] * 3))
    b = model(x, t, torch.tensor([[1.0, 0, 0]] * 3))
    assert a.shape == (3, LAYOUT.n_params) and not torch.allclose(a, b)


def test_wide_tensors_split_into_tokens_that_cover_them_and_the_model_maps_them_back():
    import dataclasses

    from diffshadow.diffusion.config import build_model
    from diffshadow.diffusion.model import PRESETS, token_sizes
    assert token_sizes([96, 32, 1024, 1], 1, 192) == [96, 32, 1024, 1]
    assert token_sizes([96, 32, 1024, 1], 4, 192) == [96, 32, 256, 256, 256, 256, 1]  # only tensors wider than 192
    assert token_sizes([1025, 3], 3, 2) == [342, 342, 341, 1, 1, 1]  # near-equal chunks
    cfg = dataclasses.replace(PRESETS["tiny"], n_embd=16, tensor_tokens=4)
    model = WeightTransformer(LAYOUT, cfg)
    assert sum(model.sizes) == LAYOUT.n_params and max(model.sizes) == 16 < max(LAYOUT.sizes)
    assert model.pos.shape[1] == len(model.sizes) + 2
    for p in model.token_out:
        torch.nn.init.normal_(p.weight, std=0.02)
    x = torch.randn(2, LAYOUT.n_params)
    out = model(x, torch.tensor([0, 9]), torch.tensor([[0.0, 0, 1]] * 2))
    assert out.shape == x.shape and torch.isfinite(out).all()
    # the config's tensor_tokens reaches the model; a checkpoint from before it existed had one token per tensor
    assert build_model(LAYOUT, dataclasses.replace(CFG, tensor_tokens=4)).cfg.tensor_tokens == 4
    old = {k: v for k, v in dataclasses.asdict(CFG).items() if k != "tensor_tokens"}
    assert DiffusionConfig.of_checkpoint({"config": old}).tensor_tokens == 1
    assert DiffusionConfig.of_checkpoint({"config": {**old, "tensor_tokens": 4}}).tensor_tokens == 4


def per_token_reference(model: WeightTransformer, x, t, light) -> torch.Tensor:
    """The model as the paper writes it: each token through its own linear map, one after another."""
    from diffshadow.diffusion.model import light_encoding, timestep_embedding
    tokens = [proj(p) for proj, p in zip(model.token_in, x.split(model.sizes, dim=1), strict=True)]
    tokens.append(model.time_mlp(timestep_embedding(t, model.cfg.n_embd)))
    tokens.append(model.light_in(light_encoding(light, model.cfg.light_freqs)))
    h = torch.stack(tokens, dim=1) + model.pos
    for block in model.blocks:
        h = block(h)
    h = model.ln_f(h)
    return torch.cat([proj(h[:, i]) for i, proj in enumerate(model.token_out)], dim=1)


@pytest.mark.parametrize("batch", [1, 5])
def test_batched_token_maps_are_each_tokens_own_linear_map(batch):
    """Tokens of one size share a batched product: the same outputs and gradients as a linear map per token (to
    float32 rounding: another summation order), and the checkpoint keeps one map per token. A gradient entry that
    sums terms of both signs can differ by more than 1e-4 of itself, so each tensor is compared at its own scale:
    over 400 random models (1 and 2 threads) the largest difference was 4e-6 of the tensor's largest entry, and
    2.5-5 % of those models failed an entry-by-entry rtol of 1e-4 (the whole suite once drew one: its global
    random state seeded the model)."""
    from diffshadow.diffusion.model import PRESETS
    cfg = dataclasses.replace(PRESETS["tiny"], n_embd=16, tensor_tokens=4)
    with torch.random.fork_rng():
        torch.manual_seed(0)
        model = WeightTransformer(LAYOUT, cfg)
        for p in model.token_out:
            torch.nn.init.normal_(p.weight, std=0.02)
    assert len({s for s, _ in model.groups}) < len(model.sizes)  # some sizes repeat: batched products do occur
    gen = torch.Generator().manual_seed(0)
    x, light = torch.randn(batch, LAYOUT.n_params, generator=gen), torch.randn(batch, 3, generator=gen)
    t = torch.randint(0, 500, (batch,), generator=gen)
    grads = []
    for forward in (model, lambda *a: per_token_reference(model, *a)):
        model.zero_grad(set_to_none=True)
        out = forward(x, t, light)
        (out * torch.linspace(-1, 1, out.numel()).view(out.shape)).sum().backward()
        grads.append((out.detach(), [p.grad for p in model.parameters()]))
    (a, ga), (b, gb) = grads
    assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
    assert all(float((u - v).abs().max()) <= 1e-5 * float(v.abs().max()) for u, v in zip(ga, gb, strict=True))
    keys = model.state_dict().keys()
    assert {f"token_in.{i}.weight" for i in range(len(model.sizes))} <= keys and not any("_cols" in k for k in keys)


def test_ema_update_is_a_lerp_of_each_parameter_bit_for_bit():
    from diffshadow.diffusion.model import PRESETS
    from diffshadow.diffusion.train import Ema, ema_decay
    model = WeightTransformer(LAYOUT, PRESETS["tiny"])
    ema = Ema(model, 0.995)
    expected = [p.detach().clone() for p in ema.model.parameters()]
    gen = torch.Generator().manual_seed(1)
    for step in range(3):
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn(p.shape, generator=gen))
        expected = [e.lerp(p.detach(), 1 - ema_decay(0.995, step)) for e, p in zip(expected, model.parameters(),
                                                                                strict=True)]
        ema.update(model, step)
    assert all(torch.equal(e, p) for e, p in zip(expected, ema.model.parameters(), strict=True))


def test_a_non_finite_sample_names_its_first_timestep():
    """The finiteness of x0 is read once per batch, after sampling: the error still names the first bad timestep."""
    from diffshadow.diffusion.model import PRESETS
    model = WeightTransformer(LAYOUT, PRESETS["tiny"]).eval()
    forward = model.forward
    model.forward = lambda x, t, light: forward(x, t, light) + torch.where(t[:, None] < 300, torch.nan, 0.0)
    std = Standardizer.fit(LAYOUT, weights(4), "param")
    first = next(t for t in Schedule().ddim_timesteps(10) if t < 300)
    with pytest.raises(DiffusionError, match=rf"x0 is not finite at timestep {first} \(torch.float32, lights 0..1\)"):
        generate(model, std, [[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]], steps=10)


def test_schedule_edges_and_ddim_steps():
    s = Schedule()
    assert s.steps == 500 and abs(float(s.betas[0]) - 1e-4) < 1e-12 and abs(float(s.betas[-1]) - 2e-2) < 1e-12
    x0 = torch.randn(2, 5)
    assert torch.allclose(s.q_sample(x0, torch.tensor([0, 0]), torch.zeros(2, 5)), x0 * s.alpha_bar[0].sqrt().float())
    assert s.ddim_timesteps(1) == [499] and s.ddim_timesteps(500) == list(range(499, -1, -1))
    with pytest.raises(ValueError, match=r"DDIM steps: expected 1..500, got 0"):
        s.ddim_timesteps(0)


def tiny_data(n=4):
    gen = torch.Generator().manual_seed(2)
    return TrainingData(weights=weights(n), lights=torch.nn.functional.normalize(torch.randn(n, 3, generator=gen)),
                        points=torch.rand(n, 64, 3, generator=gen), values=torch.rand(n, 64, generator=gen),
                        extent=torch.ones(3), layout=LAYOUT, siren=SIREN,
                        check=(torch.rand(48, 3, generator=gen), torch.rand(n, 48, generator=gen)))


# float32 products on every CPU ("auto" is bfloat16 on some): the tests' exact values are float32's
CFG = DiffusionConfig.from_config(dict(preset="tiny", epochs=6, batch_size=2, geometry_points=16, checkpoint_every=2,
                      lr_step_epochs=2, ema=0.9, pool_lights=0, target_gap=0.0, precision="float32"))


def test_ema_decay_warms_up_to_its_target():
    from diffshadow.diffusion.train import ema_decay
    decays = [ema_decay(0.995, step) for step in range(5000)]
    assert decays[0] == 0.1  # the first average is mostly the trained weights, not the initial ones
    assert all(a <= b for a, b in itertools.pairwise(decays)) and max(decays) == 0.995
    assert ema_decay(0.5, 0) == 0.1 and ema_decay(0.5, 100) == 0.5


def test_resume_matches_uninterrupted(tmp_path):
    data = tiny_data()
    full = train_diffusion(data, CFG, tmp_path / "a.ckpt", log=lambda *a: None)
    train_diffusion(data, CFG, tmp_path / "b.ckpt", log=lambda *a: None, stop_after_epoch=4)
    msgs = []
    resumed = train_diffusion(data, CFG, tmp_path / "b.ckpt", log=msgs.append)
    assert any(m.startswith("resuming from") and "epoch 4/6" in m for m in msgs)
    for key in ("model", "ema"):
        for name, value in full[key].items():
            assert torch.equal(value, resumed[key][name]), name


def test_cuda_graph_off_cuda_steps_eagerly_to_the_same_bytes_and_the_same_fingerprint(tmp_path):
    """`diffusion.cuda_graph` on a CPU: "auto" (the default) steps eagerly without a word; True says that the steps
    run eagerly, and they train the same bytes. The checkpoint records what was done (no graph), and its
    fingerprint leaves that (and `precision`) out at the old behaviour: a default run's fingerprint is the one
    computed before either key existed, so its checkpoints resume across the upgrade."""
    import hashlib
    import json

    from diffshadow.graphs import StepGraphs

    data = tiny_data()
    msgs = []
    plain_msgs = []
    assert CFG.cuda_graph == "auto"
    plain = train_diffusion(data, CFG, tmp_path / "a.ckpt", log=plain_msgs.append)
    assert not any("cuda_graph" in m for m in plain_msgs), plain_msgs
    graphed = train_diffusion(data, dataclasses.replace(CFG, cuda_graph=True), tmp_path / "b.ckpt", log=msgs.append)
    assert "diffusion.cuda_graph: CUDA graphs need a CUDA device; stepping eagerly on cpu" in msgs
    for key in ("model", "ema"):
        assert all(torch.equal(plain[key][k], graphed[key][k]) for k in plain[key])
    assert plain["config"]["cuda_graph"] is graphed["config"]["cuda_graph"] is False
    assert graphed["fingerprint"] == plain["fingerprint"]
    before = hashlib.sha256()
    for t in (data.weights, data.lights, data.points, data.values):
        before.update(t.numpy().tobytes())
    old_config = {k: v for k, v in dataclasses.asdict(CFG).items() if k not in ("precision", "cuda_graph")}
    before.update(json.dumps(old_config, sort_keys=True).encode())
    assert plain["fingerprint"] == before.hexdigest()
    with pytest.raises(ValueError, match="CUDA graphs: expected a CUDA device, got cpu"):
        StepGraphs(torch.device("cpu"))


GROWING = dataclasses.replace(CFG, epochs=2, target_gap=1.0, max_epochs=10)


def test_seen_gap_is_zero_for_a_model_that_returns_the_stage1_weights():
    from diffshadow.diffusion.standardize import Standardizer
    from diffshadow.diffusion.train import seen_gap_db
    from diffshadow.siren import box_to_siren
    data = tiny_data()
    # the true shadow at the check points: the stage-1 SIRENs' own values, off by a little (stage 1 at 40 dB)
    points = data.check[0].expand(len(data.weights), -1, -1)
    exact = BatchedSiren(data.weights, LAYOUT, SIREN.blocks)(box_to_siren(points, data.extent)).detach()
    data.check = (data.check[0], exact + 0.01 * torch.randn(exact.shape, generator=torch.Generator().manual_seed(0)))
    std = Standardizer.fit(data.layout, data.weights, "param")
    z = std.standardize(data.weights).float()

    class Oracle(torch.nn.Module):  # x0 = the stage-1 weights of the light asked for (+ shift std units)
        def __init__(self, shift=0.0):
            super().__init__()
            self.shift = shift

        def forward(self, x, t, light):
            rows = (light @ data.lights.T).argmax(1)
            return z[rows] + self.shift

    assert seen_gap_db(Oracle(), std, data, CFG) == pytest.approx(0.0, abs=1e-4)
    assert seen_gap_db(Oracle(5.0), std, data, CFG) > 3.0  # worse generated SIRENs: a positive gap


def test_training_goes_on_while_the_seen_gap_is_over_its_target_and_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    import diffshadow.diffusion.train as train
    gaps = iter([3.0, 2.0, 0.5])
    monkeypatch.setattr(train, "seen_gap_db", lambda *a: next(gaps))
    msgs = []
    state = train_diffusion(tiny_data(), GROWING, tmp_path / "a.ckpt", log=msgs.append)
    g = state["growth"]
    assert state["epoch"] == g["epochs"] == 6 and g["finished"]  # checks at 2, 4 (every 2 epochs), 6: met
    assert [c["epoch"] for c in g["checks"]] == [2, 4, 6] and "within the target 1 dB" in g["reason"]
    assert any("epoch 2: generated seen lights 3.00 dB under stage 1" in m and "training on" in m for m in msgs)
    # interrupted after the check at epoch 4, resumed: the same checks, the same weights
    gaps = iter([3.0, 2.0, 0.5])
    train_diffusion(tiny_data(), GROWING, tmp_path / "b.ckpt", log=lambda *a: None, stop_after_epoch=4)
    resumed = train_diffusion(tiny_data(), GROWING, tmp_path / "b.ckpt", log=lambda *a: None)
    assert resumed["growth"] == g
    assert all(torch.equal(state["ema"][k], resumed["ema"][k]) for k in state["ema"])


def test_growth_trains_at_the_lr_reached_at_epochs(tmp_path, monkeypatch):
    import diffshadow.diffusion.train as train
    it = iter([5.0, 4.0, 3.0, 2.0, 0.5])
    monkeypatch.setattr(train, "seen_gap_db", lambda *a: next(it))
    state = train_diffusion(tiny_data(), GROWING, tmp_path / "a.ckpt", log=lambda *a: None)
    assert state["epoch"] == 10
    # StepLR every lr_step_epochs=2: decayed once by epoch 2, then held while the gap closes
    assert state["optimizer"]["param_groups"][0]["lr"] == GROWING.lr * GROWING.lr_gamma


def test_a_run_that_stops_over_the_target_keeps_its_best_checked_weights(tmp_path, monkeypatch):
    import diffshadow.diffusion.train as train
    gaps, seen = [3.0, 2.0, 2.5, 2.4, 2.3], []  # best at epoch 4; plateau after three checks gaining < 0.1 dB

    def scripted(model, *a):
        seen.append({k: v.clone() for k, v in model.state_dict().items()})
        return gaps[len(seen) - 1]
    monkeypatch.setattr(train, "seen_gap_db", scripted)
    msgs = []
    state = train_diffusion(tiny_data(), GROWING, tmp_path / "a.ckpt", log=msgs.append)
    g = state["growth"]
    assert state["epoch"] == g["epochs"] == 10 and g["kept_epoch"] == 4 and state["best"] is None
    assert "kept the model of epoch 4 (2.00 dB under stage 1)" in g["reason"]
    assert all(torch.equal(state["ema"][k], seen[1][k]) for k in seen[1])  # the weights checked at epoch 4
    assert not all(torch.equal(state["ema"][k], seen[-1][k]) for k in seen[-1])
    assert any(m.startswith("WARNING: geometry stage done at epoch 10") for m in msgs)
    # interrupted after the check at epoch 8 (best in the checkpoint), resumed: the same weights kept
    seen.clear()
    train_diffusion(tiny_data(), GROWING, tmp_path / "b.ckpt", log=lambda *a: None, stop_after_epoch=8)
    assert torch.load(tmp_path / "b.ckpt", weights_only=False)["best"]["epoch"] == 4
    resumed = train_diffusion(tiny_data(), GROWING, tmp_path / "b.ckpt", log=lambda *a: None)
    assert resumed["growth"] == g and all(torch.equal(state["ema"][k], resumed["ema"][k]) for k in state["ema"])


@pytest.mark.parametrize("gaps, epochs, reason", [
    ([0.9], 2, "within the target"),  # met at `epochs`: no extra cost
    ([-0.2], 2, "0.20 dB over stage 1, within the target"),  # generated better than stage 1: no "-0.20 under"
    ([5.0, 4.5, 4.0, 3.5, 3.0], 10, "reached diffusion.max_epochs 10"),
    ([5.0] * 4, 8, "stopped closing"),
    ([2.0, 1.95, 1.93, 1.92], 8, "stopped closing"),  # the last 3 gained < 0.1 dB on the best before them
    ([3.0, 2.0, 1.95, 1.93, 1.85], 10, "reached diffusion.max_epochs"),
])
def test_training_stops_growing_on_target_cap_or_plateau(tmp_path, monkeypatch, gaps, epochs, reason):
    import diffshadow.diffusion.train as train
    it = iter(gaps)
    monkeypatch.setattr(train, "seen_gap_db", lambda *a: next(it))
    msgs = []
    state = train_diffusion(tiny_data(), GROWING, tmp_path / "a.ckpt", log=msgs.append)
    assert state["growth"]["epochs"] == state["epoch"] == epochs and reason in state["growth"]["reason"]
    assert any(m.startswith("WARNING: geometry stage done") for m in msgs) == (gaps[-1] > 1.0)


def test_the_gap_needs_held_out_check_points(tmp_path):
    data = tiny_data()
    data.check = None
    with pytest.raises(DiffusionError, match="target_gap needs held-out check points .* rerun presample"):
        train_diffusion(data, GROWING, tmp_path / "a.ckpt", log=lambda *a: None)
    train_diffusion(data, CFG, tmp_path / "b.ckpt", log=lambda *a: None)  # target_gap 0: not needed


def test_a_non_finite_gap_stops_with_a_clear_error(tmp_path, monkeypatch):
    import diffshadow.diffusion.train as train
    monkeypatch.setattr(train, "seen_gap_db", lambda *a: float("nan"))
    # no checkpoint was written by epoch 2 (it used to say "the last good checkpoint ... (epoch None)")
    with pytest.raises(DiffusionError, match=r"PSNR is not finite at epoch 2 .* keeping no checkpoint \(none"):
        train_diffusion(tiny_data(), GROWING, tmp_path / "a.ckpt", log=lambda *a: None)


def test_a_zero_target_gap_trains_exactly_epochs_without_measuring(tmp_path, monkeypatch):
    import diffshadow.diffusion.train as train
    monkeypatch.setattr(train, "seen_gap_db", lambda *a: pytest.fail("measured"))
    state = train_diffusion(tiny_data(), CFG, tmp_path / "a.ckpt", log=lambda *a: None)
    assert state["epoch"] == CFG.epochs and state["growth"]["checks"] == []
    assert state["growth"]["reason"] == "fixed length (diffusion.target_gap is 0)"


def test_growth_makes_no_tensor_on_the_implicit_default_device(tmp_path):
    data, cfg = tiny_data(), dataclasses.replace(GROWING, max_epochs=4)
    plain = train_diffusion(data, cfg, tmp_path / "a.ckpt", log=lambda *a: None)
    with default_device_meta():
        guarded = train_diffusion(data, cfg, tmp_path / "b.ckpt", device="cpu", log=lambda *a: None)
    assert guarded["growth"] == plain["growth"] and len(plain["growth"]["checks"]) >= 1


def test_nan_loss_stops_and_keeps_the_checkpoint(tmp_path, monkeypatch):
    import diffshadow.diffusion.train as train
    calls = []

    def failing(*args):
        calls.append(1)
        err = geometry_error(*args)
        return err * float("nan") if len(calls) == 7 else err  # epoch 3 (2 batches per epoch)

    monkeypatch.setattr(train, "_geometry_error", failing)
    ckpt = tmp_path / "c.ckpt"
    with pytest.raises(DiffusionError, match=r"loss became nan at epoch 3; keeping the last good checkpoint "
                                             r".*c.ckpt \(epoch 2\)"):
        train_diffusion(tiny_data(), CFG, ckpt, log=lambda *a: None)
    state = torch.load(ckpt, weights_only=False)
    assert state["epoch"] == 2
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def test_sampling_is_deterministic_and_checks_directions(tmp_path):
    state = train_diffusion(tiny_data(), CFG, tmp_path / "d.ckpt", log=lambda *a: None)
    model, std, layout, siren = load_sampler(state)
    lights = np.array([[0.0, 0.0, 1.0], [0.3, 0.2, 0.9]])  # the second was never trained on: allowed
    a = generate(model, std, lights, steps=5, seed=3)
    assert torch.equal(a, generate(model, std, lights, steps=5, seed=3))
    assert torch.isfinite(a).all() and a.shape == (2, layout.n_params)
    ddpm = generate(model, std, lights[:1], method="ddpm", seed=0)
    assert torch.isfinite(BatchedSiren(ddpm, layout, siren.blocks)(torch.rand(1, 10, 3))).all()
    with pytest.raises(LightError, match="light 1: must be non-zero"):
        generate(model, std, [[0, 0, 1], [0, 0, 0]])
    with pytest.raises(LightError, match="light 0: must be finite"):
        generate(model, std, [[np.nan, 0, 1]])
    # the denoiser's CUDA graphs (the default) are CUDA's alone: on a CPU none is made, and either setting gives the
    # same bytes (tests/gpu/test_cuda.py holds the graphs to eager sampling on CUDA)
    from diffshadow.diffusion import sample

    assert torch.equal(a, generate(model, std, lights, steps=5, seed=3, cuda_graph=False))
    assert model not in sample._GRAPHS


def test_training_and_sampling_make_no_tensor_on_the_implicit_default_device(tmp_path):
    """Guard for the CUDA path (see conftest.default_device_meta): the same bytes with the default device
    "meta" as without, so every tensor is made on a named device."""
    data = tiny_data()
    state = train_diffusion(data, CFG, tmp_path / "a.ckpt", log=lambda *a: None)
    model, std, _, _ = load_sampler(state)
    lights = np.array([[0.0, 0.0, 1.0], [0.3, 0.2, 0.9]])
    with default_device_meta():
        guarded = train_diffusion(data, CFG, tmp_path / "b.ckpt", device="cpu", log=lambda *a: None)
        g_model, g_std, _, _ = load_sampler(guarded, "cpu")
        ddim = generate(g_model, g_std, lights, steps=5, seed=3, device="cpu")
        ddpm = generate(g_model, g_std, lights[:1], method="ddpm", seed=0, device="cpu")
    assert all(torch.equal(state["model"][k], guarded["model"][k]) for k in state["model"])
    assert torch.equal(ddim, generate(model, std, lights, steps=5, seed=3))
    assert torch.equal(ddpm, generate(model, std, lights[:1], method="ddpm", seed=0))


def pooled(data, n=3):
    """`data` with `n` pool lights: each the blend of two training lights, with its own points and values."""
    gen = torch.Generator().manual_seed(5)
    lights = torch.nn.functional.normalize(data.lights[:n] + data.lights[1:n + 1])
    idx = torch.stack([torch.arange(n), torch.arange(1, n + 1)], 1)
    data.pool = PoolLights(lights=lights, points=torch.rand(n, 32, 3, generator=gen),
                           values=torch.rand(n, 32, generator=gen), neighbours=idx, blend=torch.full((n, 2), 0.5))
    return data


POOLED = dataclasses.replace(CFG, pool_lights=3, pool_x0_weight=0.1)


def test_pool_lights_are_trained_recorded_and_guarded(tmp_path):
    data = pooled(tiny_data())
    plain = train_diffusion(data, CFG, tmp_path / "a.ckpt", log=lambda *a: None)  # pool_lights 0: ignored
    assert plain["pool_lights"] == [] and plain["fingerprint"] == train_diffusion(
        tiny_data(), CFG, tmp_path / "b.ckpt", log=lambda *a: None)["fingerprint"]
    state = train_diffusion(data, POOLED, tmp_path / "c.ckpt", log=lambda *a: None)
    assert np.allclose(state["pool_lights"], data.pool.lights.numpy())
    assert state["fingerprint"] != plain["fingerprint"]
    assert not all(torch.equal(state["model"][k], plain["model"][k]) for k in state["model"])
    with default_device_meta():  # the pool path makes no tensor on the implicit device either
        guarded = train_diffusion(data, POOLED, tmp_path / "d.ckpt", device="cpu", log=lambda *a: None)
    assert all(torch.equal(state["model"][k], guarded["model"][k]) for k in state["model"])
    with pytest.raises(DiffusionError, match=r"diffusion.pool_lights is 3 but the geometry points hold 0 pool "
                                             r"lights; rerun presample"):
        train_diffusion(tiny_data(), POOLED, tmp_path / "e.ckpt", log=lambda *a: None)


def test_auto_preset_widens_the_model_with_the_siren_and_checkpoints_the_concrete_name(tmp_path):
    auto = dataclasses.replace(CFG, preset="auto")
    assert [auto.for_siren(w).preset for w in (8, 32, 33, 64, 128)] == ["small", "small", "medium", "medium", "medium"]
    assert CFG.for_siren(128).preset == "tiny"  # a named preset is what the user asked for
    state = train_diffusion(tiny_data(), dataclasses.replace(auto, epochs=1), tmp_path / "e.ckpt", log=lambda *a: None)
    assert state["config"]["preset"] == "small"  # SIREN width 8
    model, *_ = load_sampler(state)  # rebuilt from the stored name
    assert model.n_params() == sum(v.numel() for v in state["model"].values())
    with pytest.raises(ValueError, match=r"diffusion.preset: expected auto or one of .*got 'huge'"):
        DiffusionConfig.from_config({"preset": "huge"})


def test_bfloat16_precision_runs_the_products_in_bfloat16_and_keeps_the_rest_float32(tmp_path):
    """`diffusion.precision: bfloat16`: the forward's linear maps run in bfloat16, the prediction moves from
    float32's by bfloat16 rounding (not more), the loss and the trained weights stay float32, and the checkpoint
    records the choice; a checkpoint from before the key read float32, and a bad value is named."""
    from diffshadow.diffusion.config import build_model
    from diffshadow.diffusion.train import batch_loss, draw_batch

    data = tiny_data()
    std = Standardizer.fit(data.layout, data.weights, CFG.standardize)
    z_all = std.standardize(data.weights).float()
    model = build_model(LAYOUT, CFG)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():  # the output maps start at zero (a new model predicts the mean): give them weights
        for p in model.token_out.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.1)
    seen, attention = [], []
    model.blocks[0].mlp.fc.register_forward_hook(lambda m, i, out: seen.append(out.dtype))
    sdpa = torch.nn.functional.scaled_dot_product_attention

    def recorded(q, k, v, **kw):
        attention.append((q.dtype, k.dtype, v.dtype))
        return sdpa(q, k, v, **kw)

    batch = draw_batch(gen, torch.arange(2), data, None, CFG, Schedule().steps, torch.device("cpu"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.nn.functional, "scaled_dot_product_attention", recorded)
        out = {p: batch_loss(model, std, data, z_all, None, batch, dataclasses.replace(CFG, precision=p), Schedule())
               for p in ("float32", "bfloat16")}
    assert seen == [torch.float32, torch.bfloat16]
    # the attention itself stays float32 on a CPU (its bfloat16 backward there is 6x slower), in both blocks
    assert attention == [(torch.float32,) * 3] * (2 * len(model.blocks))
    pred32, pred16 = out["float32"][3], out["bfloat16"][3]
    assert pred16.dtype == torch.float32 and out["bfloat16"][0].dtype == torch.float32
    apart = (pred16 - pred32).abs().max()
    assert 0 < apart < 0.02 * pred32.abs().max()  # bfloat16 keeps 8 bits: 0.4 % here
    state = train_diffusion(data, dataclasses.replace(CFG, epochs=1, precision="bfloat16"), tmp_path / "b.ckpt",
                            log=lambda *a: None)
    assert state["config"]["precision"] == "bfloat16"
    assert all(v.dtype == torch.float32 for v in state["model"].values())
    old = {**state, "config": {k: v for k, v in state["config"].items() if k != "precision"}}
    assert DiffusionConfig.of_checkpoint(old).precision == "float32"
    with pytest.raises(ValueError, match=r"diffusion.precision: expected auto or one of float32, bfloat16, got 'half'"):
        DiffusionConfig.from_config({"precision": "half"})


def test_precision_auto_is_bfloat16_only_on_a_cpu_that_multiplies_it_natively(tmp_path, monkeypatch):
    """`diffusion.precision: auto` (the default): bfloat16 where `native_bfloat16` says the CPU has bfloat16
    products, float32 on other CPUs and on CUDA; a set precision is kept; the checkpoint and the log say which ran;
    a second training writes the same weights."""
    from diffshadow.diffusion import config as diffusion_config

    auto = dataclasses.replace(CFG, precision="auto")
    assert DiffusionConfig.from_config({}).precision == "auto"
    for native, want in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(diffusion_config, "native_bfloat16", lambda native=native: native)
        assert auto.for_device(torch.device("cpu")).precision == want
        assert auto.for_device(torch.device("cuda")).precision == "float32"
        assert CFG.for_device(torch.device("cpu")).precision == "float32"
        assert dataclasses.replace(CFG, precision="bfloat16").for_device(torch.device("cuda")).precision == "bfloat16"
        msgs = []
        state = train_diffusion(tiny_data(), dataclasses.replace(auto, epochs=1), tmp_path / f"{native}.ckpt",
                                log=msgs.append)
        assert state["config"]["precision"] == want
        assert ("; bfloat16 products" in msgs[0]) is native, msgs[0]
        again = train_diffusion(tiny_data(), dataclasses.replace(auto, epochs=1), tmp_path / f"{native}2.ckpt",
                                log=lambda *a: None)
        assert all(torch.equal(state["model"][k], again["model"][k]) for k in state["model"])  # same seed, same bytes


def test_layer_norm_is_pytorchs_with_the_same_parameters():
    """The model's LayerNorm applies its scale and shift outside PyTorch's fused kernel: the same function (to
    float32 rounding), the same parameter names (older checkpoints load), the same gradients to rounding."""
    from diffshadow.diffusion.model import LayerNorm

    gen = torch.Generator().manual_seed(0)
    ours, theirs = LayerNorm(24), torch.nn.LayerNorm(24)
    with torch.no_grad():
        for p in (ours.weight, ours.bias):
            p.copy_(torch.randn(24, generator=gen))
    theirs.load_state_dict(ours.state_dict())
    x = torch.randn(5, 7, 24, generator=gen)
    assert list(ours.state_dict()) == list(theirs.state_dict()) == ["weight", "bias"]
    a, b = ours(x), theirs(x)
    assert (a - b).abs().max() <= 1e-5
    grad = torch.randn(5, 7, 24, generator=gen)
    a.backward(grad)
    b.backward(grad)
    for p, q in ((ours.weight, theirs.weight), (ours.bias, theirs.bias)):
        assert torch.allclose(p.grad, q.grad, rtol=1e-5, atol=1e-5)


def test_off_a_cpu_the_layer_norm_and_the_loss_mean_are_pytorchs_own_kernels(monkeypatch):
    """The thread-order fixes are a CPU's: elsewhere (CUDA; here the meta device) one fused LayerNorm and one
    mean, as before."""
    from diffshadow.diffusion.model import LayerNorm
    from diffshadow.diffusion.train import mean

    calls = []
    fused = torch.nn.LayerNorm.forward
    monkeypatch.setattr(torch.nn.LayerNorm, "forward", lambda self, x: calls.append(x.device.type) or fused(self, x))
    norm = LayerNorm(8)
    norm(torch.zeros(2, 8))
    assert calls == []
    norm.to("meta")(torch.zeros(2, 8, device="meta"))
    assert calls == ["meta"]
    with torch.device("meta"):
        x = torch.zeros(4, 6)
    monkeypatch.setattr(torch.Tensor, "sum", lambda *a, **k: pytest.fail("a CPU's row sums off a CPU"))
    assert mean(x).shape == ()


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_training_writes_the_same_bytes_on_one_thread_and_on_two(tmp_path, precision):
    """PyTorch's CPU mean of a whole large tensor and its fused LayerNorm's scale and shift gradients add
    per-thread parts; the x0 losses sum row by row and the model's LayerNorm applies its scale and shift outside
    the kernel, so a stage-2 training's threads (the workflow's `-j`) change no byte of its checkpoint. (Before:
    the loss values and every LayerNorm's gradients differed between one thread and two.)"""
    siren = SirenConfig(32, 2)  # a batch of x0 errors (8 x 4,385) over PyTorch's grain: a mean in per-thread parts
    layout = WeightLayout.for_siren(siren)
    gen = torch.Generator().manual_seed(4)
    base = layout.flatten(init_siren(siren, gen))
    n = 16
    data = TrainingData(weights=base + 0.01 * torch.randn(n, layout.n_params, generator=gen),
                        lights=torch.nn.functional.normalize(torch.randn(n, 3, generator=gen)),
                        points=torch.rand(n, 64, 3, generator=gen), values=torch.rand(n, 64, generator=gen),
                        extent=torch.ones(3), layout=layout, siren=siren)
    cfg = dataclasses.replace(CFG, epochs=2, batch_size=8, precision=precision)
    threads = torch.get_num_threads()
    try:
        states = []
        for count in (1, 2):
            torch.set_num_threads(count)
            states.append(train_diffusion(data, cfg, tmp_path / f"{count}.ckpt", log=lambda *a: None))
    finally:
        torch.set_num_threads(threads)
    one, two = states
    for key in ("model", "ema"):
        assert all(torch.equal(one[key][k], two[key][k]) for k in one[key]), key
    moments = [[s[m] for s in st["optimizer"]["state"].values() for m in ("exp_avg", "exp_avg_sq")] for st in states]
    assert all(torch.equal(a, b) for a, b in zip(*moments, strict=True))


def test_the_loss_mean_is_the_mean_and_its_bits_do_not_depend_on_the_threads():
    from diffshadow.diffusion.train import mean

    x = torch.rand(16, 4385, generator=torch.Generator().manual_seed(0)) ** 2
    threads = torch.get_num_threads()
    try:
        got = []
        for count in (1, 2, 3):
            torch.set_num_threads(count)
            got.append(mean(x))
    finally:
        torch.set_num_threads(threads)
    assert got[0].item() == got[1].item() == got[2].item()
    assert abs(got[0].item() - x.double().mean().item()) <= 1e-6 * x.double().mean().item()
    assert mean(torch.full((3, 5), 2.0)).item() == 2.0

"""Stress: the weight-space diffusion on degenerate weights (zero spread, tiny and huge scales), at the
schedule's edges (t = 0, T-1; DDIM with 1..500 steps) and in half precision (hypothesis)."""

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from test_ground_truth_stress import SETTINGS

from diffshadow.diffusion.config import DiffusionConfig, DiffusionError
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.schedule import Schedule
from diffshadow.diffusion.standardize import Standardizer
from diffshadow.diffusion.train import TrainingData, train_diffusion
from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout

pytestmark = pytest.mark.stress

SIREN = SirenConfig(8, 1)
LAYOUT = WeightLayout.for_siren(SIREN)
SCALES = [0.0, 1e-30, 1e-13, 1e-3, 1.0, 1e3, 1e30]
OFFSETS = [0.0, -1e-3, 1.0, 1e6]


@st.composite
def weight_sets(draw):
    """(N, n_params) float32 weights whose tensors each get their own scale and offset (0: zero spread)."""
    n = draw(st.integers(1, 5))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**16)))
    parts = []
    for size in LAYOUT.sizes:
        scale, offset = draw(st.sampled_from(SCALES)), draw(st.sampled_from(OFFSETS))
        parts.append(offset + scale * torch.randn(n, size, generator=gen, dtype=torch.float64))
    return torch.cat(parts, dim=1).float()


@SETTINGS
@given(weight_sets(), st.sampled_from(["token", "param"]))
def test_standardisation_is_finite_and_its_inverse_exact(w, mode):
    std = Standardizer.fit(LAYOUT, w, mode)
    z = std.standardize(w)
    assert torch.isfinite(z).all() and torch.isfinite(std.std).all()
    back = std.destandardize(z).float()
    # Exact, except where a weight is below 2^-28 of its tensor's mean: w - mean then needs more than
    # float64's 53 bits, and the round trip is off by at most 2^-53 |mean| (docs/numerics.md).
    mean = std._expand("mean", w)
    exact = (w.double().abs() >= 2.0**-28 * mean.abs()) | (w == 0)
    assert torch.equal(back[exact], w[exact])
    assert ((back.double() - w.double()).abs() <= 2.0**-52 * mean.abs() + 1e-45).all()


@SETTINGS
@given(weight_sets(), st.sampled_from(["token", "param"]), st.floats(-3, 3))
def test_a_model_error_lands_scaled_to_each_tensors_own_spread(w, mode, eps):
    # Found by this suite: spreads up to 1e-12 got std 1, so an x0 error of eps moved weights that differ
    # by 1e-13 across lights by eps itself. Now zero spread gives back the mean whatever the model says.
    std = Standardizer.fit(LAYOUT, w, mode)
    z = std.standardize(w) + eps
    a, b = std.destandardize(z), std.destandardize(std.standardize(w))
    spread, mean = std._expand("std", w), std._expand("mean", w)
    rounding = 2.0**-50 * (mean.abs() + a.abs() + b.abs())  # float64, relative to what is added and subtracted
    assert ((a - b).abs() <= abs(eps) * spread + rounding).all()
    zero = spread == 0
    assert torch.equal(std.destandardize(z)[:, zero], std._expand("mean", w)[zero].expand(len(w), -1))


def test_non_finite_weights_are_named_by_row():
    w = torch.zeros(4, LAYOUT.n_params)
    w[2, 5] = float("nan")
    w[3, 0] = float("inf")
    with pytest.raises(DiffusionError, match=r"light row\(s\) \[2, 3\] are not finite"):
        Standardizer.fit(LAYOUT, w)


def test_ddim_timesteps_for_every_step_count():
    s = Schedule()
    for n in range(1, s.steps + 1):
        ts = s.ddim_timesteps(n)
        assert len(ts) == n and ts[0] == s.steps - 1 and all(a > b for a, b in zip(ts, ts[1:], strict=False))
        assert n == 1 or ts[-1] == 0


@SETTINGS
@given(st.sampled_from([0.0, 1e-30, 1.0, 1e4]), st.sampled_from([0, 1, 250, 498, 499]))
def test_forward_noising_at_the_edges_is_finite_and_keeps_the_variance(scale, t):
    s = Schedule()
    gen = torch.Generator().manual_seed(t)
    x0 = scale * torch.randn(256, 64, generator=gen)
    noise = torch.randn(256, 64, generator=gen)
    xt = s.q_sample(x0, torch.full((256,), t), noise)
    ab = float(s.alpha_bar[t])
    assert torch.isfinite(xt).all()
    assert torch.allclose(xt, ab**0.5 * x0 + (1 - ab) ** 0.5 * noise, rtol=1e-5, atol=1e-6)


@pytest.fixture(scope="module")
def sampler(tmp_path_factory):
    gen = torch.Generator().manual_seed(2)
    n = 6
    w = torch.randn(n, LAYOUT.n_params, generator=gen) * 0.1
    w[:, :24] = 0.25  # a zero-spread tensor
    w[:, 24:32] *= 1e-14  # a tiny-spread one
    data = TrainingData(weights=w, lights=torch.nn.functional.normalize(torch.randn(n, 3, generator=gen)),
                        points=torch.rand(n, 64, 3, generator=gen), values=torch.rand(n, 64, generator=gen),
                        extent=torch.ones(3), layout=LAYOUT, siren=SIREN)
    cfg = DiffusionConfig.from_config(dict(preset="tiny", epochs=20, batch_size=3, geometry_points=16,
                                           checkpoint_every=20, pool_lights=0, target_gap=0.0))
    state = train_diffusion(data, cfg, tmp_path_factory.mktemp("d") / "d.ckpt", log=lambda *a: None)
    return load_sampler(state)


LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [-1.0, 0.0, 0.0]])


@pytest.mark.parametrize("steps", [1, 2, 50, 500])
@pytest.mark.parametrize("temperature", [0.0, 1.0])
def test_ddim_is_finite_from_1_to_500_steps(sampler, steps, temperature):
    model, std, layout, siren = sampler
    w = generate(model, std, LIGHTS, steps=steps, temperature=temperature, seed=1)
    assert torch.isfinite(w).all()
    assert torch.equal(w[:, :24], torch.full((3, 24), 0.25))  # zero spread: exactly the constant
    assert (w[:, 24:32].abs() < 1e-12).all()  # tiny spread: errors scaled to it
    assert torch.isfinite(BatchedSiren(w, layout, siren.blocks)(torch.rand(3, 32, 3) * 2 - 1)).all()


def test_ddpm_and_stochastic_ddim_are_finite(sampler):
    model, std, layout, _ = sampler
    assert torch.isfinite(generate(model, std, LIGHTS, method="ddpm", seed=2)).all()
    sched = Schedule()
    x = sched.ddim_sample(lambda x, t: model(x, t, torch.as_tensor(LIGHTS, dtype=torch.float32)), (3, layout.n_params),
                          steps=500, eta=1.0, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(x).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_sampling_is_finite_and_close(sampler, dtype):
    model, std, layout, siren = sampler
    full = generate(model, std, LIGHTS, steps=50, temperature=0.0, seed=1)
    half = generate(model, std, LIGHTS, steps=50, temperature=0.0, seed=1, dtype=dtype)
    assert torch.isfinite(half).all()
    assert torch.equal(half[:, :24], full[:, :24])
    # the SIRENs they make agree to the half type's precision, not to float32's
    pts = torch.rand(3, 256, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    a, b = (BatchedSiren(x, layout, siren.blocks)(pts) for x in (full, half))
    tol = 2e-2 if dtype == torch.bfloat16 else 4e-3
    assert (a - b).abs().max() < tol, float((a - b).abs().max())

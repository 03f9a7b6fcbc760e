"""Stress: SIREN fitting on extreme targets, learning rates x10 and x100 and bfloat16 autocast.

The property: a fit either ends with finite weights whose held-out PSNR clears `fit.min_psnr`, or raises
`FitError` naming the lights; it never hands back NaN or a silently diverged SIREN."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from diffshadow.analytic import gaussian_blob
from diffshadow.fit import FitConfig, FitError, check_psnr, evaluate_psnr, fit_sirens
from diffshadow.siren import SirenConfig, WeightLayout, init_siren
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume, load_volume

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.stress

SIREN = SirenConfig(16, 1)
LAYOUT = WeightLayout.for_siren(SIREN)
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
INDEX = [11, 12]


def tf(density: float) -> TransferFunction:
    return TransferFunction.from_config({"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                         "density_scale": density})


def target_volume(kind: str) -> tuple[Volume, TransferFunction]:
    n = 9
    if kind == "constant_one":  # empty volume: g = 1 everywhere
        return Volume(data=np.zeros((n, n, n), np.float32), extent=np.ones(3), name=kind), tf(10.0)
    if kind == "constant_zero":  # opaque everywhere: g ≈ 0 except on the faces facing the light
        return Volume(data=np.ones((n, n, n), np.float32), extent=np.ones(3), name=kind), tf(1e4)
    if kind == "step":  # an opaque slab in the top half: g steps from 1 to 0 across it
        data = np.zeros((n, n, n), np.float32)
        data[n // 2 + 1:] = 1
        return Volume(data=data, extent=np.ones(3), name=kind), tf(1e4)
    return Volume(data=gaussian_blob(n, 0.2), extent=np.ones(3), name=kind), tf(5.0)


def init() -> torch.Tensor:
    return LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0)))


def fit_and_check(vol, t, cfg):
    """What `diffshadow fit-siren` does before it stores a subset."""
    w = fit_sirens(init(), LAYOUT, SIREN, vol, t, LIGHTS, cfg, light_index=INDEX, log=lambda *a: None)
    box, _ = evaluate_psnr(w, LAYOUT, SIREN, vol, t, LIGHTS, n_points=1024, seed=1)
    check_psnr(box, INDEX, cfg.min_psnr, "stress")
    return w, box


# Sharp shadows from a random init in 60 steps at 128 points end at 10-14.5 dB, at every lr and precision here
# (measured); constant shadows reach 19-36 dB. Each case's outcome is fixed, so a check that stops firing, or a
# fit that goes non-finite, fails the test.
HARD = {"step", "blob"}


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
@pytest.mark.parametrize("lr_scale", [1.0, 10.0, 100.0])
@pytest.mark.parametrize("kind", ["constant_one", "constant_zero", "step", "blob"])
def test_a_fit_is_finite_and_good_or_fails_naming_its_lights(kind, lr_scale, precision):
    # every combination (24), enumerated rather than sampled
    vol, t = target_volume(kind)
    cfg = FitConfig.from_config(dict(steps=60, points=128, lr=1e-2 * lr_scale, target="transmittance",
                                     precision=precision, min_psnr=15.0))
    if kind in HARD:
        with pytest.raises(FitError, match=r"held-out PSNR below fit.min_psnr = 15.0 dB "
                           r"\((light 11: 1[0-4]\.\d\d dB, )?light 1[12]: 1[0-4]\.\d\d dB\)"):
            fit_and_check(vol, t, cfg)
        return
    w, box = fit_and_check(vol, t, cfg)
    assert torch.isfinite(w).all()
    assert np.isfinite(box).all() and box.min() >= cfg.min_psnr


def test_a_tenfold_learning_rate_is_caught_not_stored():
    # Found by this suite: on nucleon at 10x fit.lr, fits from the pre-optimised init settled at 6 dB (the
    # targets' own variance) with finite weights, and fit-siren stored them. Now the end-of-fit loss check
    # stops the fit and names the lights, and the floor would have caught it before storing.
    scene = yaml.safe_load((ROOT / "config/scenes/nucleon.yaml").read_text())
    vol = load_volume("bundled:nucleon")
    t = TransferFunction.from_config(scene["transfer_function"])
    siren = SirenConfig(32, 2)
    layout = WeightLayout.for_siren(siren)
    lights = np.array([[0.3, -0.5, 0.8], [0.0, 0.6, 0.8], [-0.8, 0.0, 0.6]])
    quiet = {"log": lambda *a: None}
    pre = fit_sirens(layout.flatten(init_siren(siren, torch.Generator().manual_seed(0))), layout, siren, vol, t,
                     lights[:1], FitConfig.from_config(dict(steps=300, points=2048, chunk=512)), **quiet)[0]
    fine = FitConfig.from_config(dict(steps=150, points=2048, chunk=512))
    good = fit_sirens(pre, layout, siren, vol, t, lights, fine, light_index=[4, 5, 6], **quiet)
    box, _ = evaluate_psnr(good, layout, siren, vol, t, lights, n_points=4096, seed=1)
    check_psnr(box, [4, 5, 6], 20.0, "nucleon at fit.lr")
    with pytest.raises(FitError, match=r"fit diverged: .*light [456]: .*lower fit.lr \(now 0.01\)"):
        fit_sirens(pre, layout, siren, vol, t, lights, dataclasses.replace(fine, lr=1e-2), light_index=[4, 5, 6],
                   **quiet)


def test_an_exact_init_thrown_off_by_a_huge_step_is_reported():
    # an init that is exactly the target (g = 1, zero loss), then lr = 1: the loss ends far above its start
    vol, t = target_volume("constant_one")
    p = LAYOUT.unflatten(init().clone())
    p["last.weight"].zero_()
    p["last.bias"].fill_(1.0)  # ½ (0·x + 1) + ½ = 1 everywhere
    with pytest.raises(FitError, match=r"fit diverged: .*light 11: 1.*e-1\d -> .*lower fit.lr \(now 1.0\)"):
        fit_sirens(LAYOUT.flatten(p), LAYOUT, SIREN, vol, t, LIGHTS,
                   FitConfig.from_config(dict(steps=30, points=256, lr=1.0)),
                   light_index=INDEX, log=lambda *a: None)


def test_the_psnr_floor_names_every_light_below_it():
    with pytest.raises(FitError, match=r"fit_siren subset 3 \(v.zarr\): .*light 5: 6.40 dB, light 7: nan dB"):
        check_psnr(np.array([6.4, 30.0, np.nan]), [5, 6, 7], 20.0, "fit_siren subset 3 (v.zarr)")
    check_psnr(np.array([25.0, 30.0]), [0, 1], 20.0, "ok")


def test_constant_targets_are_fitted_closely():
    # g = 0 is not constant near the faces the light enters through: a step there, hence the lower bar
    for kind, bar in (("constant_one", 30.0), ("constant_zero", 20.0)):
        vol, t = target_volume(kind)
        w, box = fit_and_check(vol, t, FitConfig.from_config(dict(steps=100, points=256, lr=1e-2,
                                                                        target="transmittance")))
        assert box.min() > bar, (kind, box)

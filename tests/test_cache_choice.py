"""`cache: auto` (`diffshadow.caches.choose_cache`): the figures it weighs (its stored SIRENs at the training
lights, its blend at validation lights), and its rule: the smallest stored-SIREN cache that reaches the target on
both, within its tolerance of the best, else the diffusion model."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from diffshadow import caches
from diffshadow.codecs import codec_named
from diffshadow.layout import SirenConfig, WeightLayout
from diffshadow.lights import Triangulation, fibonacci_sphere, inverse_angle_weights, nearest
from diffshadow.siren import init_siren
from diffshadow.store import blend_rows

SIREN = SirenConfig(8, 1)
LAYOUT = WeightLayout.for_siren(SIREN)


class Scored:
    """An EvalTruth stand-in that keeps the SIRENs it is asked to score (and scores them 0 dB)."""

    def __init__(self):
        self.asked = []

    def median_psnr(self, weights, layout, siren, lights):
        self.asked.append(np.array(weights))
        return 0.0


def _store(n: int = 12):
    init = LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0))).numpy()
    w = (init + 0.01 * np.random.default_rng(1).standard_normal((n, LAYOUT.n_params))).astype(np.float32)
    lights = fibonacci_sphere(4 * n)[:n]
    return SimpleNamespace(weights=w, layout=LAYOUT, siren=SIREN), lights


@pytest.mark.parametrize("weighting", ["triangle", "inverse-angle"])
def test_validation_lights_are_answered_by_the_blend_of_their_stored_sirens(weighting):
    store, lights = _store()
    val = Scored()
    val.lights = fibonacci_sphere(400)[:5]
    caches.validation_psnr(store.weights, LAYOUT, SIREN, lights, val, 4, weighting)
    if weighting == "triangle":
        idx, w = Triangulation(lights).weights(val.lights)
    else:
        idx, angles = nearest(lights, val.lights, 4)
        w = inverse_angle_weights(angles)
    assert np.array_equal(val.asked[0], blend_rows(store.weights, idx, w).astype(np.float32))


@pytest.mark.parametrize(("target", "candidates", "choice"), [
    (0.0, ["blend", "fp16", "bf16", "basis-2"], "basis-2"),  # everything passes: the fewest bytes
    (99.0, ["blend", "fp16", "bf16", "basis-2"], "blend"),  # only the exact store passes
    (75.0, ["blend", "fp16", "bf16"], "fp16"),  # bf16 as small but under the target (8 bits of mantissa)
    (99.0, ["fp16", "bf16", "basis-2"], "diffusion"),  # none passes: train the model
])
def test_auto_takes_the_smallest_cache_that_reaches_the_target_else_the_model(monkeypatch, target, candidates,
                                                                               choice):
    store, lights = _store()

    def fidelity(weights, layout, siren, train, val, k, weighting):
        """PSNR of the decoded store against the fp32 one (inf when exact): a figure each codec earns."""
        mse = float(np.mean((np.asarray(weights, np.float64) - store.weights) ** 2))
        return float("inf") if mse == 0 else 10 * np.log10(float(np.abs(store.weights).max()) ** 2 / mse)

    monkeypatch.setattr(caches, "validation_psnr", fidelity)  # decisive, with the training lights' figure
    val = SimpleNamespace(lights=np.zeros((3, 3)))
    seen = SimpleNamespace(median_psnr=lambda w, layout, siren, lights: 100.0)  # every store passes there
    out = caches.choose_cache(store, seen, val, lights, blend_k=4, weighting="triangle", target_psnr=target,
                              candidates=candidates, log=lambda *a: None)
    assert out["choice"] == choice and out["why"].startswith(f"{choice}:")
    assert [r["cache"] for r in out["candidates"]] == candidates  # every candidate weighed, in order


def test_auto_needs_the_target_on_the_training_lights_too(monkeypatch):
    """A codec that answers new lights well enough but its own stored lights worse does not serve."""
    store, lights = _store()
    monkeypatch.setattr(caches, "validation_psnr", lambda *a: 40.0)
    exact = store.weights

    def seen(w, layout, siren, train):  # the exact store 50 dB, every lossy one 30
        return 50.0 if np.array_equal(w, exact) else 30.0

    out = caches.choose_cache(store, SimpleNamespace(median_psnr=seen), SimpleNamespace(lights=np.zeros((3, 3))),
                              lights, blend_k=4, weighting="triangle", target_psnr=35.0,
                              candidates=["blend", "fp16", "basis-2"], log=lambda *a: None)
    assert out["choice"] == "blend" and "30.00 and 40.00" not in out["why"]


def test_auto_gives_up_at_most_its_tolerance_under_the_best_cache(monkeypatch):
    """The target is a floor: a codec over it but far under the stored SIRENs' quality does not serve, and the
    reason names it; with no tolerance the smallest over the floor serves."""
    store, lights = _store()
    figures = {"blend": 48.0, "fp16": 47.8, "basis-2": 38.0}  # as nucleon: fp16 ~0.2 dB under, a basis ~10

    def scored(w, *a):
        for name in figures:  # each candidate's decoded weights, recognised by their codec's own encoding
            if np.array_equal(w, caches.encoded(store.weights, LAYOUT, name)[0]):
                return figures[name]
        raise AssertionError("weights of no candidate")

    monkeypatch.setattr(caches, "validation_psnr", scored)
    seen = SimpleNamespace(median_psnr=scored)

    def choose(tolerance):
        return caches.choose_cache(store, seen, SimpleNamespace(lights=np.zeros((3, 3))), lights, blend_k=4,
                                   weighting="triangle", target_psnr=36.0, tolerance=tolerance,
                                   candidates=list(figures), log=lambda *a: None)

    out = choose(1.0)
    assert out["choice"] == "fp16" and out["tolerance"] == 1.0
    assert "within 1 dB of the best (blend, 48.00 dB)" in out["why"]
    assert "more than 1 dB under the best: basis-2 (38.00 dB)" in out["why"]
    assert choose(float("inf"))["choice"] == "basis-2"  # the floor alone: the fewest bytes over 36 dB
    assert choose(0.0)["choice"] == "blend"


def test_codec_names_are_checked():
    assert codec_named("basis-16").k == 16 and codec_named("bf16").name == "bf16"
    for bad in ("basis-0", "basis-x", "int8", "blend"):
        with pytest.raises(ValueError, match=f"expected blend, fp16, bf16 or basis-<k>, got '{bad}'"):
            codec_named(bad)
